"""Reading and writing offline datasets.

Three sources, one entry point (:func:`load_dataset`):

* D4RL-style HDF5 files (``observations``, ``actions``, ``rewards``,
  ``terminals``, ``timeouts``, optional ``next_observations``), read with h5py;
* the project's own HDF5 files, written by :func:`save_dataset`: the D4RL key
  layout plus ``next_observations``, a JSON metadata attribute and, under the
  group ``extra/``, any further per-transition fields (goals, options...);
* Minari datasets already stored locally (``$MINARI_DATASETS_PATH``); nothing
  is ever downloaded.

Files are opened read-only: a failed load never modifies anything on disk.
Writing: :func:`save_dataset` (the project's HDF5) and :func:`export_minari`
(a local Minari dataset, read back by :func:`load_dataset` with its id).
"""
from __future__ import annotations

import errno
import json
import logging
import os
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from ..utils import atomic_write, disk_write_error
from .dataset import DatasetError, OfflineDataset, check_finite, check_plausible

__all__ = ["export_minari", "load_dataset", "save_dataset", "METADATA_ATTR"]

log = logging.getLogger(__name__)

METADATA_ATTR = "offhrl_metadata"
#: HDF5 group of the per-transition fields beyond the D4RL keys (e.g. the goal fields of the block-stacking
#: datasets), one dataset per TensorDict key, nested keys as paths (``extra/next/achieved_goal``)
EXTRA_GROUP = "extra"
# the keys the D4RL layout stores, and those OfflineDataset derives
_CORE_KEYS = {("observation",), ("action",), ("next", "observation"), ("next", "reward"), ("next", "terminated"), ("next", "truncated"),
              ("next", "done"), ("episode",)}
_REQUIRED = ("observations", "actions", "rewards", "terminals")
_MINARI_ID = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*-v\d+$")


def load_dataset(
    source: str | os.PathLike,
    env_id: str | None = None,
    dtype: torch.dtype = torch.float32,
) -> OfflineDataset:
    """Load an offline dataset from a file or a local Minari id.

    Args:
        source: path to an HDF5 file (D4RL layout or written by
            :func:`save_dataset`), or the id of a Minari dataset stored
            locally, e.g. ``"mujoco/hopper/medium-v0"``.
        env_id (str, optional): when given, the observation and action
            dimensions are checked against ``gymnasium.make(env_id)`` and the
            id is recorded in the metadata.
        dtype: floating dtype of observations, actions and rewards.

    Returns:
        OfflineDataset: transitions in TorchRL's offline layout.

    Raises:
        DatasetError: missing key, lengths that disagree, NaN/inf values,
            dimensions that do not match ``env_id``, a file that is not HDF5,
            or a Minari id that is not stored locally.

    Examples:
        >>> import tempfile, os
        >>> from torchrl_offhrl.data import make_toy_dataset, save_dataset, load_dataset
        >>> ds = make_toy_dataset(num_episodes=3, episode_length=4)
        >>> path = os.path.join(tempfile.mkdtemp(), "toy.hdf5")
        >>> _ = save_dataset(ds, path)
        >>> again = load_dataset(path)
        >>> len(again), again.num_episodes, again.metadata["env_id"]
        (12, 3, 'Toy-v0')
    """
    path = Path(os.fspath(source)).expanduser()
    if path.is_file():
        ds = _load_hdf5(path, dtype)
    elif path.is_dir():
        raise DatasetError(
            f"{path}: is a directory. Pass the HDF5 file itself, or a Minari dataset id "
            f"(e.g. 'mujoco/hopper/medium-v0') stored under $MINARI_DATASETS_PATH."
        )
    elif _MINARI_ID.match(str(source)) and not str(source).endswith((".hdf5", ".h5")):
        ds = _load_minari(str(source), dtype)
    else:
        raise DatasetError(
            f"{source}: no such file, and not a Minari dataset id. Give the path of a D4RL-style "
            f"or torchrl_offhrl HDF5 file, or the id of a Minari dataset stored locally."
        )
    if env_id is not None:
        _check_env_dims(ds, env_id, str(source))
        ds.metadata["env_id"] = env_id
    return ds


# --------------------------------------------------------------------- HDF5
def _load_hdf5(path: Path, dtype: torch.dtype) -> OfflineDataset:
    import h5py

    if not h5py.is_hdf5(path):
        raise DatasetError(
            f"{path}: is not an HDF5 file (h5py cannot read its signature). "
            f"Expected a D4RL-style .hdf5 with keys {list(_REQUIRED)} + 'timeouts'."
        )
    try:
        with h5py.File(path, "r") as f:
            if any(k.startswith("episode_") for k in f.keys()) and "observations" not in f:
                raise DatasetError(
                    f"{path}: looks like a Minari data file (episode_* groups). Load it by its "
                    f"Minari id with $MINARI_DATASETS_PATH pointing at its root instead."
                )
            missing = [k for k in _REQUIRED if k not in f]
            if missing:
                raise DatasetError(
                    f"{path}: missing key(s) {missing}; found {sorted(f.keys())}. A D4RL-style "
                    f"file needs {list(_REQUIRED)}, plus 'timeouts' and optionally "
                    f"'next_observations'."
                )
            arrays: dict[str, np.ndarray] = {k: f[k][()] for k in _REQUIRED}
            arrays["timeouts"] = f["timeouts"][()] if "timeouts" in f else None
            has_next = "next_observations" in f
            if has_next:
                arrays["next_observations"] = f["next_observations"][()]
            meta_raw = f.attrs.get(METADATA_ATTR)
            extras = _read_extras(f)
    except OSError as err:  # a truncated or damaged file: h5py says so without the fix
        raise DatasetError(
            f"{path}: cannot be read: the file is corrupt or truncated (h5py: {err}). Copy or download it again; "
            f"a dataset generated by torchrl_offhrl is regenerated when its cached file is removed."
        ) from None
    metadata: dict[str, Any] = json.loads(meta_raw) if meta_raw is not None else {}
    metadata["source"] = str(path)

    n = arrays["observations"].shape[0]
    expect_ndim = {"observations": 2, "actions": 2, "next_observations": 2}
    for key, arr in arrays.items():
        if arr is None:
            continue
        if arr.shape[0] != n:
            raise DatasetError(
                f"{path}: key '{key}' has {arr.shape[0]} rows (shape {arr.shape}) but "
                f"'observations' has {n} (shape {arrays['observations'].shape}); every key "
                f"must hold one row per transition."
            )
        want = expect_ndim.get(key)
        if want is not None and arr.ndim != want:
            raise DatasetError(
                f"{path}: key '{key}' has shape {arr.shape}; expected [N, dim]."
            )
        if key in ("rewards", "terminals", "timeouts") and not (
            arr.ndim == 1 or (arr.ndim == 2 and arr.shape[1] == 1)
        ):
            raise DatasetError(f"{path}: key '{key}' has shape {arr.shape}; expected [N] or [N, 1].")
    if has_next and arrays["next_observations"].shape[1] != arrays["observations"].shape[1]:
        raise DatasetError(
            f"{path}: 'next_observations' has shape {arrays['next_observations'].shape} but "
            f"'observations' has {arrays['observations'].shape}; their widths must match."
        )
    if n == 0:
        raise DatasetError(f"{path}: the file holds no transitions ('observations' has shape {arrays['observations'].shape}).")

    obs = torch.as_tensor(arrays["observations"], dtype=dtype)
    act = torch.as_tensor(arrays["actions"], dtype=dtype)
    rew = torch.as_tensor(arrays["rewards"], dtype=dtype).reshape(n, 1)
    term = torch.as_tensor(arrays["terminals"]).reshape(n).bool()
    tout = (
        torch.as_tensor(arrays["timeouts"]).reshape(n).bool()
        if arrays["timeouts"] is not None
        else torch.zeros(n, dtype=torch.bool)
    )
    source = str(path)
    check_finite(
        TensorDict({"observations": obs, "actions": act, "rewards": rew}, batch_size=[n]), source
    )
    check_plausible(TensorDict({"observations": obs, "actions": act, "rewards": rew}, batch_size=[n]), source)
    if has_next:
        nobs = torch.as_tensor(arrays["next_observations"], dtype=dtype)
        check_finite(TensorDict({"next_observations": nobs}, batch_size=[n]), source)
        check_plausible(TensorDict({"next_observations": nobs}, batch_size=[n]), source)
        keep = torch.ones(n, dtype=torch.bool)
        # a file that stops mid-episode: the collection ended there (truncation)
        if not (term[-1] or tout[-1]):
            tout = tout.clone()
            tout[-1] = True
    else:
        # next observation of step t is the observation of step t+1 within an
        # episode; an episode's last step has no recorded successor -> dropped.
        end = term | tout
        end[-1] = True
        keep = ~end
        nobs = torch.empty_like(obs)
        nobs[:-1] = obs[1:]
        dropped = int(end.sum())
        metadata["dropped_transitions"] = dropped
        log.info(
            "%s: no 'next_observations'; derived them within episodes and dropped the last "
            "transition of each of %d episodes (its next observation is not recorded).",
            path,
            dropped,
        )
        # the step before a dropped one now ends its episode: a truncation
        tout = torch.zeros(n, dtype=torch.bool)
        tout[:-1] = end[1:] & ~end[:-1]
        term = torch.zeros(n, dtype=torch.bool)
        if keep.sum() == 0:
            raise DatasetError(
                f"{path}: no transition left after deriving next observations (every episode "
                f"has a single step); store 'next_observations' in the file."
            )
    td = TensorDict(
        {
            "observation": obs,
            "action": act,
            "next": {
                "observation": nobs,
                "reward": rew,
                "terminated": term.unsqueeze(-1),
                "truncated": (tout & ~term).unsqueeze(-1),
            },
        },
        batch_size=[n],
    )
    for key, arr in extras.items():
        if arr.shape[:1] != (n,):
            raise DatasetError(f"{path}: '{EXTRA_GROUP}/{'/'.join(key)}' has shape {arr.shape} but 'observations' has {n} rows; "
                               "every key must hold one row per transition.")
        t = torch.as_tensor(arr)
        td.set(key, t.to(dtype) if t.is_floating_point() else t)
    if extras:
        check_finite(td.select(*[k for k in extras if td.get(k).is_floating_point()]), source)
    return OfflineDataset(td[keep], metadata)


def _read_extras(f) -> dict[tuple[str, ...], np.ndarray]:
    """The per-transition fields beyond the D4RL keys, stored under :data:`EXTRA_GROUP` (key path -> array)."""
    import h5py

    out: dict[tuple[str, ...], np.ndarray] = {}
    if EXTRA_GROUP not in f:
        return out

    def visit(name, obj):
        if isinstance(obj, h5py.Dataset):
            out[tuple(name.split("/"))] = obj[()]

    f[EXTRA_GROUP].visititems(visit)
    return out


def save_dataset(dataset: OfflineDataset, path: str | os.PathLike, compression: str | None = "gzip") -> Path:
    """Write a dataset to HDF5 (D4RL key layout + ``next_observations`` + metadata + the other fields under ``extra/``).

    The file is written to a temporary name in the same folder and renamed at
    the end, so an interrupted write never leaves a file that looks complete.

    Returns:
        the path written.
    """
    import h5py

    path = Path(os.fspath(path)).expanduser()
    td = dataset.data
    meta = dict(dataset.metadata)
    meta.pop("source", None)
    meta.pop("split", None)
    meta["action_low"] = dataset.action_low.tolist()
    meta["action_high"] = dataset.action_high.tolist()
    # h5py on a disk that fills up mid-write fails deep in HDF5 (and has crashed the interpreter): check the room first,
    # against the uncompressed size (an upper bound of what is written)
    need = sum(v.numel() * v.element_size() for v in td.values(include_nested=True, leaves_only=True)) + 2**20
    path.parent.mkdir(parents=True, exist_ok=True)
    free = shutil.disk_usage(path.parent).free
    if free < need:
        raise disk_write_error(OSError(errno.ENOSPC, f"the dataset needs up to {need / 2**20:.0f} MiB"), path)
    with atomic_write(path) as tmp, h5py.File(tmp, "w") as f:

        def put(name, tensor):
            f.create_dataset(name, data=tensor.detach().cpu().numpy(), compression=compression)

        put("observations", td.get("observation"))
        put("actions", td.get("action"))
        put("next_observations", td.get(("next", "observation")))
        put("rewards", td.get(("next", "reward")).reshape(-1))
        put("terminals", td.get(("next", "terminated")).reshape(-1))
        put("timeouts", (td.get(("next", "truncated")) & ~td.get(("next", "terminated"))).reshape(-1))
        for key in td.keys(include_nested=True, leaves_only=True):
            path_ = (key,) if isinstance(key, str) else tuple(key)
            if path_ not in _CORE_KEYS:
                put(f"{EXTRA_GROUP}/{'/'.join(path_)}", td.get(key))
        f.attrs[METADATA_ATTR] = json.dumps(meta, default=_json_default)
    return path


def _json_default(obj):
    if isinstance(obj, torch.Tensor):
        return obj.tolist()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return str(obj)


# ------------------------------------------------------------------- Minari
def _load_minari(dataset_id: str, dtype: torch.dtype) -> OfflineDataset:
    """A locally stored Minari dataset as an :class:`OfflineDataset` (flat Box observations).

    Why not TorchRL's ``MinariExperienceReplay``: it is a replay buffer that
    converts a dataset into its own memory-mapped storage under its root
    (downloading it unless ``load_from_local_minari`` is set), where the project needs the transitions as one flat
    dataset with its metadata (env id, start states, episode ends) to fit
    models on and to hash; reading the episodes with ``minari`` directly is
    that, with nothing downloaded and the errors saying what to do.
    """
    try:
        import minari
    except ImportError as err:  # pragma: no cover - depends on the install
        raise DatasetError(
            f"{dataset_id}: reading Minari datasets needs the 'minari' package: "
            f"pip install 'torchrl-offhrl[minari]'."
        ) from err
    local = minari.list_local_datasets()
    if dataset_id not in local:
        root = os.environ.get("MINARI_DATASETS_PATH", "~/.minari/datasets")
        raise DatasetError(
            f"{dataset_id}: no Minari dataset with this id is stored locally (looked in "
            f"{root}; found {sorted(local)[:10]}). Nothing is downloaded: copy the dataset "
            f"there or set $MINARI_DATASETS_PATH to its root."
        )
    mds = minari.load_dataset(dataset_id)
    obs_l, nobs_l, act_l, rew_l, term_l, trunc_l = [], [], [], [], [], []
    for ep in mds.iterate_episodes():
        o = np.asarray(ep.observations)
        if o.dtype == object or o.ndim != 2:
            raise DatasetError(
                f"{dataset_id}: episode {ep.id} has observations of shape {o.shape}; only flat "
                f"Box observations are supported (flatten dict observations first)."
            )
        t = len(ep.actions)
        obs_l.append(o[:t])
        nobs_l.append(o[1 : t + 1])
        act_l.append(np.asarray(ep.actions).reshape(t, -1))
        rew_l.append(np.asarray(ep.rewards).reshape(t))
        term_l.append(np.asarray(ep.terminations).reshape(t))
        tr = np.asarray(ep.truncations).reshape(t).copy()
        if not (tr[-1] or term_l[-1][-1]):
            tr[-1] = True  # an episode stored unfinished ends by truncation
        trunc_l.append(tr)
    if not obs_l:
        raise DatasetError(f"{dataset_id}: the Minari dataset holds no episodes.")
    n = sum(len(a) for a in act_l)
    term = torch.as_tensor(np.concatenate(term_l)).bool().unsqueeze(-1)
    td = TensorDict(
        {
            "observation": torch.as_tensor(np.concatenate(obs_l), dtype=dtype),
            "action": torch.as_tensor(np.concatenate(act_l), dtype=dtype),
            "next": {
                "observation": torch.as_tensor(np.concatenate(nobs_l), dtype=dtype),
                "reward": torch.as_tensor(np.concatenate(rew_l), dtype=dtype).unsqueeze(-1),
                "terminated": term,
                "truncated": torch.as_tensor(np.concatenate(trunc_l)).bool().unsqueeze(-1) & ~term,
            },
        },
        batch_size=[n],
    )
    check_finite(td, dataset_id)
    check_plausible(td, dataset_id)
    meta: dict[str, Any] = {"source": f"minari:{dataset_id}"}
    env_spec = getattr(mds, "env_spec", None)
    if env_spec is not None:
        meta["env_id"] = env_spec.id
    space = mds.action_space
    bounds = None
    if hasattr(space, "low"):
        bounds = (torch.as_tensor(space.low, dtype=torch.float32), torch.as_tensor(space.high, dtype=torch.float32))
    return OfflineDataset(td, meta, bounds)


def export_minari(
    dataset: OfflineDataset,
    dataset_id: str,
    author: str | None = "torchrl_offhrl",
    author_email: str | None = None,
    description: str | None = None,
):
    """Write ``dataset`` as a local Minari dataset (under ``$MINARI_DATASETS_PATH``).

    ``dataset.metadata["env_id"]`` names the env (its spaces give the stored
    dtypes); the generation-time reference returns become Minari's
    ``ref_min_score`` / ``ref_max_score`` when both are known. Needs the
    optional ``minari`` package. Returns the ``MinariDataset``; read it back
    with :func:`~torchrl_offhrl.data.load_dataset` and the same id.
    """
    try:
        import minari
        from minari.data_collector.episode_buffer import EpisodeBuffer
    except ImportError as err:  # pragma: no cover - depends on the install
        raise ImportError(
            "export_minari needs the optional 'minari' package: pip install 'torchrl-offhrl[minari]'."
        ) from err
    import gymnasium as gym

    env_id = dataset.metadata.get("env_id")
    if env_id is None:
        raise DatasetError("export_minari: the dataset's metadata has no 'env_id'; set it first.")
    env = gym.make(env_id)
    obs_dtype, act_dtype = env.observation_space.dtype, env.action_space.dtype
    td = dataset.data
    _, counts = torch.unique_consecutive(td.get("episode"), return_counts=True)
    bounds = np.concatenate([[0], np.cumsum(counts.numpy())])

    def arr(key, dtype=None):
        x = td.get(key).detach().cpu().numpy()
        return x.astype(dtype) if dtype is not None else x

    obs, nobs = arr("observation", obs_dtype), arr(("next", "observation"), obs_dtype)
    act = arr("action", act_dtype)
    rew = arr(("next", "reward")).reshape(-1).astype(np.float64)
    term = arr(("next", "terminated")).reshape(-1)
    trunc = arr(("next", "truncated")).reshape(-1) & ~term
    buffers = []
    for i in range(len(counts)):
        a, b = int(bounds[i]), int(bounds[i + 1])
        buffers.append(
            EpisodeBuffer(
                id=i,
                observations=np.concatenate([obs[a:b], nobs[b - 1 : b]]),
                actions=act[a:b],
                rewards=rew[a:b],
                terminations=term[a:b],
                truncations=trunc[a:b],
            )
        )
    meta = dataset.metadata
    lo, hi = meta.get("ref_min_return"), meta.get("ref_max_return")
    refs = {"ref_min_score": lo, "ref_max_score": hi} if lo is not None and hi is not None else {}
    if description is None:
        description = (
            f"{meta.get('dataset', 'dataset')} in {env_id}: {len(dataset)} transitions, "
            f"{len(counts)} episodes, policy {meta.get('policy')}, seed {meta.get('seed')}; "
            f"generated by torchrl_offhrl following D4RL's protocol."
        )
    try:
        return minari.create_dataset_from_buffers(
            dataset_id,
            buffer=buffers,
            env=env_id,
            eval_env=env_id,
            algorithm_name=str(meta.get("policy", "unknown")),
            author=author,
            author_email=author_email,
            code_permalink="torchrl_offhrl.data.generate",
            description=description,
            **refs,
        )
    finally:
        env.close()


def _check_env_dims(ds: OfflineDataset, env_id: str, source: str) -> None:
    import gymnasium as gym

    try:
        env = gym.make(env_id)
    except Exception as err:
        raise DatasetError(f"{source}: cannot check dimensions against env {env_id!r}: {err}") from err
    try:
        space = env.observation_space
        if isinstance(space, gym.spaces.Dict) and "observation" in space.spaces:  # a goal env (block stacking): the state entry
            space = space["observation"]
        obs_shape = space.shape
        act_shape = env.action_space.shape
        action_low, action_high = env.action_space.low, env.action_space.high
    finally:
        env.close()
    if obs_shape is None or (ds.observation_dim,) != tuple(obs_shape):
        raise DatasetError(
            f"{source}: key 'observations' has width {ds.observation_dim} but {env_id} "
            f"observations have shape {obs_shape}; is this the dataset of another env or version?"
        )
    if act_shape is None or (ds.action_dim,) != tuple(act_shape):
        raise DatasetError(
            f"{source}: key 'actions' has width {ds.action_dim} but {env_id} actions have "
            f"shape {act_shape}; is this the dataset of another env or version?"
        )
    ds.action_low = torch.as_tensor(action_low, dtype=torch.float32)
    ds.action_high = torch.as_tensor(action_high, dtype=torch.float32)
