"""The envs and dataset levels the project knows by name (below every other layer).

Reference scores live in :mod:`torchrl_offhrl.scores`, termination functions
of the model env in :mod:`torchrl_offhrl.envs.termination`.
"""
from __future__ import annotations

import re

__all__ = ["ENV_IDS", "LEVELS", "resolve_env"]

#: Short dataset names of the envs and their Gymnasium ids.
ENV_IDS: dict[str, str] = {"hopper": "Hopper-v5", "halfcheetah": "HalfCheetah-v5", "blockstack2": "BlockStack2-v0", "blockstack3": "BlockStack3-v0"}
#: Dataset levels of D4RL's protocol.
LEVELS = ("random", "medium", "expert", "medium-expert")


def resolve_env(env_id_or_short: str) -> tuple[str, str]:
    """``(env_id, short)`` for a short name (``"hopper"``) or a full Gymnasium id (``"Hopper-v5"``).

    Examples:
        >>> resolve_env("hopper")
        ('Hopper-v5', 'hopper')
        >>> resolve_env("HalfCheetah-v5")
        ('HalfCheetah-v5', 'halfcheetah')
    """
    key = env_id_or_short.lower()
    if key in ENV_IDS:
        return ENV_IDS[key], key
    m = re.match(r"^(?:.*/)?([A-Za-z0-9_]+)-v\d+$", env_id_or_short)
    if m:
        return env_id_or_short, m.group(1).lower()
    raise ValueError(
        f"{env_id_or_short!r}: not a known short name {sorted(ENV_IDS)} nor a Gymnasium id "
        f"like 'Hopper-v5'."
    )
