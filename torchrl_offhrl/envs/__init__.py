"""Environments: the pessimistic model env, the latent action transform, terminations, the transfer tasks, block stacking."""
from .goal_model import BlockStackModelEnv, SubGoalTracker
from .latent import DEFAULT_LATENT_BOUND, AffineActionMap, LatentActionTransform
from .pessimistic import CalibrationReport, PessimisticModelEnv, calibrate_threshold, dataset_discrepancy
from .tasks import TASKS, TERMINATION_FNS, hopper_termination, make_task_env, never_terminates, task_kwargs, termination_fn_for

__all__ = [
    "BlockStackModelEnv",
    "AffineActionMap",
    "DEFAULT_LATENT_BOUND",
    "CalibrationReport",
    "LatentActionTransform",
    "PessimisticModelEnv",
    "SubGoalTracker",
    "TASKS",
    "TERMINATION_FNS",
    "calibrate_threshold",
    "dataset_discrepancy",
    "hopper_termination",
    "make_task_env",
    "never_terminates",
    "task_kwargs",
    "termination_fn_for",
]
