"""Where training batches come from: a TorchRL collector on an env (the composed model env offline, the real env
while fine-tuning online in the transfer setting), or the dataset itself.

The loop only iterates over batches and hands them to ``agent.update``.
"""
from __future__ import annotations

__all__ = ["dataset_batches", "dataset_replay_buffer", "env_collector", "model_env_metrics", "online_metrics", "restore_source", "source_state"]


def env_collector(env, agent, frames: int, frames_done: int = 0, device="cpu"):
    """A :class:`~torchrl.collectors.Collector` of ``frames`` frames of ``agent.policy`` on ``env`` (model env or real env).

    Batches of ``agent.frames_per_batch`` frames (``[envs, steps]``); the first
    ``agent.init_random_frames`` frames of the run (those not yet collected
    before ``frames_done``) use uniformly random actions: none when resuming,
    nor in a transfer run's online phase (its offline frames count as done).
    """
    from torchrl.collectors import Collector

    return Collector(
        env,
        agent.policy,
        frames_per_batch=agent.frames_per_batch,
        total_frames=frames,
        init_random_frames=0 if frames_done else agent.init_random_frames,
        split_trajs=False,
        auto_register_policy_transforms=False,  # the envs are built with the transforms they need
        device=device,
    )


def model_env_metrics(batch) -> dict[str, float]:
    """What a model-env batch says about the P-MDP: the mean return of the episodes that ended, the share of penalised steps."""
    keys = batch.keys(True)
    out = {}
    done = batch["next", "done"]
    if done.any():
        out["train/model_episode_return"] = float(batch["next", "episode_reward"][done].mean()) if ("next", "episode_reward") in keys else float("nan")
    out["train/penalized_rate"] = float(batch["next", "penalized"].float().mean()) if ("next", "penalized") in keys else float("nan")
    return out


def online_metrics(batch) -> dict[str, float]:
    """What a real-env batch of the online phase says: the mean return of the episodes that ended in it (on the task trained on)."""
    done = batch["next", "done"]
    if done.any() and ("next", "episode_reward") in batch.keys(True):
        return {"train/online_episode_return": float(batch["next", "episode_reward"][done].mean())}
    return {}


def dataset_replay_buffer(data, agent, device="cpu"):
    """The dataset once in a TorchRL replay buffer on ``device``, sampling ``agent.batch_size`` transitions (at most the dataset's size)."""
    return data.to_replay_buffer(batch_size=min(int(agent.batch_size), len(data)), device=device)


def dataset_batches(data, agent, updates: int, device="cpu"):
    """``updates`` minibatches of ``agent.batch_size`` transitions drawn uniformly (with replacement) from ``data``.

    The dataset goes once into a TorchRL replay buffer
    (:meth:`~torchrl_offhrl.data.OfflineDataset.to_replay_buffer`) on
    ``device``; sampling uses torch's global RNG, which a resumed run restores
    from its checkpoint.
    """
    rb = dataset_replay_buffer(data, agent, device)
    for _ in range(int(updates)):
        yield rb.sample()


def _model_env(source):
    """The model env a collector steps, or None: a model env keeps its whole state in the tensordict it steps (plus its
    RNG), where a real env's simulator holds its own, which a restored carrier would contradict."""
    from ..envs import PessimisticModelEnv  # BlockStackModelEnv is one

    env = getattr(getattr(source, "env", None), "base_env", None)
    return env if isinstance(env, PessimisticModelEnv) else None


def source_state(source) -> dict | None:
    """What a batch source carries from one batch to the next, for a checkpoint: a collector's carrier (the envs' current
    states, e.g. the model env's observation, member and step) and its model env's RNG; None for other sources (the
    dataset's minibatches draw from torch's global RNG only, which the checkpoint keeps; a real env's collector)."""
    carrier, env = getattr(source, "_carrier", None), _model_env(source)  # TorchRL's Collector: its carrier is not
    if carrier is None or env is None:                                    # serialisable in general, a model env's is
        return None
    return {"carrier": carrier.cpu().to_dict(),  # plain nested tensors: what torch.load(weights_only=True) reads back
            "env_rng": env._rng.get_state()}


def restore_source(source, state: dict | None) -> bool:
    """Put a new source where a checkpointed one stood (:func:`source_state`); False when it cannot (another kind of source,
    or a carrier of other keys or shape: the source then starts from fresh resets, as TorchRL's own collectors do)."""
    carrier, env = getattr(source, "_carrier", None), _model_env(source)
    if not state or carrier is None or env is None or "carrier" not in state:
        return False
    from tensordict import TensorDict

    saved = TensorDict.from_dict(state["carrier"], batch_size=carrier.batch_size)
    keys = list(carrier.keys(True, True))  # what a fresh carrier holds (the saved one may also hold the policy's last outputs)
    if any(k not in saved.keys(True, True) or saved.get(k).shape != carrier.get(k).shape for k in keys):
        return False
    saved = saved.select(*keys)
    carrier.update_(saved.to(carrier.device) if carrier.device is not None else saved)
    if "env_rng" in state:
        env._rng.set_state(state["env_rng"])
    return True
