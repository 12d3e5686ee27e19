"""The real tasks as the model env and the transfer setting need them: where episodes end, and which reward is paid.

**Terminal states.** A task's termination function maps next observations
``[..., obs_dim]`` to a boolean ``[...]`` that is ``True`` where the real
env would end the episode (:data:`TERMINATION_FNS`, by env id:
:func:`termination_fn_for`); the pessimistic model env ends its episodes
there too. (The option-critic's *termination head*, when an option ends, is
another thing: :class:`~torchrl_offhrl.modules.OptionHeads`.)

**Tasks of the transfer setting**: the same MuJoCo body, another reward.
The paper's transfer setting (Section "Transfer setting") trains offline on
data of the forward-running task, then fine-tunes online on a task that
rewards running *backwards*. Gymnasium's v5 locomotion envs expose the
weight of the forward-velocity term of their reward
(``forward_reward_weight``), so a task is a set of ``gymnasium.make``
keyword arguments: ``backward`` flips the sign of that weight, and keeps
its size, the healthy reward and the control cost, so returns of the two
tasks are on the same scale.
"""
from __future__ import annotations

import logging
from typing import Callable

import torch

from ..data import make_gym_env

__all__ = [
    "TASKS", "TERMINATION_FNS", "hopper_termination", "make_task_env", "never_terminates", "task_kwargs", "termination_fn_for",
    "walker2d_termination",
]

log = logging.getLogger(__name__)

#: task name -> ``gymnasium.make`` keyword arguments (Hopper-v5, HalfCheetah-v5, Walker2d-v5, Ant-v5, ...)
TASKS: dict[str, dict] = {
    "forward": {},
    "backward": {"forward_reward_weight": -1.0},
}


def task_kwargs(task: str) -> dict:
    """The ``gymnasium.make`` keyword arguments of a named task.

    Examples:
        >>> task_kwargs("backward")
        {'forward_reward_weight': -1.0}
        >>> task_kwargs("sideways")
        Traceback (most recent call last):
        ...
        ValueError: unknown task 'sideways': the tasks are 'forward', 'backward' (torchrl_offhrl.envs.TASKS)
    """
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}: the tasks are {', '.join(map(repr, TASKS))} (torchrl_offhrl.envs.TASKS)")
    return dict(TASKS[task])


def make_task_env(env_id: str, task: str = "forward", num_envs: int = 1, device="cpu", **gym_kwargs):
    """The batched real env of ``env_id`` with the reward of ``task`` (:func:`~torchrl_offhrl.data.make_gym_env`).

    Raises ``ValueError`` naming the env and the task when the env has no
    such reward weight (e.g. ``backward`` on an env without a
    forward-velocity term).
    """
    kwargs = {**task_kwargs(task), **gym_kwargs}
    try:
        return make_gym_env(env_id, num_envs=num_envs, device=device, **kwargs)
    except TypeError as err:
        if not task_kwargs(task):
            raise
        raise ValueError(f"{env_id} does not take the reward arguments {task_kwargs(task)} of task {task!r} ({err}); "
                         "the locomotion envs of Gymnasium v5 (Hopper-v5, HalfCheetah-v5, Walker2d-v5, Ant-v5) do") from None


def hopper_termination(
    next_obs: torch.Tensor,
    healthy_z_range: tuple[float, float] = (0.7, float("inf")),
    healthy_angle_range: tuple[float, float] = (-0.2, 0.2),
    healthy_state_range: tuple[float, float] = (-100.0, 100.0),
) -> torch.Tensor:
    """Gymnasium ``Hopper-v5``'s "unhealthy" check on its default observation.

    Observation layout (positions without x): ``[z, angle, ...]``; healthy
    means ``obs[1:]`` inside ``healthy_state_range``, ``z`` inside
    ``healthy_z_range`` and ``angle`` inside ``healthy_angle_range`` (all
    open intervals), exactly as ``Hopper.is_healthy``.

    Examples:
        >>> import torch
        >>> obs = torch.zeros(3, 11)
        >>> obs[:, 0] = torch.tensor([1.25, 0.5, 1.25])
        >>> obs[2, 1] = 0.3
        >>> hopper_termination(obs).tolist()
        [False, True, True]
    """
    z, angle = next_obs[..., 0], next_obs[..., 1]
    state = next_obs[..., 1:]
    healthy_state = ((state > healthy_state_range[0]) & (state < healthy_state_range[1])).all(-1)
    healthy_z = (z > healthy_z_range[0]) & (z < healthy_z_range[1])
    healthy_angle = (angle > healthy_angle_range[0]) & (angle < healthy_angle_range[1])
    return ~(healthy_state & healthy_z & healthy_angle)


def walker2d_termination(next_obs: torch.Tensor) -> torch.Tensor:
    """Gymnasium ``Walker2d-v5``: healthy iff ``0.8 < z < 2`` and ``-1 < angle < 1``."""
    z, angle = next_obs[..., 0], next_obs[..., 1]
    return ~((z > 0.8) & (z < 2.0) & (angle > -1.0) & (angle < 1.0))


def never_terminates(next_obs: torch.Tensor) -> torch.Tensor:
    """HalfCheetah and other tasks without termination."""
    return torch.zeros(next_obs.shape[:-1], dtype=torch.bool, device=next_obs.device)


#: Known terminations by env-name prefix (the part of the id before ``-v``).
TERMINATION_FNS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "Hopper": hopper_termination,
    "HalfCheetah": never_terminates,
    "Walker2d": walker2d_termination,
    "Toy": never_terminates,  # torchrl_offhrl.data.make_toy_dataset
}


def termination_fn_for(env_id: str | None) -> Callable[[torch.Tensor], torch.Tensor]:
    """The known termination of ``env_id`` (e.g. ``"Hopper-v5"``).

    Unknown ids fall back to :func:`never_terminates`, with a warning: the
    model env then ends episodes only by pessimism and the horizon.
    """
    name = (env_id or "").split("/")[-1].split("-v")[0]
    fn = TERMINATION_FNS.get(name)
    if fn is None:
        log.warning(
            "No known termination function for env id %r; the model env will terminate only on "
            "model disagreement. Pass termination_fn=... to PessimisticModelEnv to set one.",
            env_id,
        )
        return never_terminates
    return fn
