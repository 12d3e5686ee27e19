"""A generated dataset as its actions alone, rebuilt bit for bit by replaying them in MuJoCo.

A dataset made by :func:`~torchrl_offhrl.data.collect_dataset` is fixed by
its env, seed, number of side-by-side envs and the actions its policy drew:
the observations, rewards and episode ends follow from MuJoCo. An *action
pack* keeps only those actions (Hopper's 1M transitions: 10 MB instead of
95 MB of HDF5; the float32 actions are stored byte-shuffled and
zlib-compressed, 16-24% smaller than raw, which decides whether two packs
and the wheels fit the 64 MiB a call to a lent GPU machine carries), so the
dataset can travel to a machine that cannot afford to generate it (a lent
GPU machine has minutes, not the quarter of an hour that sampling the
policy takes; a different torch there would not even draw the
same actions). Rebuilding checks the content hash, so a run trained on the
rebuilt data resumes anywhere on the original, and a replay that differs (a
MuJoCo or Gymnasium that computes otherwise) is refused, not used.

The replay follows the collection: stream ``i`` of ``num_envs`` is the env
seeded ``seed + i`` at its first reset and reset again, unseeded, before
its first step (the collector's reset at construction), then reset unseeded
after every episode end; actions are passed as float32, as the collector
does (the control cost is computed from them). Where every stream ended an
episode at the same step (HalfCheetah's fixed 1000-step episodes, always),
the collector reset the whole vector env once more after Gymnasium's own
reset of each: the replay finds those steps from its own episode ends and
replays again with the extra resets until they agree (two passes for
HalfCheetah, one where episodes end apart).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from .dataset import DatasetError, OfflineDataset

__all__ = ["load_action_pack", "read_action_pack", "save_action_pack"]

FORMAT = "torchrl_offhrl.action_pack/2"  # /2: actions byte-shuffled and zlib-compressed; /1 (raw float32) is still read
FORMATS = ("torchrl_offhrl.action_pack/1", FORMAT)
MAX_PASSES = 4  # replays until the steps where all streams end together stop changing (the content hash checks the result)


def save_action_pack(dataset: OfflineDataset, path: str | os.PathLike) -> Path:
    """Write ``dataset``'s actions, metadata and content hash to ``path`` (a ``torch.save`` file).

    Raises:
        DatasetError: the dataset was not made by one collection (its metadata
            lacks ``env_id``, ``seed`` or ``num_envs``, or it concatenates
            levels, as ``medium-expert`` does: pack its parts instead).
    """
    meta = dataset.metadata
    missing = [k for k in ("env_id", "seed", "num_envs") if meta.get(k) is None]
    if missing or meta.get("level") == "medium-expert" or len(dataset) % int(meta.get("num_envs") or 1):
        raise DatasetError(f"{meta.get('source', '<in-memory>')}: only a dataset made by one collection (collect_dataset / generate_dataset, "
                           f"not a concatenation such as medium-expert) can be rebuilt from its actions"
                           + (f"; its metadata lacks {missing}" if missing else "; pack its medium and expert parts instead"))
    path = Path(path)
    torch.save({"format": FORMAT, "actions": _compress(dataset.data["action"].float()), "metadata": _plain(meta),
                "content_hash": dataset.content_hash(), "action_bounds": (dataset.action_low, dataset.action_high)}, path)
    return path


def read_action_pack(path: str | os.PathLike) -> dict:
    """The contents of an action pack (``actions``, ``metadata``, ``content_hash``, ``action_bounds``), without replaying it.

    Raises:
        DatasetError: not readable, or not an action pack.
    """
    path = Path(path)
    try:
        pack = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # a truncated or foreign file
        raise DatasetError(f"{path}: not readable as an action pack ({err}); write one with save_action_pack") from None
    if not isinstance(pack, dict) or pack.get("format") not in FORMATS:
        raise DatasetError(f"{path}: not an action pack (format {pack.get('format') if isinstance(pack, dict) else type(pack).__name__!r}, "
                           f"expected one of {FORMATS})")
    if pack["format"] != FORMATS[0]:
        pack = {**pack, "actions": _decompress(pack["actions"])}
    return pack


def _compress(actions: torch.Tensor) -> dict:
    """float32 ``actions`` as zlib-compressed byte planes (all first bytes, then all second bytes...): a float's sign and
    exponent bytes repeat across actions, which zlib finds only once they stand together."""
    import zlib

    planes = np.ascontiguousarray(actions.contiguous().numpy().view(np.uint8).reshape(-1, 4).T)
    return {"shape": tuple(actions.shape), "zlib": torch.frombuffer(bytearray(zlib.compress(planes.tobytes(), 6)), dtype=torch.uint8)}


def _decompress(packed: dict) -> torch.Tensor:
    import zlib

    planes = np.frombuffer(zlib.decompress(packed["zlib"].numpy().tobytes()), dtype=np.uint8).reshape(4, -1)
    return torch.from_numpy(np.ascontiguousarray(planes.T).view(np.float32).reshape(packed["shape"]))


def load_action_pack(path: str | os.PathLike, workers: int | None = None, progress: bool = True) -> OfflineDataset:
    """Rebuild the dataset of an action pack by replaying its actions (one process per env stream, at most ``workers``).

    Raises:
        DatasetError: not an action pack, or the replay does not give the
            packed content hash (the message says what differs).
    """
    import multiprocessing as mp

    from tqdm.auto import tqdm

    path = Path(path)
    pack = read_action_pack(path)
    meta = dict(pack["metadata"])
    actions = pack["actions"].numpy()
    streams = int(meta["num_envs"])
    steps = len(actions) // streams
    jobs = [(meta["env_id"], int(meta["seed"]) + i, actions[i * steps:(i + 1) * steps]) for i in range(streams)]
    workers = max(1, min(streams, workers or os.cpu_count() or 1))
    # fork where there is one: the workers need only Gymnasium, and a spawned worker would re-run a caller's unguarded script
    method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
    together = np.zeros(0, dtype=np.int64)  # steps at which every stream ended an episode: one more reset of each after them
    with mp.get_context(method).Pool(workers) as pool:
        for _ in range(MAX_PASSES):
            parts = list(tqdm(pool.imap(_replay_stream, [(*j, together) for j in jobs]), total=streams, desc=f"replay {meta['env_id']}",
                              unit="stream", disable=not progress))
            obs, nobs, rew, term, trunc = (np.stack([p[k] for p in parts]) for k in range(5))
            found = np.nonzero((term | trunc)[:, :-1].all(0))[0]
            if np.array_equal(found, together):
                break
            together = found
    trunc[:, -1] |= ~term[:, -1]  # as collect_dataset: each stream's last, cut-short episode ends truncated
    data = TensorDict({"observation": torch.from_numpy(obs), "action": pack["actions"].reshape(streams, steps, -1),
                       "next": {"observation": torch.from_numpy(nobs), "reward": torch.from_numpy(rew)[..., None],
                                "terminated": torch.from_numpy(term)[..., None], "truncated": torch.from_numpy(trunc)[..., None]}},
                      batch_size=[streams, steps]).reshape(-1)
    low, high = pack["action_bounds"]
    ds = OfflineDataset(data, {**meta, "source": str(path), "rebuilt_from_actions": True}, (low, high))
    if ds.content_hash() != pack["content_hash"]:
        raise DatasetError(f"{path}: replaying the actions gave other data (hash {ds.content_hash()}, packed {pack['content_hash']}): this "
                           f"machine's MuJoCo/Gymnasium step differently from those that collected it ({meta.get('versions')}); "
                           "generate the dataset here instead")
    return ds


def _replay_stream(job):
    import gymnasium as gym

    env_id, seed, actions, together = job
    together = set(together.tolist())
    env = gym.make(env_id)
    env.reset(seed=seed)
    o, _ = env.reset()
    steps = len(actions)
    obs = np.empty((steps, o.shape[0]), np.float32)
    nobs = np.empty_like(obs)
    rew = np.empty(steps, np.float32)
    term = np.zeros(steps, bool)
    trunc = np.zeros(steps, bool)
    for t in range(steps):
        obs[t] = o
        o2, r, te, tr, _ = env.step(actions[t])
        nobs[t], rew[t], term[t], trunc[t] = o2, r, te, tr
        o = env.reset()[0] if (te or tr) else o2
        if t in together:
            o = env.reset()[0]
    env.close()
    return obs, nobs, rew, term, trunc


def _plain(obj):
    """Metadata as the plain types ``torch.load(weights_only=True)`` reads back."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (np.generic,)):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None or isinstance(obj, torch.Tensor):
        return obj
    return str(obj)
