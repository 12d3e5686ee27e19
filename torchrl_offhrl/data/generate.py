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
:func:`named_dataset` caches the result as HDF5 under
``cache_dir()/datasets``.
"""
from __future__ import annotations

import hashlib
import os
import re
import sys
import warnings
from pathlib import Path
from typing import Any

from tensordict.nn import TensorDictModuleBase

from ..registry import ENV_IDS, LEVELS, resolve_env, task_of
from ..rollouts import evaluate_policy
from ..scores import normalized_score
from ..utils import cache_dir, one_thread, remove_stale_tmp
from .collect import collect_dataset, combine_levels, make_gym_env
from .dataset import DatasetError, OfflineDataset
from .io import export_minari, load_dataset, save_dataset  # export_minari: re-exported (it lived here)
from .stacking import SCRIPT_LEVELS, SCRIPT_VERSION, combine_stacking, generate_stacking_dataset
from .policies import (
    PolicyNotFoundError,
    list_policies,
    load_policy,
    missing_policy_message,
)

__all__ = [
    "ENV_IDS",
    "LEVELS",
    "SampledPolicy",
    "dataset_path",
    "estimate_seconds",
    "export_minari",
    "generate_dataset",
    "named_dataset",
    "resolve_env",
]

#: Offset between a dataset's seed and the seed of its reference evaluations.
REF_SEED_OFFSET = 100_003

#: Collection speed in env steps per second (8 envs, one torch thread, the
#: project's 2-core machine while two trainings ran), for the time estimate
#: of :func:`named_dataset`: uniform random actions, and a (256, 256) SAC actor.
STEPS_PER_SECOND: dict[str, dict[str, float]] = {
    "hopper": {"random": 2600.0, "policy": 1800.0},
    "halfcheetah": {"random": 4700.0, "policy": 2900.0},
    # the scripted block stacker on 8 TorchRL-batched envs, one core (MuJoCo's 20 sub-steps dominate)
    "blockstack2": {"random": 300.0, "policy": 300.0},
    "blockstack3": {"random": 280.0, "policy": 280.0},
}
#: short names of the block-stacking envs (their datasets come from :mod:`torchrl_offhrl.data.stacking`)

_NAME = re.compile(
    r"^(?P<env>[a-z0-9_]+?)-(?P<level>random|medium-expert|medium|expert)(?:-(?P<size>\d+[km]?))?$",
    re.IGNORECASE,
)


class SampledPolicy(TensorDictModuleBase):
    """Runs a stochastic actor under ``ExplorationType.RANDOM``, whatever the caller set.

    D4RL's medium and expert data are *sampled* from the SAC policy, not taken
    from its mean. Wrapping the actor makes that independent of the
    exploration type a collector or a caller happens to use.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.envs.utils import ExplorationType, set_exploration_type
        >>> from torchrl_offhrl.data.policies.training import make_behaviour_actor
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


# ------------------------------------------------------------ named + cached
def _parse_name(name: str) -> tuple[str, str, str, int | None]:
    m = _NAME.match(name.strip())
    if m is None:
        raise ValueError(
            f"{name!r}: expected '<env>-<level>' with env in {sorted(ENV_IDS)} (or a Gymnasium "
            f"id's lower-case name) and level in {list(LEVELS)}, optionally with a size suffix "
            f"like '-100k'; e.g. 'hopper-medium', 'halfcheetah-medium-expert-200k'."
        )
    env_id, short = resolve_env(m["env"])
    size = m["size"]
    n = None
    if size:
        mult = {"k": 1_000, "m": 1_000_000}.get(size[-1].lower(), 1)
        n = int(size.rstrip("kKmM")) * mult
    return env_id, short, m["level"].lower(), n


_POLICY_LEVELS = {"random": [], "medium": ["medium"], "expert": ["expert"], "medium-expert": ["medium", "expert"]}


def _policy_tag(short: str, level: str) -> str:
    """``-p<hash>`` of the shipped policy weights a level uses ('' for random or when not shipped).

    Part of the cache key: a dataset generated with other weights (an older
    package version) is never mistaken for one of the shipped policy.
    """
    from . import policies

    needed = _POLICY_LEVELS[level]
    h = hashlib.sha1()
    for lv in needed:
        f = Path(policies.POLICY_DIR) / f"{short}-{lv}.pt"
        if not f.is_file():
            return ""
        h.update(f.read_bytes())
    return f"-p{h.hexdigest()[:8]}" if needed else ""


def dataset_path(name: str, num_transitions: int | None = None, seed: int = 0, num_envs: int = 8) -> Path:
    """Where :func:`named_dataset` caches a dataset: ``cache_dir()/datasets/<name>-<N>-seed<S>[-envs<k>][-p<hash>].hdf5``.

    ``-p<hash>`` identifies the shipped policy weights of medium/expert levels.
    """
    _, short, level, n = _resolve_size(name, num_transitions)
    envs = "" if num_envs == 8 else f"-envs{num_envs}"
    tag = f"-script{SCRIPT_VERSION}" if task_of(short).goal_conditioned else _policy_tag(short, level)
    return cache_dir() / "datasets" / f"{short}-{level}-{n}-seed{seed}{envs}{tag}.hdf5"


def _resolve_size(name: str, num_transitions: int | None):
    env_id, short, level, n = _parse_name(name)
    if n is not None and num_transitions is not None and n != num_transitions:
        raise ValueError(f"{name!r} says {n} transitions but num_transitions={num_transitions}.")
    n = n if n is not None else (num_transitions if num_transitions is not None else 1_000_000)
    if n <= 0:
        raise ValueError(f"{name!r}: the number of transitions must be positive, got {n}.")
    return env_id, short, level, n


def estimate_seconds(env: str, level: str, num_transitions: int, ref_episodes: int = 10) -> float:
    """Rough generation time on the project's 2-core machine (see :data:`STEPS_PER_SECOND`).

    ``num_transitions`` per part; ``medium-expert`` counts two parts. The
    reference evaluations add one 1000-step rollout of ``ref_episodes``
    envs per reference policy.

    Examples:
        >>> round(estimate_seconds("hopper", "random", 260_000, ref_episodes=0))
        100
    """
    short = resolve_env(env)[1]
    rates = STEPS_PER_SECOND.get(short, STEPS_PER_SECOND["hopper"])
    parts = 2 if level == "medium-expert" else 1
    if task_of(short).goal_conditioned:  # no reference evaluations
        return parts * num_transitions / rates["policy"]
    seconds = parts * num_transitions / rates["random" if level == "random" else "policy"]
    if ref_episodes > 0:
        seconds += ref_episodes * 1000 * (1 / rates["random"] + 1 / rates["policy"])
    return seconds


def _fmt_seconds(s: float) -> str:
    if s < 90:
        return f"{s:.0f} s"
    if s < 5400:
        return f"{s / 60:.0f} min"
    return f"{s / 3600:.1f} h"


def named_dataset(
    name: str,
    num_transitions: int | None = None,
    seed: int = 0,
    progress: bool = True,
    num_envs: int = 8,
) -> OfflineDataset:
    """A D4RL-style dataset by name, generated once and cached as HDF5.

    Args:
        name: ``"<env>-<level>"`` (``"hopper-medium"``,
            ``"halfcheetah-random"``, ``"hopper-medium-expert"``), optionally
            with a size suffix (``"hopper-medium-100k"``).
        num_transitions: transitions per part (default: the suffix, else
            1,000,000 as in D4RL; ``medium-expert`` holds twice as many).
        seed: generation seed (part of the cache key).
        progress: progress bars and the "generating" message.
        num_envs: environments stepped side by side (part of the cache key
            when not 8, since it changes the data).

    The file is ``cache_dir()/datasets/<env>-<level>-<N>-seed<S>[-p<hash>].hdf5``
    (the hash names the shipped policy weights); it is
    written under a temporary name and renamed when complete, so an
    interrupted generation never leaves a file that would be loaded. A
    ``medium-expert`` dataset is built from the cached ``medium`` and
    ``expert`` datasets of the same size and seed (generated first when
    absent).

    Raises:
        PolicyNotFoundError: the level needs a policy that is not shipped; the
            message lists the shipped ones and the commands that make one.
    """
    env_id, short, level, n = _resolve_size(name, num_transitions)
    path = dataset_path(f"{short}-{level}", n, seed, num_envs)
    remove_stale_tmp(path.parent)  # left by generations that were killed while saving
    if path.is_file():
        try:
            return load_dataset(path)
        except DatasetError as err:  # the cache can always be rebuilt: say so, and generate the file again
            warnings.warn(f"the cached dataset {path} is corrupt ({err}); deleting it and generating it again", stacklevel=2)
            path.unlink()
    if task_of(short).goal_conditioned:  # scripted behaviour: no shipped policy needed
        if level not in (*SCRIPT_LEVELS, "medium-expert"):
            raise ValueError(f"{name!r}: the block-stacking datasets come in the levels {[*SCRIPT_LEVELS, 'medium-expert']}")
        if level == "medium-expert":  # from the cached parts, generated first when absent
            parts = [named_dataset(f"{short}-{lv}", n, seed, progress, num_envs) for lv in ("medium", "expert")]
            ds = combine_stacking(parts, seed)
            ds.metadata.update({"dataset": f"{short}-{level}", "level": level, "num_transitions_requested": n})
        else:
            _announce(name, path, n, estimate_seconds(short, level, n), progress, "scripted controller")
            ds = generate_stacking_dataset(env_id, level, n, seed=seed, num_envs=num_envs, progress=progress)
    else:
        needed = _POLICY_LEVELS[level]
        shipped = list_policies()
        for lv in needed:
            if f"{short}-{lv}" not in shipped:
                raise PolicyNotFoundError(missing_policy_message(f"{short}-{lv}"))
        if level == "medium-expert":
            todo = [lv for lv in needed if not dataset_path(f"{short}-{lv}", n, seed, num_envs).is_file()]
            seconds = sum(estimate_seconds(short, lv, n) for lv in todo)
            detail = f"parts to generate first: {[f'{short}-{lv}' for lv in todo]}" if todo else "from the cached parts"
            _announce(name, path, n * len(todo), seconds, progress, detail)
            parts = [named_dataset(f"{short}-{lv}", n, seed, progress, num_envs) for lv in needed]
            ds = combine_levels(parts, seed)
            refs = {k: parts[1].metadata.get(k) for k in
                    ("ref_min_return", "ref_max_return", "ref_episodes", "ref_seed", "ref_policy", "ref_note")}
            _finish_metadata(ds, env_id, short, level, seed, n, refs)
        else:
            _announce(name, path, n, estimate_seconds(short, level, n), progress, "")
            ds = generate_dataset(env_id, level, n, seed=seed, num_envs=num_envs, progress=progress)
    save_dataset(ds, path)
    ds.metadata["source"] = str(path)
    return ds


def _announce(name, path, n, seconds, progress, detail) -> None:
    if not progress:
        return
    if n:
        msg = (f"{name}: not cached at {path}; generating it now ({detail + '; ' if detail else ''}"
               f"{n:,} transitions to collect, estimated {_fmt_seconds(seconds)} on a 2-core machine).")
    else:
        msg = f"{name}: not cached at {path}; building it {detail}."
    print(msg, file=sys.stderr, flush=True)
