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
    """The model env a collector steps, or None (a real env's collector)."""
    from ..envs import PessimisticModelEnv  # BlockStackModelEnv is one

    env = getattr(getattr(source, "env", None), "base_env", None)
    return env if isinstance(env, PessimisticModelEnv) else None


def _simulators(source) -> list | None:
    """The MuJoCo envs behind a real env's collector, in batch order (Gymnasium's synchronous vector env, which
    :func:`~torchrl_offhrl.data.make_gym_env` builds), or None when there are none to reach."""
    from torchrl.envs import GymWrapper

    base = getattr(getattr(source, "env", None), "base_env", None)
    if not isinstance(base, GymWrapper):  # a model env, or envs batched by TorchRL (block stacking): nothing to reach
        return None
    envs = getattr(base._env, "envs", None)
    if not envs or not all(hasattr(getattr(e, "unwrapped", None), "data") and hasattr(e.unwrapped, "model") for e in envs):
        return None
    return list(envs)


def _simulator_state(env) -> dict:
    """One Gymnasium MuJoCo env's whole state: the physics (MuJoCo's integration state: time, positions, velocities,
    actuator activations, controls and the solver's warm start), the steps its time limit has counted, its reset RNG."""
    import mujoco
    import numpy as np
    import torch

    sim = env.unwrapped
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    physics = np.empty(mujoco.mj_stateSize(sim.model, spec))
    mujoco.mj_getState(sim.model, sim.data, physics, spec)
    elapsed = int(env.get_wrapper_attr("_elapsed_steps")) if env.has_wrapper_attr("_elapsed_steps") else None  # TimeLimit's count
    return {"physics": torch.from_numpy(physics), "elapsed_steps": elapsed, "np_random": sim.np_random.bit_generator.state}


def _set_simulator_state(env, state: dict) -> None:
    import mujoco

    sim = env.unwrapped
    mujoco.mj_setState(sim.model, sim.data, state["physics"].numpy(), mujoco.mjtState.mjSTATE_INTEGRATION)
    if state["elapsed_steps"] is not None:
        env.set_wrapper_attr("_elapsed_steps", state["elapsed_steps"], force=False)
    sim.np_random.bit_generator.state = state["np_random"]


def source_state(source) -> dict | None:
    """What a batch source carries from one batch to the next, for a checkpoint: a collector's carrier (the envs' current
    states as the agent sees them, e.g. the model env's observation, member and step) and, behind it, the model env's RNG
    or the real envs' simulators (:func:`_simulator_state`); None for other sources (the dataset's minibatches draw from
    torch's global RNG only, which the checkpoint keeps)."""
    carrier, env, sims = getattr(source, "_carrier", None), _model_env(source), _simulators(source)  # TorchRL's Collector
    if carrier is None or (env is None and sims is None):
        return None
    state = {"carrier": carrier.cpu().to_dict()}  # plain nested tensors: what torch.load(weights_only=True) reads back
    if env is not None:
        state["env_rng"] = env._rng.get_state()
    else:
        state["simulators"] = [_simulator_state(e) for e in sims]
    return state


def restore_source(source, state: dict | None) -> bool:
    """Put a new source where a checkpointed one stood (:func:`source_state`); False when it cannot (another kind of source,
    or a carrier of other keys or shape: the source then starts from fresh resets, as TorchRL's own collectors do)."""
    carrier, env, sims = getattr(source, "_carrier", None), _model_env(source), _simulators(source)
    if not state or carrier is None or "carrier" not in state:
        return False
    if (env is None or "env_rng" not in state) and (sims is None or len(state.get("simulators") or []) != len(sims)):
        return False
    from tensordict import TensorDict

    saved = TensorDict.from_dict(state["carrier"], batch_size=carrier.batch_size)
    keys = list(carrier.keys(True, True))  # what a fresh carrier holds (the saved one may also hold the policy's last outputs)
    if any(k not in saved.keys(True, True) or saved.get(k).shape != carrier.get(k).shape for k in keys):
        return False
    saved = saved.select(*keys)
    carrier.update_(saved.to(carrier.device) if carrier.device is not None else saved)
    if env is not None:
        env._rng.set_state(state["env_rng"])
    else:
        for sim, sim_state in zip(sims, state["simulators"]):
            _set_simulator_state(sim, sim_state)
    return True
