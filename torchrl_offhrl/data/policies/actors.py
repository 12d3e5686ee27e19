"""What a behaviour-policy run makes: the actor's format, the training algorithms' defaults, picking a level's checkpoint.

D4RL's protocol: "expert" is a fully trained SAC policy, "medium" a checkpoint
of the same run stopped at about a third of the expert's return. The run
(:func:`torchrl_offhrl.recipes.behaviour.train_behaviour`, ``scripts/train_behaviour.py``)
keeps every evaluated actor, in the format of :func:`make_behaviour_actor`;
:func:`pick_checkpoint` picks the levels from its records afterwards. The
shipped policies (:mod:`torchrl_offhrl.data.policies`) are read back in that
format, so it lives here in the data layer; the training itself is an agent
(:class:`~torchrl_offhrl.agents.behaviour.BehaviourLearner`) and a loop above it.
"""
from __future__ import annotations

import math

from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn

from ...nets import mlp, tanh_gaussian_actor

__all__ = ["ALGORITHMS", "algorithm_defaults", "make_behaviour_actor", "pick_checkpoint"]


def make_behaviour_actor(obs_dim: int, act_dim: int, low, high, hidden=(256, 256)):
    """SAC's tanh-Gaussian actor: ``observation`` -> ``action`` (+ ``action_log_prob``).

    Call it inside ``torchrl.envs.utils.set_exploration_type`` to choose
    between sampling (``RANDOM``, D4RL's stochastic data) and the mean
    (``DETERMINISTIC``).

    Examples:
        >>> import torch
        >>> actor = make_behaviour_actor(3, 2, -torch.ones(2), torch.ones(2), hidden=(8,))
        >>> from tensordict import TensorDict
        >>> actor(TensorDict(observation=torch.zeros(4, 3), batch_size=[4]))["action"].shape
        torch.Size([4, 2])
    """
    net = nn.Sequential(mlp(obs_dim, 2 * act_dim, hidden, activation="relu"), NormalParamExtractor())
    return tanh_gaussian_actor(TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]), low, high)


#: Defaults of each algorithm of :func:`~torchrl_offhrl.recipes.behaviour.train_behaviour` (the published ones,
#: except CrossQ's critic width: 256 instead of 2048, for CPU budgets).
ALGORITHMS = {
    "sac": {"lr": 3e-4, "betas": (0.9, 0.999), "policy_delay": 1, "target_critics": True, "loss": "SAC (torchrl SACLoss)"},
    "crossq": {"lr": 1e-3, "betas": (0.5, 0.999), "policy_delay": 3, "target_critics": False, "loss": "CrossQ (torchrl CrossQLoss)"},
}


def algorithm_defaults(name: str) -> dict:
    """The defaults of a behaviour-training algorithm of :data:`ALGORITHMS` (a clear error for an unknown name)."""
    if name not in ALGORITHMS:
        raise ValueError(f"train_behaviour: algorithm must be one of {sorted(ALGORITHMS)}, got {name!r}.")
    return ALGORITHMS[name]


def pick_checkpoint(records: list[dict], target: float | None = None, key: str = "stochastic") -> dict:
    """The evaluation record for a level: the best return (``target=None``) or the return closest to ``target``."""
    if not records:
        raise ValueError("pick_checkpoint: no evaluation records")
    if target is None:
        return max(records, key=lambda r: r[key]["mean"])
    return min(records, key=lambda r: abs(r[key]["mean"] - target) if math.isfinite(r[key]["mean"]) else float("inf"))
