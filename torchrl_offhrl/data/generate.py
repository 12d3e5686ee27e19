"""Generate D4RL-style offline datasets in the Gymnasium v5 MuJoCo envs.

D4RL's datasets cannot be downloaded here, and Minari's replacements ship no
reference scores, so the project regenerates them with D4RL's protocol:

* ``random``: actions drawn uniformly from the action box;
* ``medium``: a SAC policy stopped at about a third of the expert's return,
  sampled stochastically (the shipped ``<env>-medium`` policy);
* ``expert``: the fully trained SAC policy, sampled stochastically (the
  shipped ``<env>-expert`` policy);
* ``medium-expert``: the medium and the expert datasets concatenated.

Each dataset records the returns of a random and of the expert policy
measured at generation time (``ref_min_return`` / ``ref_max_return``), to
normalise scores on the v5 envs besides D4RL's own constants.
This module is the protocol alone; naming and caching (``"hopper-medium-100k"``
-> a cached HDF5 file) live in :mod:`torchrl_offhrl.data.catalog`.
"""
from __future__ import annotations

import os
from typing import Any

from tensordict.nn import TensorDictModuleBase

from ..registry import LEVELS, resolve_env
from ..rollouts import evaluate_policy
from ..scores import normalized_score
from ..utils import one_thread
from .collect import collect_dataset, combine_levels, make_gym_env
from .dataset import OfflineDataset
from .policies import PolicyNotFoundError, list_policies, load_policy

__all__ = ["SampledPolicy", "generate_dataset", "medium_expert_from_parts"]

#: Offset between a dataset's seed and the seed of its reference evaluations.
REF_SEED_OFFSET = 100_003



class SampledPolicy(TensorDictModuleBase):
    """Runs a stochastic actor under ``ExplorationType.RANDOM``, whatever the caller set.

    D4RL's medium and expert data are *sampled* from the SAC policy, not taken
    from its mean. Wrapping the actor makes that independent of the
    exploration type a collector or a caller happens to use.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> from torchrl_offhrl.data.policies.actors import make_behaviour_actor
        >>> actor = make_behaviour_actor(3, 2, -torch.ones(2), torch.ones(2), hidden=(8,))
        >>> td = TensorDict(observation=torch.zeros(5, 3), batch_size=[5])
        >>> with set_exploration_type(ExplorationType.DETERMINISTIC):
        ...     a = SampledPolicy(actor)(td.clone())["action"]
        ...     mean = actor(td.clone())["action"]
        >>> bool((a != mean).all())
        True
    """

    def __init__(self, actor: TensorDictModuleBase):
        super().__init__()
        self.actor = actor
        self.in_keys = list(actor.in_keys)
        self.out_keys = list(actor.out_keys)

    def forward(self, tensordict):
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        with set_exploration_type(ExplorationType.RANDOM):
            return self.actor(tensordict)


# ---------------------------------------------------------------- generation
def generate_dataset(
    env_id_or_short: str,
    level: str,
    num_transitions: int = 1_000_000,
    seed: int = 0,
    num_envs: int = 8,
    progress: bool = True,
    policy: Any = None,
    ref_episodes: int = 10,
) -> OfflineDataset:
    """Generate a dataset of ``level`` in an env, following D4RL's protocol.

    Args:
        env_id_or_short: ``"hopper"``, ``"halfcheetah"`` or a Gymnasium id.
        level: ``"random"``, ``"medium"``, ``"expert"`` or ``"medium-expert"``.
        num_transitions: transitions per part (``medium-expert`` holds twice
            as many: medium, then expert), rounded up to a multiple of
            ``num_envs``.
        seed: seeds the envs and the action sampling; the same seed (and
            ``num_envs``) gives identical tensors. ``medium-expert``'s parts
            use the same seed as the ``medium`` and ``expert`` datasets, so it
            is exactly their concatenation.
        num_envs: environments stepped side by side.
        progress: show progress bars.
        policy: ``None`` uses the shipped ``<env>-<level>`` policy. Otherwise
            the path of a ``.pt`` with its ``.json`` card, a shipped name, or
            an actor (a TensorDict module writing ``"action"``); for
            ``medium-expert`` a pair ``(medium, expert)`` of those. The
            policy is always sampled (see :class:`SampledPolicy`).
        ref_episodes: episodes of the reference evaluations (D4RL-style
            ``ref_min_return``: uniform random actions; ``ref_max_return``:
            the expert policy, sampled); ``0`` skips them (recorded as null).

    Returns:
        OfflineDataset whose metadata holds ``env_id``, ``level``,
        ``dataset`` (``"<env>-<level>"``), ``policy`` and ``policy_card``,
        ``seed``, ``versions``, ``returns`` (mean/std/min/max/episodes of
        the complete episodes in the data, and the count of ``unfinished``
        ones: those the budget cut short, listed in ``unfinished_episodes``), ``ref_min_return``,
        ``ref_max_return``, ``ref_note`` and ``score`` (the mean return
        normalised with D4RL's constants and with the references).

    Raises:
        PolicyNotFoundError: no shipped policy for the level (the message
            says how to make one).
    """
    env_id, short = resolve_env(env_id_or_short)
    if level not in LEVELS:
        raise ValueError(f"generate_dataset: level must be one of {LEVELS}, got {level!r}.")
    with one_thread():
        return _generate(env_id, short, level, num_transitions, seed, num_envs, progress, policy, ref_episodes)


def _generate(env_id, short, level, num_transitions, seed, num_envs, progress, policy, ref_episodes):
    if level == "random":
        if policy is not None:
            raise ValueError("generate_dataset: level 'random' draws uniform actions; it takes no policy.")
        ds = collect_dataset(env_id, num_transitions, None, num_envs=num_envs, seed=seed, progress=progress,
                             metadata={"policy": "uniform-random", "policy_card": None})
        expert = _optional_expert(short)
    elif level in ("medium", "expert"):
        actor, card = _get_policy(policy, short, level, env_id)
        ds = _collect_with(env_id, actor, card, num_transitions, num_envs, seed, progress)
        expert = (actor, card) if level == "expert" else _optional_expert(short)
    else:
        if policy is None:
            policy = (None, None)
        if not (isinstance(policy, (tuple, list)) and len(policy) == 2):
            raise ValueError("generate_dataset: 'medium-expert' takes policy=(medium, expert), or None.")
        medium = _get_policy(policy[0], short, "medium", env_id)
        expert = _get_policy(policy[1], short, "expert", env_id)
        parts = [_collect_with(env_id, *p, num_transitions, num_envs, seed, progress) for p in (medium, expert)]
        ds = combine_levels(parts, seed)
    refs = _reference_returns(env_id, short, expert, ref_episodes, seed)
    _finish_metadata(ds, env_id, short, level, seed, num_transitions, refs)
    return ds


def _get_policy(policy: Any, short: str, level: str, env_id: str):
    if policy is None:
        actor, card = load_policy(f"{short}-{level}")
    elif isinstance(policy, (str, os.PathLike)):
        actor, card = load_policy(policy)
    elif isinstance(policy, TensorDictModuleBase):
        actor, card = policy, {"name": "user-given", "type": type(policy).__name__, "level": level}
    else:
        raise TypeError(
            f"generate_dataset: policy must be None, a shipped name, a path to a .pt file or a "
            f"TensorDict module; got {type(policy).__name__}."
        )
    if card.get("env_id") not in (None, env_id):
        raise ValueError(
            f"policy {card.get('name')!r} was trained in {card['env_id']}, not in {env_id}."
        )
    return actor, card


def _optional_expert(short: str):
    try:
        return load_policy(f"{short}-expert")
    except PolicyNotFoundError:
        return None


def _collect_with(env_id, actor, card, n, num_envs, seed, progress) -> OfflineDataset:
    meta = {"policy": card.get("name", "user-given"), "policy_card": card}
    return collect_dataset(env_id, n, SampledPolicy(actor), num_envs=num_envs, seed=seed,
                           progress=progress, metadata=meta)


def _reference_returns(env_id: str, short: str, expert, episodes: int, seed: int) -> dict:
    """Mean returns of uniform random actions and of the (sampled) expert policy, measured now."""
    ref_seed = seed + REF_SEED_OFFSET
    out: dict[str, Any] = {"ref_min_return": None, "ref_max_return": None, "ref_episodes": episodes,
                           "ref_seed": ref_seed, "ref_policy": None, "ref_note": None}
    if episodes <= 0:
        out["ref_note"] = "reference returns not measured (ref_episodes=0)."
        return out
    env = make_gym_env(env_id, num_envs=episodes)
    try:
        # seeded stochastic evaluations: their samples come from torch's RNG seeded with ref_seed, the caller's stream untouched
        rets = evaluate_policy(env, None, episodes, deterministic=False, seed=ref_seed)
        out["ref_min_return"] = float(rets.mean())
        if expert is not None:
            actor, card = expert
            rets = evaluate_policy(env, actor, episodes, deterministic=False, seed=ref_seed)
            out["ref_max_return"] = float(rets.mean())
            out["ref_policy"] = card.get("name")
    finally:
        env.close()
    if expert is None:
        out["ref_note"] = (
            f"no shipped expert policy '{short}-expert' (shipped: {list_policies() or 'none'}): "
            f"ref_max_return not measured; normalise with D4RL's constants instead."
        )
    else:
        out["ref_note"] = (
            f"mean returns over {episodes} episodes of uniform random actions (min) and of "
            f"{out['ref_policy']} sampled stochastically (max), measured at generation time."
        )
    return out


def _finish_metadata(ds, env_id, short, level, seed, num_transitions, refs) -> None:
    mean = ds.metadata["returns"]["mean"]
    own = None
    lo, hi = refs["ref_min_return"], refs["ref_max_return"]
    if lo is not None and hi is not None and hi != lo:
        own = normalized_score(env_id, mean, (lo, hi))
    ds.metadata.update(
        {
            "dataset": f"{short}-{level}",
            "env_id": env_id,
            "level": level,
            "seed": seed,
            "num_transitions_requested": num_transitions,
            "protocol": "D4RL: random = uniform actions; medium/expert = SAC policy sampled "
            "stochastically; medium-expert = medium + expert concatenated",
            **refs,
            "score": {"d4rl": normalized_score(env_id, mean), "own_refs": own},
        }
    )


def medium_expert_from_parts(parts: list[OfflineDataset], seed: int, num_transitions: int) -> OfflineDataset:
    """D4RL's ``medium-expert``: a ``[medium, expert]`` pair of generated datasets concatenated, with the expert part's references.

    :func:`~torchrl_offhrl.data.catalog.named_dataset` builds it from the
    cached parts; :func:`generate_dataset` from parts it collects itself.
    """
    medium = parts[0].metadata
    env_id, short = resolve_env(medium["env_id"])
    ds = combine_levels(parts, seed)
    refs = {k: parts[1].metadata.get(k) for k in ("ref_min_return", "ref_max_return", "ref_episodes", "ref_seed", "ref_policy", "ref_note")}
    _finish_metadata(ds, env_id, short, "medium-expert", seed, num_transitions, refs)
    return ds
