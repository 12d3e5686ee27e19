"""Datasets by name (``"hopper-medium-100k"``), generated once and cached as HDF5 under ``cache_dir()/datasets``.

The naming scheme (``<env>-<level>[-<size>]``), the cache key (size, seed,
envs, and the hash of the shipped policy weights or the stacking script's
version), and the time estimate printed before a generation (measured
collection speeds on the project's 2-core machine). What a generation does
is :mod:`torchrl_offhrl.data.generate` (D4RL's protocol) and
:mod:`torchrl_offhrl.data.stacking` (the scripted block stacker).
"""
from __future__ import annotations

import hashlib
import re
import sys
import warnings
from pathlib import Path

from ..registry import ENV_IDS, LEVELS, resolve_env, task_of
from ..utils import cache_dir, remove_stale_tmp
from . import generate  # called through the module: tests replace its functions
from .dataset import DatasetError, OfflineDataset
from .io import load_dataset, save_dataset
from .policies import PolicyNotFoundError, list_policies, missing_policy_message
from .stacking import SCRIPT_LEVELS, SCRIPT_VERSION, combine_stacking, generate_stacking_dataset

__all__ = ["STEPS_PER_SECOND", "dataset_path", "estimate_seconds", "named_dataset"]

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

_NAME = re.compile(
    r"^(?P<env>[a-z0-9_]+?)-(?P<level>random|medium-expert|medium|expert)(?:-(?P<size>\d+[km]?))?$",
    re.IGNORECASE,
)


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
            ds = generate.medium_expert_from_parts(parts, seed, n)
        else:
            _announce(name, path, n, estimate_seconds(short, level, n), progress, "")
            ds = generate.generate_dataset(env_id, level, n, seed=seed, num_envs=num_envs, progress=progress)
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
