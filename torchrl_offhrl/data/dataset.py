"""Offline datasets in TorchRL's offline TensorDict layout.

An :class:`OfflineDataset` is a flat ``TensorDict`` of ``N`` transitions with
the keys TorchRL's offline replay buffers use::

    observation, action, episode,
    ("next", "observation" | "reward" | "done" | "terminated" | "truncated")

plus a ``metadata`` dict (env id, versions, seed, return statistics, ...).
Episodes are contiguous and numbered by ``episode``; an episode ends at a
transition whose ``("next", "done")`` is set.
"""
from __future__ import annotations

import dataclasses
import logging
import operator
import os
from typing import Any, Sequence

import torch
from tensordict import TensorDict

__all__ = ["DatasetError", "OfflineDataset", "NormalizationStats"]


class DatasetError(ValueError):
    """Raised for a dataset that cannot be used as it is.

    The message names the file, the key and the shape involved, and what to do.
    """


@dataclasses.dataclass
class NormalizationStats:
    """Per-dimension statistics of a dataset, used by every learned model.

    ``delta`` is the next-state residual ``s' - s``. Standard deviations are
    floored at ``eps`` so that constant dimensions do not blow up.
    """

    obs_mean: torch.Tensor
    obs_std: torch.Tensor
    delta_mean: torch.Tensor
    delta_std: torch.Tensor
    reward_mean: torch.Tensor
    reward_std: torch.Tensor
    obs_min: torch.Tensor
    obs_max: torch.Tensor
    action_low: torch.Tensor
    action_high: torch.Tensor

    def to(self, device) -> "NormalizationStats":
        return NormalizationStats(
            **{f.name: getattr(self, f.name).to(device) for f in dataclasses.fields(self)}
        )


def _drop_storage_init_log(record: logging.LogRecord) -> bool:
    """Logging filter: leave out TorchRL's "Initialized LazyTensorStorage ..." line."""
    return not str(record.msg).startswith("Initialized LazyTensorStorage")


class OfflineDataset:
    """A fixed set of transitions with episode boundaries and metadata.

    Args:
        data (TensorDict): ``N`` transitions in TorchRL's offline layout (see
            the module docstring). ``episode`` is created from the done flags
            when absent.
        metadata (dict, optional): free-form information kept with the data
            (``env_id``, ``seed``, ``returns``, ``source``...).
        action_bounds (tuple of tensors, optional): the action box. Defaults
            to ``metadata["action_low"/"action_high"]`` when present, else the
            per-dimension min/max of the actions in the data.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_offhrl.data import OfflineDataset
        >>> n = 6
        >>> td = TensorDict({
        ...     "observation": torch.arange(n, dtype=torch.float32)[:, None],
        ...     "action": torch.zeros(n, 1),
        ...     "next": {
        ...         "observation": torch.arange(1, n + 1, dtype=torch.float32)[:, None],
        ...         "reward": torch.ones(n, 1),
        ...         "terminated": torch.tensor([0, 0, 1, 0, 0, 0], dtype=torch.bool)[:, None],
        ...         "truncated": torch.tensor([0, 0, 0, 0, 0, 1], dtype=torch.bool)[:, None],
        ...     },
        ... }, batch_size=[n])
        >>> ds = OfflineDataset(td, metadata={"env_id": "Toy-v0"})
        >>> len(ds), ds.num_episodes, ds.observation_dim, ds.action_dim
        (6, 2, 1, 1)
        >>> ds.episode_returns().tolist()
        [3.0, 3.0]
        >>> ds.initial_observations().squeeze(-1).tolist()
        [0.0, 3.0]
    """

    def __init__(
        self,
        data: TensorDict,
        metadata: dict | None = None,
        action_bounds: tuple[torch.Tensor, torch.Tensor] | None = None,
    ):
        self.metadata: dict[str, Any] = dict(metadata or {})
        source = self.metadata.get("source", "<in-memory>")
        required = [
            "observation",
            "action",
            ("next", "observation"),
            ("next", "reward"),
            ("next", "terminated"),
            ("next", "truncated"),
        ]
        for key in required:
            if key not in data.keys(include_nested=True):
                raise DatasetError(
                    f"{source}: the dataset has no entry {key!r}. An OfflineDataset needs "
                    f"{required}; build it with torchrl_offhrl.data.load_dataset or add the key."
                )
        if data.batch_dims != 1:
            raise DatasetError(
                f"{source}: expected a flat TensorDict of transitions (batch_size=[N]), "
                f"got batch_size={list(data.batch_size)}; call data.reshape(-1) first."
            )
        for key in (("next", "terminated"), ("next", "truncated")):
            v = data.get(key)
            if v.dim() == 1:
                data.set(key, v.unsqueeze(-1))
            data.set(key, data.get(key).bool())
        if data.get(("next", "reward")).dim() == 1:
            data.set(("next", "reward"), data.get(("next", "reward")).unsqueeze(-1))
        data.set(
            ("next", "done"),
            data.get(("next", "terminated")) | data.get(("next", "truncated")),
        )
        if "episode" not in data.keys():
            done = data.get(("next", "done")).squeeze(-1)
            starts = torch.zeros_like(done)
            starts[1:] = done[:-1]
            data.set("episode", torch.cumsum(starts.long(), 0))
        self.data = data
        if action_bounds is None and "action_low" in self.metadata:
            action_bounds = (
                torch.as_tensor(self.metadata["action_low"], dtype=torch.float32),
                torch.as_tensor(self.metadata["action_high"], dtype=torch.float32),
            )
        if action_bounds is None:
            act = data.get("action")
            action_bounds = (act.min(0).values, act.max(0).values)
        self.action_low = torch.as_tensor(action_bounds[0], dtype=torch.float32).reshape(-1)
        self.action_high = torch.as_tensor(action_bounds[1], dtype=torch.float32).reshape(-1)
        self._stats: NormalizationStats | None = None

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return self.data.shape[0]

    def __getitem__(self, index):
        """Index the transitions like the wrapped ``TensorDict``.

        An int, slice, index tensor or boolean mask returns the selected
        transitions as a ``TensorDict`` (an int gives ``batch_size=[]``); a
        key (``"observation"``, ``("next", "reward")``) returns the stored
        tensor, not a copy.
        """
        return self.data[index]

    def __contains__(self, key) -> bool:
        """Whether ``key`` (a string or a nested tuple) is an entry of the data."""
        return key in self.data.keys(include_nested=True)

    def keys(
        self,
        include_nested: bool = False,
        leaves_only: bool = False,
        is_leaf=None,
        *,
        sort: bool = False,
    ):
        """The keys of the wrapped ``TensorDict``; same arguments as :meth:`TensorDict.keys`."""
        return self.data.keys(include_nested, leaves_only, is_leaf, sort=sort)

    @property
    def batch_size(self) -> torch.Size:
        """``torch.Size([N])``, the batch size of the wrapped ``TensorDict``."""
        return self.data.batch_size

    @property
    def device(self) -> torch.device | None:
        """Where the transitions live.

        The wrapped ``TensorDict``'s device, or, when it has none, the device
        all its tensors share (``None`` if they are spread over several).
        """
        if self.data.device is not None:
            return self.data.device
        devices = {v.device for v in self.data.values(include_nested=True, leaves_only=True)}
        return devices.pop() if len(devices) == 1 else None

    def __repr__(self) -> str:
        env = self.metadata.get("env_id", "?")
        return (
            f"OfflineDataset(env_id={env!r}, transitions={len(self)}, "
            f"episodes={self.num_episodes}, obs_dim={self.observation_dim}, "
            f"action_dim={self.action_dim})"
        )

    @property
    def observation_dim(self) -> int:
        return self.data.get("observation").shape[-1]

    @property
    def action_dim(self) -> int:
        return self.data.get("action").shape[-1]

    @property
    def env_id(self) -> str | None:
        return self.metadata.get("env_id")

    @property
    def num_episodes(self) -> int:
        return int(torch.unique_consecutive(self.data.get("episode")).numel())

    def episode_starts(self) -> torch.Tensor:
        """Boolean mask of the transitions that begin an episode."""
        ep = self.data.get("episode")
        starts = torch.ones_like(ep, dtype=torch.bool)
        starts[1:] = ep[1:] != ep[:-1]
        return starts

    def initial_observations(self) -> torch.Tensor:
        """The first observation of every episode, ``[num_episodes, obs_dim]``."""
        return self.data.get("observation")[self.episode_starts()]

    def episode_returns(self, complete_only: bool = False) -> torch.Tensor:
        """Undiscounted return of every episode in the data, in order.

        With ``complete_only``, the episodes listed in
        ``metadata["unfinished_episodes"]`` (their ``episode`` values: the
        episodes a collection budget cut short, see
        :func:`~torchrl_offhrl.data.collect_dataset`) are left out; data
        without that entry (e.g. a D4RL file) counts every episode as
        complete.
        """
        ep = self.data.get("episode")
        ids, inverse = torch.unique_consecutive(ep, return_inverse=True)
        rewards = self.data.get(("next", "reward")).squeeze(-1).double()
        out = torch.zeros(ids.numel(), dtype=torch.float64, device=rewards.device)
        out.index_add_(0, inverse, rewards)
        return self._complete(ids, out) if complete_only else out

    def episode_lengths(self, complete_only: bool = False) -> torch.Tensor:
        """Number of transitions of every episode in the data, in order (``complete_only``: as :meth:`episode_returns`).

        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> make_toy_dataset(num_episodes=2, episode_length=5).episode_lengths().tolist()
        [5, 5]
        """
        ids, counts = torch.unique_consecutive(self.data.get("episode"), return_counts=True)
        return self._complete(ids, counts) if complete_only else counts

    def _complete(self, ids: torch.Tensor, per_episode: torch.Tensor) -> torch.Tensor:
        """``per_episode`` (one value per episode id in ``ids``) without the episodes ``metadata["unfinished_episodes"]`` lists."""
        unfinished = self.metadata.get("unfinished_episodes") or []
        if not unfinished:
            return per_episode
        return per_episode[~torch.isin(ids, torch.as_tensor(unfinished, dtype=ids.dtype, device=ids.device))]

    def top_return_episodes(self, share: float) -> tuple[torch.Tensor, dict]:
        """``(mask, info)``: the transitions of the highest-return episodes, as few as cover ``share`` of the data.

        Episodes are ranked by their undiscounted return (an episode the
        collection budget cut short counts with its partial return) and taken
        from the top until they hold at least ``share * len(self)``
        transitions: percentile behaviour cloning's "top X% of timesteps,
        ordered by episode returns" (Chen et al., 2021). ``share=1`` keeps
        everything; data that is one long episode is kept whole whatever the
        share. ``info``: the episodes and transitions kept and the mean
        episode return kept and overall.

        Examples:
            >>> from torchrl_offhrl.data import make_toy_dataset
            >>> ds = make_toy_dataset(num_episodes=4, episode_length=5)
            >>> mask, info = ds.top_return_episodes(0.25)
            >>> int(mask.sum()), info["episodes_kept"]
            (5, 1)
        """
        if not 0.0 < share <= 1.0:
            raise ValueError(f"share must be in (0, 1], got {share}")
        returns = self.episode_returns()
        ep = torch.cumsum(self.episode_starts().long(), 0) - 1  # episode index of every transition
        length = torch.bincount(ep, minlength=returns.numel())
        order = torch.argsort(returns, descending=True, stable=True)
        covered = torch.cumsum(length[order], 0)
        k = min(int((covered < share * len(self)).sum()) + 1, returns.numel())  # the first k episodes reach the share
        keep = torch.zeros(returns.numel(), dtype=torch.bool, device=returns.device)
        keep[order[:k]] = True
        mask = keep[ep]
        info = {"share": float(share), "episodes_kept": k, "episodes": int(returns.numel()), "transitions_kept": int(mask.sum()),
                "return_kept_mean": float(returns[keep].mean()), "return_mean": float(returns.mean())}
        return mask, info

    def returns_to_go(self, gamma: float) -> torch.Tensor:
        """Discounted return from every transition to the end of its episode, ``[N]`` (float64).

        ``G_t = r_t + gamma * G_{t+1}`` inside an episode, ``G = r`` at its last
        transition (a truncated episode is cut there too). Vectorised: the
        rewards weighted by ``gamma ** t`` (``t`` the step within the episode)
        are summed backwards once and each episode's tail subtracted.

        Why not TorchRL's ``Reward2GoTransform``: it is a replay-buffer
        transform applied to sampled trajectories (``[..., T]`` batches with
        their done flags), where this is a statistic of the whole flat dataset
        at once (the reward scale, FQE's targets), episodes delimited by
        ``terminated | truncated``; it would need the dataset split into
        padded trajectories first.

        Examples:
            >>> import torch
            >>> from tensordict import TensorDict
            >>> from torchrl_offhrl.data import OfflineDataset
            >>> td = TensorDict({"observation": torch.zeros(4, 1), "action": torch.zeros(4, 1), "next": {
            ...     "observation": torch.zeros(4, 1), "reward": torch.tensor([[1.0], [2.0], [4.0], [8.0]]),
            ...     "terminated": torch.tensor([[False], [True], [False], [True]]),
            ...     "truncated": torch.zeros(4, 1, dtype=torch.bool)}}, batch_size=[4])
            >>> OfflineDataset(td).returns_to_go(0.5).tolist()
            [2.0, 2.0, 8.0, 8.0]
        """
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        rewards = self.data.get(("next", "reward")).reshape(-1).double()
        if gamma == 0:
            return rewards
        ep = torch.cumsum(self.episode_starts().long(), 0) - 1  # episode index of every transition
        length = torch.bincount(ep)
        first = torch.cumsum(length, 0) - length  # first transition of every episode
        t = torch.arange(rewards.numel(), device=rewards.device) - first[ep]  # step within the episode
        weights = torch.tensor(gamma, dtype=torch.float64, device=rewards.device) ** t
        if not bool((weights > 0).all()):
            raise ValueError(f"returns_to_go: gamma={gamma} ** (episode length {int(length.max())}) underflows float64; use a larger gamma")
        tail = torch.flip(torch.cumsum(torch.flip(rewards * weights, (0,)), 0), (0,))  # tail[i] = sum_{k >= i} w_k
        tail = torch.cat([tail, tail.new_zeros(1)])
        return (tail[: rewards.numel()] - tail[(first + length)[ep]]) / weights

    def return_stats(self) -> dict:
        """Mean/std/min/max and count of the returns of the complete episodes.

        The episodes a collection budget cut short (``unfinished``, listed in
        ``metadata["unfinished_episodes"]``) are left out: their partial
        returns would drag the mean down. When no episode finished at all,
        the stats cover the unfinished ones and ``complete`` is false.
        """
        rets = self.episode_returns(complete_only=True)
        complete = rets.numel() > 0
        if not complete:
            rets = self.episode_returns()
        return {
            "mean": float(rets.mean()),
            "std": float(rets.std()) if rets.numel() > 1 else 0.0,
            "min": float(rets.min()),
            "max": float(rets.max()),
            "episodes": int(rets.numel()),
            "unfinished": len(self.metadata.get("unfinished_episodes") or []),
            "complete": complete,
        }

    def content_hash(self) -> str:
        """A SHA-256 (hex, 16 digits) of the transitions' content: every key's bytes, dtype and shape, in key order.

        Caches and run resumption key on it, so a file replaced at the same
        path by other data is never mistaken for the old one. Computed once
        per dataset object (about 0.3 s per 1M Hopper transitions).

        Examples:
            >>> from torchrl_offhrl.data import make_toy_dataset
            >>> a, b = make_toy_dataset(num_episodes=2, episode_length=5), make_toy_dataset(num_episodes=2, episode_length=5)
            >>> a.content_hash() == b.content_hash()
            True
            >>> b.data["next", "reward"][0] += 1.0
            >>> b._content_hash = None  # (edits in place are not tracked: a changed copy is a new dataset)
            >>> a.content_hash() == b.content_hash()
            False
        """
        if getattr(self, "_content_hash", None) is None:
            import hashlib

            h = hashlib.sha256()
            for key in sorted(self.data.keys(include_nested=True, leaves_only=True), key=str):
                t = self.data.get(key).detach().cpu().contiguous()
                h.update(f"{key}|{t.dtype}|{tuple(t.shape)}|".encode())
                h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
            self._content_hash = h.hexdigest()[:16]
        return self._content_hash

    def to(self, device) -> "OfflineDataset":
        """A new dataset with the transitions and action bounds on ``device``.

        The metadata is copied and ``self`` is left as it is; tensors already
        on ``device`` are shared, not copied (as with :meth:`torch.Tensor.to`).
        """
        data = self.data.to(device)
        if data is self.data:  # same device: a new container, so that edits of one do not reach the other
            data = data.copy()
        out = OfflineDataset(
            data, self.metadata, (self.action_low.to(device), self.action_high.to(device))
        )
        if self._stats is not None:
            out._stats = self._stats.to(device)
        return out

    # ---------------------------------------------------------- replay buffer
    def to_replay_buffer(
        self,
        batch_size: int | None = 256,
        device=None,
        sampler=None,
        transform=None,
    ):
        """A TorchRL ``ReplayBuffer`` already filled with every transition.

        The buffer holds a copy of the data in a ``LazyTensorStorage`` of
        capacity ``len(self)``; ``rb.sample()`` returns a ``TensorDict`` of
        ``batch_size`` transitions with the dataset's keys.

        Args:
            batch_size (int or None): transitions per ``rb.sample()``, in
                ``[1, len(self)]``. ``None`` leaves it to each
                ``rb.sample(batch_size)`` call. Defaults to ``256``.
            device (torch.device or str, optional): where the storage keeps
                the data and returns samples. Defaults to :attr:`device`
                (the CPU when the data has no single device).
            sampler (torchrl.data.replay_buffers.Sampler, optional): how to
                draw indices; defaults to uniform sampling with replacement
                (``RandomSampler``). ``SamplerWithoutReplacement`` gives epochs.
            transform (Transform or callable, optional): applied to every
                sampled batch, as in ``ReplayBuffer``.

        Returns:
            torchrl.data.ReplayBuffer: holding ``len(self)`` transitions.

        Raises:
            ValueError: ``batch_size`` is not in ``[1, len(self)]``.
            TypeError: ``batch_size`` is not an int, or ``sampler`` is not a
                TorchRL ``Sampler``.
            DatasetError: the dataset holds no transitions.

        Examples:
            >>> from torchrl_offhrl.data import make_toy_dataset
            >>> ds = make_toy_dataset(num_episodes=4, episode_length=10)
            >>> rb = ds.to_replay_buffer(batch_size=8)
            >>> len(rb)
            40
            >>> batch = rb.sample()
            >>> batch.batch_size
            torch.Size([8])
            >>> sorted(batch.keys(True), key=str) == sorted(ds.keys(True), key=str)
            True
        """
        from torchrl.data import LazyTensorStorage, ReplayBuffer
        from torchrl.data.replay_buffers.samplers import Sampler

        n = len(self)
        source = self.metadata.get("source", "<in-memory>")
        if n == 0:
            raise DatasetError(f"{source}: the dataset holds no transitions; a replay buffer needs at least one.")
        if batch_size is not None:
            try:
                if isinstance(batch_size, bool):
                    raise TypeError
                batch_size = operator.index(batch_size)  # int, numpy or 0-dim integer tensor
            except TypeError:
                raise TypeError(
                    f"batch_size must be an int in [1, {n}] (or None to give it to rb.sample), "
                    f"got {batch_size!r} of type {type(batch_size).__name__}."
                ) from None
            if batch_size <= 0:
                raise ValueError(
                    f"batch_size must be positive, got {batch_size}; pass the number of transitions "
                    f"per sample, e.g. batch_size=256 (at most {n}, the size of this dataset)."
                )
            if batch_size > n:
                raise ValueError(
                    f"batch_size={batch_size} is larger than the dataset ({n} transitions from {source}); "
                    f"pass batch_size <= {n}, or use a larger dataset."
                )
        if sampler is not None and not (isinstance(sampler, Sampler) or callable(sampler)):
            raise TypeError(
                f"sampler must be a torchrl.data.replay_buffers.Sampler (e.g. RandomSampler() or "
                f"SamplerWithoutReplacement()), got {type(sampler).__name__}."
            )
        if device is None:
            device = self.device or torch.device("cpu")
        storage = LazyTensorStorage(n, device=device)
        rb = ReplayBuffer(storage=storage, sampler=sampler, batch_size=batch_size, transform=transform)
        # the storage logs its creation at INFO on stdout, noise here as it is filled at once
        # (shown still when the user sets TorchRL's level with RL_LOGGING_LEVEL)
        logger = logging.getLogger("torchrl")
        quiet = "RL_LOGGING_LEVEL" not in os.environ
        if quiet:
            logger.addFilter(_drop_storage_init_log)
        try:
            rb.extend(self.data)
        finally:
            if quiet:
                logger.removeFilter(_drop_storage_init_log)
        return rb

    # ------------------------------------------------------------- statistics
    def stats(self, eps: float = 1e-6) -> NormalizationStats:
        """Normalisation statistics (cached); see :class:`NormalizationStats`."""
        if self._stats is None:
            obs = self.data.get("observation").double()
            nobs = self.data.get(("next", "observation")).double()
            rew = self.data.get(("next", "reward")).double()
            delta = nobs - obs
            self._stats = NormalizationStats(
                obs_mean=obs.mean(0).float(),
                obs_std=obs.std(0).clamp_min(eps).float(),
                delta_mean=delta.mean(0).float(),
                delta_std=delta.std(0).clamp_min(eps).float(),
                reward_mean=rew.mean(0).float(),
                reward_std=rew.std(0).clamp_min(eps).float(),
                obs_min=torch.minimum(obs.min(0).values, nobs.min(0).values).float(),
                obs_max=torch.maximum(obs.max(0).values, nobs.max(0).values).float(),
                action_low=self.action_low.clone(),
                action_high=self.action_high.clone(),
            )
        return self._stats

    # ------------------------------------------------------------------ split
    def split(self, val_ratio: float = 0.1, seed: int = 0) -> tuple["OfflineDataset", "OfflineDataset"]:
        """Split by whole episodes into ``(train, validation)``.

        ``val_ratio`` is the fraction of *episodes* held out (at least one
        episode each side when the data has two or more). The split is
        deterministic for a given ``seed``.

        Examples:
            >>> from torchrl_offhrl.data import make_toy_dataset
            >>> ds = make_toy_dataset(num_episodes=10, episode_length=5)
            >>> train, val = ds.split(0.2, seed=0)
            >>> len(train), len(val)
            (40, 10)
            >>> set(train.data["episode"].tolist()).isdisjoint(val.data["episode"].tolist())
            True
        """
        if not 0.0 < val_ratio < 1.0:
            raise ValueError(f"val_ratio must be in (0, 1), got {val_ratio}.")
        ep = self.data.get("episode")
        ids = torch.unique_consecutive(ep)
        n = ids.numel()
        if n < 2:
            raise DatasetError(
                f"{self.metadata.get('source', '<in-memory>')}: cannot split a dataset with "
                f"{n} episode(s) by episode; provide more episodes or skip validation."
            )
        g = torch.Generator().manual_seed(seed)
        perm = ids[torch.randperm(n, generator=g)]
        n_val = min(max(1, int(round(val_ratio * n))), n - 1)
        val_ids = perm[:n_val]
        is_val = torch.isin(ep, val_ids)
        meta_t = dict(self.metadata, split="train")
        meta_v = dict(self.metadata, split="validation")
        bounds = (self.action_low, self.action_high)
        return (
            OfflineDataset(self.data[~is_val], meta_t, bounds),
            OfflineDataset(self.data[is_val], meta_v, bounds),
        )

    @staticmethod
    def concatenate(datasets: Sequence["OfflineDataset"], metadata: dict | None = None) -> "OfflineDataset":
        """Concatenate datasets (e.g. medium + expert), renumbering episodes.

        ``metadata["unfinished_episodes"]`` of the result lists the parts'
        unfinished episodes under their new numbers.
        """
        parts = []
        offset = 0
        unfinished: list[int] = []
        for ds in datasets:
            td = ds.data.clone()
            # a part's last transition always ends its episode, also after save/load
            trunc = td.get(("next", "truncated"))
            trunc[-1] |= ~td.get(("next", "terminated"))[-1]  # "done" is rebuilt by OfflineDataset
            ids, inv = torch.unique_consecutive(td.get("episode"), return_inverse=True)
            td.set("episode", inv + offset)
            cut = ds.metadata.get("unfinished_episodes") or []  # renumbered like the episodes
            unfinished += (torch.isin(ids, torch.as_tensor(cut, dtype=ids.dtype)).nonzero().squeeze(-1) + offset).tolist()
            offset += int(inv.max()) + 1
            parts.append(td)
        low = torch.stack([d.action_low for d in datasets]).min(0).values
        high = torch.stack([d.action_high for d in datasets]).max(0).values
        meta = dict(metadata or datasets[0].metadata)
        meta["unfinished_episodes"] = unfinished
        return OfflineDataset(torch.cat(parts, 0), meta, (low, high))


def make_toy_dataset(
    num_episodes: int = 20,
    episode_length: int = 50,
    obs_dim: int = 3,
    action_dim: int = 2,
    seed: int = 0,
) -> OfflineDataset:
    """A small synthetic dataset with known linear dynamics, for tests and docs.

    ``s' = s + 0.1 * A a`` with a fixed matrix ``A``, reward ``-|s'|^2``,
    actions drawn uniformly from ``[-1, 1]`` times 0.5 (so ``[-0.5, 0.5]`` is
    in-distribution and the corners of ``[-1, 1]`` are not), episodes that
    time out after ``episode_length`` steps.
    """
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(obs_dim, action_dim, generator=g)
    n = num_episodes * episode_length
    obs = torch.empty(n, obs_dim)
    nobs = torch.empty(n, obs_dim)
    act = (torch.rand(n, action_dim, generator=g) * 2 - 1) * 0.5
    i = 0
    for _ in range(num_episodes):
        s = torch.randn(obs_dim, generator=g) * 0.1
        for _ in range(episode_length):
            obs[i] = s
            s = s + 0.1 * (A @ act[i])
            nobs[i] = s
            i += 1
    truncated = torch.zeros(n, 1, dtype=torch.bool)
    truncated[episode_length - 1 :: episode_length] = True
    td = TensorDict(
        {
            "observation": obs,
            "action": act,
            "next": {
                "observation": nobs,
                "reward": -(nobs**2).sum(-1, keepdim=True),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
                "truncated": truncated,
            },
        },
        batch_size=[n],
    )
    meta = {
        "env_id": "Toy-v0",
        "source": "make_toy_dataset",
        "seed": seed,
        "action_low": [-1.0] * action_dim,
        "action_high": [1.0] * action_dim,
    }
    return OfflineDataset(td, meta)


def check_finite(td: TensorDict, source: str) -> None:
    """Raise :class:`DatasetError` naming the first key holding NaN or inf."""
    for key, value in td.items(include_nested=True, leaves_only=True):
        if value.is_floating_point() and not torch.isfinite(value).all():
            bad = (~torch.isfinite(value)).nonzero()
            first = bad[0].tolist()
            raise DatasetError(
                f"{source}: key {key!r} (shape {tuple(value.shape)}) holds "
                f"{int((~torch.isfinite(value)).sum())} NaN/inf value(s), the first at index "
                f"{first}. Remove or repair those transitions before loading."
            )


#: set to 1 to load data whose values :func:`check_plausible` finds implausible (you know your data)
TRUST_DATA_ENV = "TORCHRL_OFFHRL_TRUST_DATA"
#: how far from a column's median, in units of its robust range (the 0.1-99.9 percentile span), a value is implausible
OUTLIER_RANGES = 1000.0


def check_plausible(td: TensorDict, source: str, ranges: float = OUTLIER_RANGES) -> None:
    """Raise :class:`DatasetError` naming the first key holding values far outside the rest of its column.

    A robust outlier rule, per column (each dimension of each floating key):
    implausible is farther from the column's median than ``ranges`` times its
    robust range (the span between its 0.1 and 99.9 percentiles; at least
    ``1e-2 * (|median| + 1)``, so a near-constant column is not flagged for
    noise or a rare event: a column of zeros may hold values up to 10). At 1000 ranges a reading of 1e30 (a sensor glitch, a unit
    error, an uninitialised buffer) is caught while heavy-tailed data is not:
    of 100,000 standard Cauchy draws the largest sits ~50 ranges out. The
    percentiles come from at most 100,000 rows (a fixed draw, so the check is
    deterministic); the test runs on every row. Set ``TORCHRL_OFFHRL_TRUST_DATA=1``
    to load such data anyway.
    """
    if os.environ.get(TRUST_DATA_ENV, "").strip() not in ("", "0"):
        return
    for key, value in td.items(include_nested=True, leaves_only=True):
        if not value.is_floating_point() or value.numel() == 0:
            continue
        x = value.reshape(value.shape[0], -1).double()
        rows = x if x.shape[0] <= 100_000 else x[torch.randperm(x.shape[0], generator=torch.Generator().manual_seed(0))[:100_000]]
        q = torch.quantile(rows, torch.tensor([0.001, 0.5, 0.999], dtype=x.dtype), dim=0)
        median = q[1]
        spread = torch.maximum(q[2] - q[0], 1e-2 * (median.abs() + 1))
        far = (x - median).abs() > ranges * spread
        if bool(far.any()):
            first = far.nonzero()[0].tolist()
            raise DatasetError(
                f"{source}: key {key!r} (shape {tuple(value.shape)}) holds {int(far.sum())} implausible value(s), the first "
                f"{float(x[first[0], first[1]]):.4g} at index {first} (column median {float(median[first[1]]):.4g}, "
                f"99.8% of the column within {float(q[0, first[1]]):.4g}..{float(q[2, first[1]]):.4g}). Remove or repair those "
                f"transitions, or set {TRUST_DATA_ENV}=1 to load the data as it is."
            )
