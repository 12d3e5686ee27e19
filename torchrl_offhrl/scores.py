"""Reference scores and D4RL score normalisation."""
from __future__ import annotations

import re

__all__ = ["D4RL_REF", "PUBLISHED_SCORES", "d4rl_reference", "normalized_score", "return_for_score"]

#: D4RL reference returns (the same for v0/v1/v2 and every dataset type).
D4RL_REF: dict[str, tuple[float, float]] = {
    "hopper": (-20.272305, 3234.3),
    "halfcheetah": (-280.178953, 12135.0),
}


#: Published D4RL-normalised scores, measured on D4RL's own datasets (not ours), by method and ``<env>-<dataset>``:
#: the paper's Table I (Offline MOC; MOReL, MOPO from their papers; CQL as the paper quotes it) and CORL's /
#: OfflineRL-Kit's re-runs (IQL, TD3+BC: last evaluation; COMBO).
PUBLISHED_SCORES: dict[str, dict[str, float]] = {
    "Offline MOC (the paper)": {"hopper-medium": 76.8, "hopper-medium-expert": 107.4, "halfcheetah-medium": 45.04, "halfcheetah-medium-expert": 90.6},
    "MOReL (its paper)": {"hopper-medium": 95.4, "hopper-medium-expert": 108.7, "halfcheetah-medium": 42.1, "halfcheetah-medium-expert": 53.3},
    "MOPO (its paper)": {"hopper-medium": 28.0, "hopper-medium-expert": 23.7, "halfcheetah-medium": 42.3, "halfcheetah-medium-expert": 63.3},
    "CQL (as quoted by the paper)": {"hopper-medium": 86.6, "hopper-medium-expert": 111.0, "halfcheetah-medium": 44.4,
                                     "halfcheetah-medium-expert": 62.4},
    "IQL (CORL re-run, last)": {"hopper-medium": 67.5, "hopper-medium-expert": 107.4, "halfcheetah-medium": 48.3, "halfcheetah-medium-expert": 94.7},
    "TD3+BC (CORL re-run, last)": {"hopper-medium": 60.4, "hopper-medium-expert": 101.2, "halfcheetah-medium": 48.1,
                                   "halfcheetah-medium-expert": 90.8},
    "COMBO (OfflineRL-Kit re-run)": {"hopper-medium": 84.7, "hopper-medium-expert": 108.8, "halfcheetah-medium": 71.9,
                                     "halfcheetah-medium-expert": 98.2},
}


def _key(env_id: str) -> str | None:
    # "Hopper-v5", "hopper-medium-v2", "mujoco/hopper/medium-v0" -> "hopper"
    for token in re.split(r"[/\-_]", env_id.lower()):
        if token in D4RL_REF:
            return token
    return None


def d4rl_reference(env_id: str) -> tuple[float, float] | None:
    """D4RL's ``(REF_MIN, REF_MAX)`` returns for an env or dataset id; ``None`` when it has none.

    Examples:
        >>> d4rl_reference("Hopper-v5")
        (-20.272305, 3234.3)
        >>> d4rl_reference("Toy-v0") is None
        True
    """
    return D4RL_REF.get(_key(env_id) or "")


def normalized_score(env_id: str, ret: float, ref: tuple[float, float] | None = None) -> float | None:
    """``100 * (R - REF_MIN) / (REF_MAX - REF_MIN)``; ``None`` for an env without references.

    ``ref`` overrides the D4RL constants, e.g. with a generated dataset's own
    random and expert returns.

    Examples:
        >>> round(normalized_score("Hopper-v5", 3234.3), 6)
        100.0
        >>> round(normalized_score("hopper-medium-v2", -20.272305), 6)
        0.0
        >>> round(normalized_score("HalfCheetah-v5", 4770.0), 1)
        40.7
        >>> round(normalized_score("mujoco/halfcheetah/medium-v0", 12135.0), 6)
        100.0
        >>> normalized_score("Toy-v0", 1.0) is None
        True
    """
    if ref is None:
        ref = d4rl_reference(env_id)
        if ref is None:
            return None
    lo, hi = ref
    return 100.0 * (ret - lo) / (hi - lo)


def return_for_score(env_id: str, score: float, ref: tuple[float, float] | None = None) -> float | None:
    """The return whose normalised score is ``score`` (the inverse of :func:`normalized_score`).

    Examples:
        >>> round(return_for_score("HalfCheetah-v5", 85.0), 1)  # D4RL's expert bar
        10272.7
        >>> round(return_for_score("Hopper-v5", 100.0), 6)
        3234.3
    """
    if ref is None:
        ref = d4rl_reference(env_id)
        if ref is None:
            return None
    lo, hi = ref
    return lo + score / 100.0 * (hi - lo)
