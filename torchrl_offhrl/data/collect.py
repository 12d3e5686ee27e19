"""Collect offline datasets by rolling a policy out in a real Gymnasium env."""
from __future__ import annotations

import importlib.metadata as md
import time
from typing import Callable

import torch
from .dataset import OfflineDataset

__all__ = ["collect_dataset", "combine_levels", "make_gym_env", "package_versions"]


def make_gym_env(env_id: str, num_envs: int = 1, device: str | torch.device = "cpu", **kwargs):
    """A TorchRL env over Gymnasium's *synchronous* vector env, float32 throughout.

    Synchronous vectorisation (no subprocesses) is the faster choice on small
    machines for MuJoCo envs whose step costs microseconds. ``num_envs=1``
    still returns a batched env of batch size ``[1]``. The block-stacking
    envs (``BlockStack2-v0``, ``BlockStack3-v0``) are batched by TorchRL
    instead (:func:`~torchrl_offhrl.blockstack.make_blockstack_env`).
    """
    import gymnasium as gym
    from torchrl.envs import DoubleToFloat, GymWrapper, TransformedEnv

    from ..blockstack import make_blockstack_env
    from ..registry import task_of

    if task_of(env_id).goal_conditioned:  # dict observations: batched by TorchRL (see make_blockstack_env)
        return make_blockstack_env(env_id, num_envs=num_envs, device=device, **kwargs)
    venv = gym.make_vec(
        env_id,
        num_envs=num_envs,
        vectorization_mode="sync",
        vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP},
        **kwargs,
    )
    env = GymWrapper(venv, device=device)  # vector envs come back already transformed
    if isinstance(env, TransformedEnv):
        env.append_transform(DoubleToFloat())
        return env
    return TransformedEnv(env, DoubleToFloat())


def collect_dataset(
    env_id: str,
    num_transitions: int,
    policy: Callable | None = None,
    num_envs: int = 8,
    seed: int = 0,
    progress: bool = True,
    metadata: dict | None = None,
) -> OfflineDataset:
    """Roll ``policy`` out in ``env_id`` for ``num_transitions`` steps in total.

    Args:
        env_id: a Gymnasium id, e.g. ``"Hopper-v5"``.
        num_transitions: transitions to record (rounded up to a multiple of
            ``num_envs``).
        policy: a TensorDict module writing ``"action"``; ``None`` draws
            actions uniformly from the action box (D4RL's "random").
        num_envs: environments stepped side by side.
        seed: seeds the envs and the random policy; the same seed gives the
            same dataset.
        progress: show a tqdm bar.

    Each environment's stream is cut into episodes at ``done``; the last,
    unfinished episode of each stream ends with ``truncated=True`` and its
    ``episode`` value is listed in ``metadata["unfinished_episodes"]``.
    ``metadata["returns"]`` (mean/std/min/max/episodes) covers the complete
    episodes only (see :meth:`OfflineDataset.return_stats`).
    """
    from torchrl.collectors import Collector
    from tqdm.auto import tqdm

    env = make_gym_env(env_id, num_envs=num_envs)
    steps_per_env = -(-num_transitions // num_envs)
    chunk = min(steps_per_env, 1000)
    # seed before the collector is built: it resets the env at construction
    env.set_seed(seed)
    torch.manual_seed(seed)
    collector = Collector(
        env,
        policy,
        frames_per_batch=chunk * num_envs,
        total_frames=steps_per_env * num_envs,
        split_trajs=False,
        auto_register_policy_transforms=False,  # the envs are built with the transforms they need
    )
    keys = ["observation", "action", ("next", "observation"), ("next", "reward"), ("next", "terminated"), ("next", "truncated")]
    parts = []
    t0 = time.time()
    bar = tqdm(total=steps_per_env * num_envs, desc=f"collect {env_id}", disable=not progress, unit="step")
    left = steps_per_env * num_envs
    for batch in collector:  # the collector rounds its budget up to whole batches
        parts.append(batch.select(*keys).cpu())
        bar.update(min(batch.numel(), left))
        left -= batch.numel()
    bar.close()
    collector.shutdown()
    data = torch.cat(parts, dim=-1)  # [num_envs, T] in time order per env
    data = data[:, :steps_per_env]
    trunc = data.get(("next", "truncated")).clone()
    term = data.get(("next", "terminated"))
    cut = ~(term[:, -1] | trunc[:, -1]).squeeze(-1)  # streams whose last episode the budget cut short
    trunc[:, -1] |= ~term[:, -1]
    data.set(("next", "truncated"), trunc)
    data = data.reshape(-1)
    act_spec = env.action_spec
    low = act_spec.space.low.reshape(-1, act_spec.shape[-1])[0].float()
    high = act_spec.space.high.reshape(-1, act_spec.shape[-1])[0].float()
    env.close()
    meta = {
        "env_id": env_id,
        "seed": seed,
        "num_envs": num_envs,
        "policy": "uniform-random" if policy is None else type(policy).__name__,
        "collection_seconds": round(time.time() - t0, 2),
        "versions": package_versions(),
    }
    meta.update(metadata or {})
    ds = OfflineDataset(data, meta, (low, high))
    last = (torch.arange(1, num_envs + 1) * steps_per_env - 1)[cut]  # flat index of each cut stream's last step
    ds.metadata["unfinished_episodes"] = ds.data.get("episode")[last].tolist()
    ds.metadata["returns"] = ds.return_stats()
    return ds


def package_versions() -> dict:
    out = {}
    for pkg in ("torch", "torchrl", "tensordict", "gymnasium", "mujoco"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:  # pragma: no cover
            out[pkg] = None
    return out


def combine_levels(parts: list[OfflineDataset], seed: int, keep: tuple[str, ...] = ("env_id", "num_envs", "versions"),
                   part_keys: tuple[str, ...] = ("policy", "returns", "collection_seconds")) -> OfflineDataset:
    """medium + expert -> medium-expert (D4RL's protocol): episodes renumbered and kept apart, the parts described in the metadata.

    The result's metadata holds ``keep`` from the medium part, ``seed``,
    ``policy`` and ``policy_card`` of both parts, ``parts`` (per part: its
    transitions and ``part_keys`` of its metadata), the summed
    ``collection_seconds`` and the ``returns`` of the whole.
    """
    med, exp = parts
    meta = {k: med.metadata[k] for k in keep if k in med.metadata}
    meta.update({
        "seed": seed,
        "policy": f"{med.metadata.get('policy')} + {exp.metadata.get('policy')}",
        "policy_card": {"medium": med.metadata.get("policy_card"), "expert": exp.metadata.get("policy_card")},
        "parts": {name: {"transitions": len(p), **{k: p.metadata.get(k) for k in part_keys}} for name, p in (("medium", med), ("expert", exp))},
        "collection_seconds": round(sum(p.metadata.get("collection_seconds", 0.0) for p in parts), 2),
    })
    ds = OfflineDataset.concatenate(parts, meta)
    ds.metadata["returns"] = ds.return_stats()
    return ds
