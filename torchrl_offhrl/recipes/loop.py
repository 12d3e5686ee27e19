"""The training loop every setting runs, and the phases it is handed.

A run is a list of :class:`Phase` objects run in order by one
:class:`TrainingLoop`: an offline run has one phase (batches from the model
env, or minibatches of the dataset for the agents that learn from it), a
transfer run two (offline, then online fine-tuning in the real env on the
new task; or the online phase alone for its from-scratch baseline), an
online run one (the real env). What differs between settings is in the
phase (where its batches come from, its budget and evaluator, how it starts)
and in the setting that builds the phases
(:func:`~torchrl_offhrl.recipes.train.build_setting`); the loop itself
has no mode: it updates the agent on every batch, logs, and every ``every``
steps evaluates, keeps the snapshots asked for, offers the policy to the
offline policy selection and checkpoints.

Where a phase's batches come from (:func:`env_collector`: a TorchRL
collector on the composed model env offline, or on the real env online;
:func:`dataset_batches`: minibatches of the dataset itself) and how a
resumed run puts those sources back where they stood
(:func:`source_state`, :func:`restore_source`) are at the end of this
module: the loop only iterates over batches and hands them to
``agent.update``.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..utils import save_torch_file
from .summary import fmt_number

__all__ = [
    "OfflinePhase", "OnlinePhase", "Phase", "TrainingLoop", "dataset_batches", "dataset_replay_buffer", "env_collector", "model_env_metrics",
    "online_metrics", "restore_source", "source_state",
]

#: dataset agents (one gradient step per batch) log the mean of their metrics over this many updates
LOG_EVERY_UPDATES = 100


@dataclass
class Phase:
    """One stretch of training: where batches come from, its budget, its evaluation.

    Args:
        name: written into its evaluation records as ``phase`` (None: the
            run's only phase, no ``phase`` key).
        evaluator: an :class:`~torchrl_offhrl.recipes.evaluation.Evaluator`.
        total: the phase's budget in the run's unit (frames or updates).
        every: its evaluation period, in the same unit.
        batches: ``(remaining, frames_done) -> iterable of batches``: a
            TorchRL collector (shut down after the phase) or the dataset's
            minibatches.
        desc: the progress bar's label.
        final_dir: where the last evaluation writes the agent's files.
        batch_metrics: ``batch -> dict`` logged with each update (or None).
        seed_env: the env whose seed is set to ``seed + frames`` when the phase (re)starts (or None).
        seed: the run's seed.
        selects: its evaluations are candidates of the offline policy selection.
    """

    name: str | None
    evaluator: object
    total: int
    every: int
    batches: Callable[[int, int], Iterable]
    desc: str
    final_dir: Path
    batch_metrics: Callable | None = None
    seed_env: object = None
    seed: int = 0
    selects: bool = True
    #: the step the phase's budget and evaluations count from (set by :meth:`begin`)
    start: int = field(default=0, init=False)

    def begin(self, loop: TrainingLoop) -> int:
        """Prepare the phase (first evaluations, seeds); returns the steps still to train."""
        raise NotImplementedError


@dataclass
class OfflinePhase(Phase):
    """The phase from step 0: the untrained agent is evaluated first (``at_start``); done when ``done_when`` records exist.

    ``done_when``: a later phase's name; once a record of it exists (a
    transfer run resumed in its online phase) this phase has nothing left.
    A run with nothing left to train and no record yet is evaluated once
    (its final files).
    """

    at_start: bool = True
    done_when: str | None = None

    def begin(self, loop: TrainingLoop) -> int:
        run = loop.run
        done = self.done_when is not None and any(r.get("phase") == self.done_when for r in run.records)
        remaining = 0 if done else max(self.total - run.step, 0)
        if self.seed_env is not None:
            self.seed_env.set_seed(self.seed + run.frames)
        if remaining > 0 and not run.records and self.at_start:
            # the untrained agent: the start of the learning curve (with the CVAE: latent 0, decoded through the latent origin)
            loop.keep(loop.evaluate(self.evaluator, phase=self.name, selects=self.selects))
        elif remaining == 0 and not run.records:
            loop.keep(loop.evaluate(self.evaluator, save_to=self.final_dir, phase=self.name, selects=self.selects))
        return remaining


@dataclass
class OnlinePhase(Phase):
    """A phase that starts where the previous one ended (its *switch*): the agent is evaluated there, on the new task.

    ``new_task``: call ``agent.new_task()`` at the switch (after an offline
    phase; not for a run that starts online). A resumed run finds its switch
    in the records.
    """

    new_task: bool = True

    def begin(self, loop: TrainingLoop) -> int:
        run = loop.run
        switch = next((r["frames"] for r in run.records if r.get("phase") == self.name), None)
        if switch is None:  # the switch: the agent as it starts on the new task (after the offline phase's last evaluation, on the old task)
            switch = run.frames
            if self.new_task:
                loop.agent.new_task()
            loop.keep(loop.evaluate(self.evaluator, phase=self.name, selects=self.selects))
        self.start = switch
        remaining = max(switch + self.total - run.frames, 0)
        if remaining > 0 and self.seed_env is not None:
            self.seed_env.set_seed(self.seed + run.frames)
        return remaining


@dataclass
class _PhaseProgress:
    """Where a phase's training stands between batches (:meth:`TrainingLoop.start`, :meth:`TrainingLoop.account`)."""

    bar: object
    next_eval: int
    pending: dict = field(default_factory=dict)
    pending_n: int = 0


class TrainingLoop:
    """Update ``agent`` on every batch of each phase; evaluate, log, snapshot and checkpoint every ``phase.every`` steps.

    Args:
        run: the :class:`~torchrl_offhrl.recipes.rundir.RunDirectory` (its
            counters, records, selector and checkpoints).
        agent: the agent (:class:`~torchrl_offhrl.agents.Agent`).
        logger: a TorchRL logger, or None.
        title: the evaluation plots' title.
        snapshots: steps at which the agent's state is kept for good (``snapshot-<step>.pt``).
        t_start: the run's start time (records' ``wall_s``).
        progress: show progress bars.
        on_record: called with every evaluation record as it is made (e.g.
            a Ray Tune trial reporting it, so that a scheduler can stop it early).

    ``timing["update_time_s"]``: the time spent in ``agent.update``.
    """

    def __init__(self, run, agent, *, logger=None, title: str = "", snapshots=(), t_start: float | None = None, progress: bool = True,
                 env_label: str = "", on_record=None):
        self.run, self.agent, self.logger, self.title = run, agent, logger, title
        self.on_record = on_record
        self.snapshots = {int(x) for x in snapshots}
        self.t_start = time.time() if t_start is None else t_start
        self.progress = progress
        self.env_label = env_label
        self.timing = {"update_time_s": 0.0}
        self.source = None  # the phase's batch source while it trains (its state goes into each checkpoint)

    def evaluate(self, evaluator, save_to=None, phase: str | None = None, selects: bool = True) -> dict:
        """One evaluation record of the agent as it is now (and, with ``selects``, offered to the run's policy selection)."""
        run = self.run
        rec = {"frames": run.frames, "updates": run.updates, "step": run.step, "wall_s": round(time.time() - self.t_start, 1)}
        if phase is not None:
            rec["phase"] = phase
        rec.update(evaluator(self.agent, save_to=save_to, title=self.title))
        if selects:
            run.selector.consider(rec, self.agent, run.step)
        return rec

    def keep(self, rec: dict) -> None:
        """Keep an evaluation record: appended to the run's records, checkpointed with the agent, then reported."""
        self.run.records.append(rec)
        self.run.checkpoint(self.agent, source=source_state(self.source))
        self.report(rec)

    def _next_eval(self, phase: Phase) -> int:
        """The step of the phase's next evaluation after the run's current step (every ``phase.every`` steps from its start)."""
        return phase.start + ((self.run.step - phase.start) // phase.every + 1) * phase.every

    def report(self, rec: dict) -> None:
        """Hand a kept record to ``on_record`` (after its checkpoint: a trial stopped there resumes from it)."""
        if self.on_record is not None:
            self.on_record(rec)

    def run_phase(self, phase: Phase) -> None:
        """:meth:`Phase.begin`, then train on its batches until its budget is spent."""
        remaining = phase.begin(self)
        if remaining <= 0:
            return
        resumed, self.run.resume_state = self.run.resume_state, None
        if resumed is not None and resumed.get("source") is None:  # checkpointed with no source running (the evaluation at
            torch.set_rng_state(resumed["rng"])                    # step 0, a dataset agent): the source starts from this RNG
        source = phase.batches(remaining, self.run.frames)
        if resumed is not None and resumed.get("source") is not None:  # where the checkpointed run's source stood, and the RNG it
            restore_source(source, resumed["source"])                  # had there: the batches the uninterrupted run drew
            torch.set_rng_state(resumed["rng"])
        self.source = source
        try:
            self._train(phase, source)
        finally:
            self.source = None
            if hasattr(source, "shutdown"):
                source.shutdown()

    def _train(self, phase: Phase, source) -> None:
        st = self.start(phase)
        try:
            for batch in source:
                t0 = time.time()
                self.agent.set_progress((self.run.step - phase.start) / phase.total)  # before this batch counts: schedules (e.g. anneal_lr) follow the phase's budget
                metrics = self.agent.update(batch)
                self.timing["update_time_s"] += time.time() - t0
                if self.account(st, phase, batch, metrics):
                    break
        finally:
            st.bar.close()

    def start(self, phase: Phase) -> _PhaseProgress:
        """The bookkeeping of a phase about to train (its progress bar, next evaluation, pending logs): for :meth:`account`."""
        from tqdm.auto import tqdm

        run = self.run
        bar = tqdm(total=phase.total, initial=min(run.step - phase.start, phase.total), desc=phase.desc, disable=not self.progress, unit=run.unit[:-1])
        return _PhaseProgress(bar=bar, next_eval=self._next_eval(phase))

    def evaluation_due(self, st: _PhaseProgress, phase: Phase, steps: int = 1) -> bool:
        """Whether the next batch (``steps`` more steps) ends at an evaluation (a batched driver syncs its agents first)."""
        return self.run.step + steps >= min(st.next_eval, phase.start + phase.total)

    def account(self, st: _PhaseProgress, phase: Phase, batch, metrics: dict) -> bool:
        """Count an update the agent took on ``batch`` (``metrics``: what it returned): counters, logs, progress, and at an
        evaluation step the evaluation, snapshots and checkpoint. True when the phase's budget is spent."""
        run, logger = self.run, self.logger
        unit = run.unit
        per_update = unit == "updates"  # dataset agents: one gradient step per batch, logged as means over LOG_EVERY_UPDATES
        end = phase.start + phase.total
        before = run.step
        run.frames += batch.numel()
        metrics = dict(metrics)
        run.updates += int(metrics.pop("updates"))
        if phase.batch_metrics is not None:
            metrics.update(phase.batch_metrics(batch))
        for k, v in metrics.items():  # (sum, count) per key: some metrics come with some updates only (e.g. a delayed actor)
            total_k, n_k = st.pending.get(k, (0.0, 0))
            st.pending[k] = (total_k + v, n_k + 1)
        st.pending_n += 1
        if logger is not None and (not per_update or st.pending_n >= LOG_EVERY_UPDATES or run.step >= end):
            for k, (v, n) in st.pending.items():  # dataset agents: the mean over LOG_EVERY_UPDATES updates (their 0-dim tensors, read now)
                logger.log_scalar(k, float(v) / n, step=run.step)
        if not per_update or st.pending_n >= LOG_EVERY_UPDATES:
            st.pending, st.pending_n = {}, 0
        st.bar.update(run.step - before)
        if run.step >= st.next_eval or run.step >= end:
            rec = self.evaluate(phase.evaluator, save_to=phase.final_dir if run.step >= end else None, phase=phase.name, selects=phase.selects)
            self._report(rec, st.bar, unit)
            self._snapshot(rec)  # before the checkpoint moves on
            self.keep(rec)
            st.next_eval = self._next_eval(phase)
            if run.step >= end:
                return True
        return False

    def _report(self, rec: dict, bar, unit: str) -> None:
        if self.logger is not None:
            for k in ("return_mean", "normalized_d4rl", "model_return_mean", "model_real_gap", "success_rate"):
                if rec.get(k) is not None:
                    self.logger.log_scalar(f"eval/{k}", rec[k], step=self.run.step)
        score = "" if rec["normalized_d4rl"] is None else f" (D4RL-normalised {rec['normalized_d4rl']:.1f})"
        if "success_per_goal" in rec:
            score = f", success per goal {' '.join(f'{x:.2f}' for x in rec['success_per_goal'])}"
        bar.set_postfix(ret=f"{rec['return_mean']:.0f}", score=fmt_number(rec["normalized_d4rl"]))
        where = self.env_label + (f" ({rec['task']} task)" if "task" in rec else "")
        bar.write(f"[{self.run.step} {unit}] real {where} return {rec['return_mean']:.1f} ± {rec['return_std']:.1f}{score}")

    def _snapshot(self, rec: dict) -> None:
        run = self.run
        for snap in sorted(x for x in self.snapshots if x <= run.step and not (run.path / f"snapshot-{x}.pt").is_file()):
            # a state kept for good (e.g. UOF's 20-epoch policy), at the first evaluation at or past it, before the checkpoint
            # moves on (a run killed in between takes it again on resume)
            save_torch_file({"agent": self.agent.state_dict(), "frames": run.frames, "updates": run.updates, "step": run.step, "record": rec},
                            run.path / f"snapshot-{snap}.pt")


# ---- where batches come from --------------------------------------------------------------------------------------------

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
