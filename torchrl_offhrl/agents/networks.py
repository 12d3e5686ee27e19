"""The networks the agents share: tanh-Gaussian and deterministic actors, Q-networks, on an env's action box.

Each reads ``observation`` (normalised by the dataset's statistics, built
into the network) and, on a goal-conditioned task, its goal.
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["action_box", "deterministic_actor", "gaussian_actor", "q_network", "tanh_mean_gaussian_actor"]


def action_box(env, key: str) -> tuple[int, torch.Tensor, torch.Tensor]:
    """``(dim, low, high)`` of the action ``key`` of ``env`` (one env's box when the env is batched)."""
    spec = env.full_action_spec[key] if key in env.full_action_spec.keys(True, True) else env.action_spec
    dim = spec.shape[-1]
    low = spec.space.low.reshape(-1, dim)[0].float()
    high = spec.space.high.reshape(-1, dim)[0].float()
    return dim, low, high


def _inputs(env, goal_key: str | None) -> tuple[list[str], int]:
    """The actor's in-keys (``observation``, and the goal if any) and the goal's size (not normalised: an extra input)."""
    if goal_key is None:
        return ["observation"], 0
    return ["observation", goal_key], env.observation_spec[goal_key].shape[-1]


def gaussian_actor(env, action_key: str, hidden_sizes, obs_loc=None, obs_scale=None, default_scale: float = 1.0, scale_lb: float = 0.1,
                   goal_key: str | None = None):
    """A tanh-Gaussian :class:`~torchrl.modules.ProbabilisticActor` on ``env``'s action box, state-dependent scale.

    The scale is ``biased_softplus_<default_scale>`` of the network's output,
    at least ``scale_lb`` (TorchRL's IQL / CQL sota scripts: 1.0 and 0.1).
    With ``goal_key`` the actor also reads that goal (goal-conditioned tasks).
    """
    from tensordict.nn import NormalParamExtractor, TensorDictModule

    from ..nets import NormalizedMLP, tanh_gaussian_actor

    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim, low, high = action_box(env, action_key)
    in_keys, goal_dim = _inputs(env, goal_key)
    net = nn.Sequential(
        NormalizedMLP(obs_dim, goal_dim, 2 * act_dim, list(hidden_sizes), "relu", obs_loc, obs_scale),
        NormalParamExtractor(scale_mapping=f"biased_softplus_{float(default_scale)}", scale_lb=float(scale_lb)),
    )
    return tanh_gaussian_actor(TensorDictModule(net, in_keys=in_keys, out_keys=["loc", "scale"]), low, high, action_key)


def tanh_mean_gaussian_actor(env, action_key: str, hidden_sizes, obs_loc=None, obs_scale=None, log_std_min: float = -5.0):
    """A Gaussian actor whose mean is squashed into the box and whose scale is one learned number per action dimension.

    The IQL paper's actor for the D4RL locomotion tasks (its official
    ``learner.py``: ``NormalTanhPolicy(state_dependent_std=False,
    tanh_squash_distribution=False, log_std_min=-5)``): the distribution is a
    plain Normal, not squashed, so the log-likelihood of a dataset action at
    the edge of the box stays finite and its gradient bounded (a tanh-Gaussian
    takes ``atanh`` of it). Its deterministic action is the mean, inside the
    box; a sample is projected into the box (``safe``). Built from TorchRL's
    ``TanhModule``, TensorDict's ``AddStateIndependentNormalScale`` (scale
    ``exp(log_std)``, at least ``exp(log_std_min)``, log-std starting at 0) and
    ``IndependentNormal``.
    """
    import math

    from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule, TensorDictSequential
    from torchrl.data import Bounded
    from torchrl.modules import IndependentNormal, ProbabilisticActor

    act_dim, low, high = action_box(env, action_key)
    mean = TensorDictSequential(
        deterministic_actor(env, action_key, hidden_sizes, obs_loc, obs_scale, out_key="loc_squashed"),
        TensorDictModule(AddStateIndependentNormalScale(act_dim, scale_mapping="exp", scale_lb=math.exp(log_std_min)),
                         in_keys=["loc_squashed"], out_keys=["loc", "scale"]),
    )
    box = Bounded(low=low, high=high, shape=(act_dim,))
    return ProbabilisticActor(mean, in_keys=["loc", "scale"], out_keys=[action_key], distribution_class=IndependentNormal,
                              spec=box, safe=True, return_log_prob=True)


def deterministic_actor(env, action_key: str, hidden_sizes, obs_loc=None, obs_scale=None, goal_key: str | None = None,
                        out_key: str | None = None):
    """A deterministic actor: an MLP squashed into ``env``'s action box by TorchRL's ``TanhModule`` (TD3+BC, BC); with ``goal_key``, also on that goal.

    It writes ``out_key`` (default ``action_key``): another key makes it the
    squashed mean of a stochastic actor (:func:`tanh_mean_gaussian_actor`).
    """
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.modules import TanhModule

    from ..nets import NormalizedMLP

    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim, low, high = action_box(env, action_key)
    in_keys, goal_dim = _inputs(env, goal_key)
    net = TensorDictModule(NormalizedMLP(obs_dim, goal_dim, act_dim, list(hidden_sizes), "relu", obs_loc, obs_scale), in_keys=in_keys, out_keys=["param"])
    return TensorDictSequential(net, TanhModule(in_keys=["param"], out_keys=[out_key or action_key], low=low, high=high))


def q_network(env, action_key: str, hidden_sizes, obs_loc=None, obs_scale=None):
    """``Q(observation, action)`` as a TorchRL ``ValueOperator`` writing ``state_action_value``."""
    from torchrl.modules import ValueOperator

    from ..nets import NormalizedMLP

    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim, _, _ = action_box(env, action_key)
    return ValueOperator(NormalizedMLP(obs_dim, act_dim, 1, list(hidden_sizes), "relu", obs_loc, obs_scale),
                         in_keys=["observation", action_key], out_keys=["state_action_value"])
