"""Known termination functions of the real tasks, pluggable by env id.

Each function maps next observations ``[..., obs_dim]`` to a boolean
``[...]`` that is ``True`` where the real env would terminate.
"""
from __future__ import annotations

import logging
from typing import Callable

import torch

__all__ = ["hopper_termination", "never_terminates", "termination_fn_for", "TERMINATION_FNS"]

log = logging.getLogger(__name__)


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
