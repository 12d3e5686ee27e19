"""Environments: the pessimistic model env, the latent action transform, terminations."""
from .calibration import CalibrationReport, calibrate_threshold, dataset_discrepancy
from .latent import LatentActionTransform
from .pessimistic import PessimisticModelEnv
from .termination import TERMINATION_FNS, hopper_termination, never_terminates, termination_fn_for

__all__ = [
    "CalibrationReport",
    "LatentActionTransform",
    "PessimisticModelEnv",
    "TERMINATION_FNS",
    "calibrate_threshold",
    "dataset_discrepancy",
    "hopper_termination",
    "never_terminates",
    "termination_fn_for",
]
