"""Several seeds of one config trained as one computation: ``offhrl train algo=iql --seeds 4 5 6 7 8``.

Each seed is still a run of its own: its own run directory (the config's
default directory with that seed, or ``run_dir/seed<s>``), setting, agent,
evaluations, logs, checkpoints and summary, so ``offhrl report`` reads them
as it reads separate runs, and each resumes from its checkpoint. What is
shared: the dataset (one replay buffer) and the updates, which
:class:`~torchrl_offhrl.agents.seeds.SeedBatch` takes for all seeds at once.
Each seed's minibatches come from the RNG stream its own run would use (the
state after its phase began), and its evaluations, snapshots and checkpoints
happen with that stream in place: the records match those of separate runs
up to the floating-point rounding of the batched products
(``tests/test_seed_batch.py``).

The agents that learn from the dataset (BC, TD3+BC, IQL, CQL), and the
on-policy agents on the model env (PPO, MOC; an offline run of one phase):
their seeds collect from one model env of ``N x E`` envs (``E =
collector.num_envs`` per seed, seed ``i`` owning envs ``i E .. (i + 1) E - 1``)
with their policies run as one, and each seed's part of a batch is its run's
batch (:class:`~torchrl_offhrl.agents.seeds.OnPolicySeedBatch`). There the
collection's random draws come from one stream for all seeds, so a seed's
run is a run of its config, not a replay of its separate run (its
untrained evaluation is the same; ``tests/test_seed_batch.py``). On a task
whose episodes never end early (HalfCheetah, ``Task.terminates``) the
seeds' evaluations after the untrained one run as one rollout
(:class:`~torchrl_offhrl.recipes.evaluation.SeedsEvaluation`): each seed's
policy from its own run's start states, but the deterministic episodes
follow a separate run's only to floating-point rounding (which a long
chaotic episode amplifies), and the sampled one's draws come from the
batch's stream: those records are the same policies' evaluations, not
replays of separate runs'. SAC and MOPO batch on the model env as PPO and MOC do, each
seed filling its own replay buffer
(:class:`~torchrl_offhrl.agents.seeds.OffPolicySeedBatch`). MOReL-style (PPO
with an adaptive KL penalty) and the transfer and online settings run one
seed per run (``offhrl sweep``).
"""
from __future__ import annotations

import time
from contextlib import ExitStack
from collections.abc import Mapping, Sequence

import torch

from ..agents.seeds import SeedBatch
from ..utils import to_plain
from .config import learns_from_dataset, model_env_batch
from .schema import validate_config
from .loop import dataset_replay_buffer

__all__ = ["RunsApart", "batchable", "refusal", "seed_configs", "train_seed_configs", "train_seeds"]


class RunsApart(ValueError):
    """The seeds' runs stand at different steps (resumed from different points): they cannot take one batch.

    ``steps``: where each run stands (its checkpoint's step, in ``unit``: ``"frames"`` or ``"updates"``)."""

    def __init__(self, message: str, steps: Sequence[int] = (), unit: str = "frames"):
        super().__init__(message)
        self.steps, self.unit = list(steps), unit


def seed_configs(cfg: Mapping, seeds: Sequence[int]) -> list[dict]:
    """One config per seed: ``seed`` set, ``seeds`` removed, ``run_dir`` (when given) suffixed ``/seed<s>``."""
    cfg = to_plain(cfg)
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds) or any(s < 0 for s in seeds):
        raise ValueError(f"seeds must be distinct non-negative integers, got {seeds}")
    out = []
    for s in seeds:
        c = {k: v for k, v in cfg.items() if k != "seeds"}
        c["seed"] = s
        if cfg.get("run_dir"):
            c["run_dir"] = f"{cfg['run_dir']}/seed{s}"
        out.append(c)
    return out


class _Lane:
    """One seed's run inside a batch: its prepared run and its own RNG stream (swapped in around its bookkeeping)."""

    def __init__(self, prepared):
        self.r = prepared
        self.rng = torch.Generator()

    def __enter__(self):
        self._outer = torch.get_rng_state()
        torch.set_rng_state(self.rng.get_state())
        return self

    def __exit__(self, *exc):
        self.rng.set_state(torch.get_rng_state())
        torch.set_rng_state(self._outer)


def train_seeds(cfg: Mapping, seeds: Sequence[int], progress: bool = True) -> list[dict]:
    """Train one run per seed, the updates of all seeds batched (:class:`~torchrl_offhrl.agents.seeds.SeedBatch`); each run's summary."""
    return train_seed_configs(seed_configs(cfg, seeds), progress=progress)


def batchable(cfg: Mapping) -> bool:
    """Whether a config's seeds can train as one batch (:func:`train_seed_configs`; :func:`refusal` says why not)."""
    return refusal(cfg) is None


def refusal(cfg: Mapping) -> str | None:
    """Why a config's seeds cannot train as one batch (None: they can), known from the config before any run is prepared."""
    algo = cfg["algo"]
    if algo.get("compile"):
        return "algo.compile is set (the vmapped update is not compiled yet; algo.cudagraphs=true captures it on a GPU)"
    if learns_from_dataset(cfg):
        return None
    if not _model_env_batchable(cfg):
        return (f"seeds=[...] batches the agents that learn from the dataset (bc, td3bc, iql, cql) and the agents on the model "
                f"env (ppo and morel, moc, sac, mopo; offline, one phase) for now; algo={algo['name']} "
                f"{'in this setting ' if algo['name'] in MODEL_ENV else ''}runs one seed per run")
    if algo.get("policy_ema") is not None:
        return "algo.policy_ema (MOC's averaged copy of the policy) is not batched yet"
    if algo.get("functional"):
        return "algo.functional=true (a functional TorchRL loss swaps its critic's weights in only inside its own call)"
    return None


def train_seed_configs(configs: Sequence[Mapping], progress: bool = True, catch_up: bool = True) -> list[dict]:
    """:func:`train_seeds` on given per-seed configs (e.g. each with the run directory a results script names): they must
    be one config but for ``seed`` and ``run_dir``.

    Runs that stand at different steps (a batch interrupted while it wrote its checkpoints one run after the other, or
    runs of which some went on alone) cannot take one batch. With ``catch_up`` (the default) the runs behind are first
    trained alone, each to the step of the run furthest on (a checkpoint's step is one of the evaluation schedule's, so
    each of them gets the records its schedule has there), and then all of them batched from there; without it,
    :class:`RunsApart` is raised.
    """
    try:
        return _train_seed_configs(configs, progress)
    except RunsApart as apart:
        if not catch_up:
            raise
        from .train import train

        target = max(apart.steps)
        key = "total_frames" if apart.unit == "frames" else "total_updates"
        for c, step in zip(configs, apart.steps):
            if step < target:
                c = to_plain(c)
                print(f"{c.get('run_dir') or 'seed ' + str(c['seed'])}: at {step} {apart.unit}, behind the batch's furthest run "
                      f"({target}); training it alone to there first", flush=True)
                train({**c, "train": {**c["train"], key: target}}, progress=progress)
        return _train_seed_configs(configs, progress)


def _train_seed_configs(configs: Sequence[Mapping], progress: bool = True) -> list[dict]:
    from .train import PreparedRun, run_directory  # the one-run steps, shared

    configs = [to_plain(c) for c in configs]
    if not configs:
        raise ValueError("train_seed_configs: no configs")
    rest = [{k: v for k, v in c.items() if k not in ("seed", "run_dir")} for c in configs]
    if any(r != rest[0] for r in rest[1:]):
        differ = sorted({k for r in rest[1:] for k in r.keys() | rest[0].keys() if r.get(k) != rest[0].get(k)})
        raise ValueError(f"the seeds' configs differ beyond seed and run_dir ({differ}): they cannot train as one batch")
    if len({c.get("seed") for c in configs}) != len(configs):
        raise ValueError(f"the seeds' configs need distinct seeds, got {[c.get('seed') for c in configs]}")
    for c in configs:
        validate_config(c)
    on_dataset = learns_from_dataset(configs[0])
    why = refusal(configs[0])
    if why:
        raise NotImplementedError(f"{why}: train its seeds one per run (offhrl train seed=S, or offhrl sweep)")
    with ExitStack() as stack:
        lanes = []
        for c in configs:
            t_start = time.time()
            run = run_directory(c)
            stack.enter_context(run.locked())
            lane = _Lane(PreparedRun.prepare(c, run, t_start, progress))
            phases = lane.r.setting.phases
            if len(phases) != 1:
                raise NotImplementedError("seeds=[...] runs settings of one phase")
            lane.remaining = phases[0].begin(lane.r.loop)  # the untrained evaluation, or where a resumed run stands
            lane.rng.set_state(torch.get_rng_state())  # from here on the seed's own stream: its run would sample from it now
            lanes.append(lane)
        steps = {lane.remaining for lane in lanes}
        if len(steps) != 1:
            raise RunsApart(f"the seeds' runs stand at different steps ({[lane.r.run.step for lane in lanes]}): resume them one by one "
                            "(offhrl train seed=S) to the same step, or start the batch in new run directories",
                            [lane.r.run.step for lane in lanes], lanes[0].r.run.unit)
        remaining = steps.pop()
        if remaining > 0:
            # the batch's own stream (draws inside the vmapped losses, the collection), seeded from the seeds and the step:
            # not the last lane's stream, which its own bookkeeping reads
            torch.manual_seed(_batch_seed([c["seed"] for c in configs], lanes[0].r.run.step))
            evaluation = _seeds_evaluation(lanes)
            if evaluation is not None:
                stack.callback(evaluation.close)
            (_train_batched if on_dataset else _train_batched_on_model_env)(lanes, remaining, evaluation)
        summaries = []
        for lane in lanes:
            with lane:
                summaries.append(lane.r.finish())
        return summaries


def _seeds_evaluation(lanes: list[_Lane]):
    """One :class:`~torchrl_offhrl.recipes.evaluation.SeedsEvaluation` for the lanes' real-env evaluations (their
    evaluations' envs as blocks of one env), or None where they do not batch, and each run evaluates on its own: per-goal
    evaluations, a setting that builds no such env, and a task whose episodes can end early (``Task.terminates``).

    Why not there: an evaluation stops when its last episode ends, and one env of N runs' blocks steps every block
    until the longest episode of all runs ends, each step paying MuJoCo per env; on Hopper that made 5 seeds'
    evaluations 2x *slower* than one after the other, and on HalfCheetah, whose episodes all run 1,000 steps, 1.56x
    faster (``benchmarks/evaluation_speed.py``, ``benchmarks/README.md``)."""
    from ..registry import task_of
    from .evaluation import Evaluator, SeedsEvaluation

    settings = [lane.r.setting for lane in lanes]
    evaluators = [s.phases[0].evaluator for s in settings]
    if (settings[0].eval_env_for is None or any(type(ev) is not Evaluator for ev in evaluators)
            or task_of(evaluators[0].env_id).terminates):
        return None
    with torch.random.fork_rng():  # building the env checks its specs with draws: the training stream stays as it was
        env = settings[0].eval_env_for(len(lanes))
    return SeedsEvaluation(evaluators, env, seed=_batch_seed([ev.seed for ev in evaluators], 0))


def _train_batched(lanes: list[_Lane], remaining: int, evaluation=None) -> None:
    first = lanes[0].r.setting
    hashes = {lane.r.run.data_hash for lane in lanes}
    if len(hashes) != 1:
        raise ValueError("the seeds' runs read different data; they cannot share updates")
    batch = SeedBatch([lane.r.setting.agent for lane in lanes], generators=[lane.rng for lane in lanes])
    rb = dataset_replay_buffer(first.data, first.agent, first.device)
    _drive(lanes, batch, (batch.sample(rb) for _ in range(remaining)), lambda data: data, evaluation)


def _drive(lanes: list[_Lane], batch, source, split, evaluation=None) -> None:
    """The seeds' training loop: each batch of ``source`` is one update of ``batch`` (a seeds' batch), and ``split(data)[i]``
    is accounted to lane ``i``'s run (its counters, logs, evaluations and checkpoints, with its own RNG stream in place);
    the agents are synced before any evaluation and at the end. With ``evaluation`` (a
    :class:`~torchrl_offhrl.recipes.evaluation.SeedsEvaluation`), a step where every run evaluates rolls their policies
    out as one first, and each run's evaluation makes its record from its part. Timed as the single-run loop times an
    update: from the batch's arrival."""
    phases = [lane.r.setting.phases[0] for lane in lanes]
    progress = [lane.r.loop.start(phase) for lane, phase in zip(lanes, phases)]
    per_update = lanes[0].r.run.unit == "updates"
    try:
        for data in source:
            t0 = time.time()
            run0 = lanes[0].r.run
            batch.worker.set_progress((run0.step - phases[0].start) / phases[0].total)
            metrics = batch.update(data)
            dt = (time.time() - t0) / len(lanes)
            parts = split(data)
            steps = 1 if per_update else parts[0].numel()
            due = [lane.r.loop.evaluation_due(st, phase, steps) for lane, st, phase in zip(lanes, progress, phases)]
            if any(due):
                batch.sync()  # the evaluations and checkpoints act with each seed's own agent
            together = evaluation is not None and all(due)
            if together:
                evaluation.prepare([lane.r.setting.agent.eval_policy for lane in lanes])
            done = []
            try:
                for i, (lane, st, phase) in enumerate(zip(lanes, progress, phases)):
                    lane.r.loop.timing["update_time_s"] += dt
                    with lane:
                        done.append(lane.r.loop.account(st, phase, parts[i], metrics[i]))
            finally:
                if together:
                    evaluation.discard()  # each run's evaluation took its part above; nothing may wait for a later one
            if all(done):
                break
    finally:
        batch.sync()
        for st in progress:
            st.bar.close()

#: the on-policy agents whose seeds batch on the model env (OnPolicySeedBatch)
ON_POLICY = ("ppo", "moc")
#: the off-policy agents whose seeds batch on the model env (OffPolicySeedBatch)
OFF_POLICY = ("sac", "mopo")
MODEL_ENV = ON_POLICY + OFF_POLICY


def _batch_seed(seeds: Sequence[int], step: int) -> int:
    """A seed for a batch's shared random stream, from its runs' seeds and the step it (re)starts at.

    Examples:
        >>> _batch_seed([4, 5], 0) == _batch_seed([4, 5], 0) != _batch_seed([4, 5], 2048)
        True
    """
    import numpy as np

    return int(np.random.SeedSequence([*map(int, seeds), int(step)]).generate_state(1)[0])


def _model_env_batchable(cfg: Mapping) -> bool:
    from .train import ModelEnvSetting, setting_of

    return cfg["algo"]["name"] in MODEL_ENV and isinstance(setting_of(cfg), ModelEnvSetting)


def _train_batched_on_model_env(lanes: list[_Lane], remaining: int, evaluation=None) -> None:
    """The seeds' agents on one model env of ``N * E`` envs (seed ``i``'s: ``i * E .. (i + 1) * E - 1``), their
    policies run as one (:class:`~torchrl_offhrl.agents.seeds.SeedBatchedPolicy`), their updates as one
    (:class:`~torchrl_offhrl.agents.seeds.OnPolicySeedBatch` for PPO and MOC,
    :class:`~torchrl_offhrl.agents.seeds.OffPolicySeedBatch` for SAC and MOPO, each seed with its own replay buffer);
    each seed's part of a batch is accounted to its own run. A run starting from scratch collects its first
    ``init_random_frames`` frames with random actions, each seed's own count.

    The collection's draws (actions, options, the env's start states and members) come from one stream for all seeds,
    not from each seed's own: the seeds' runs are runs of the same config, not replays of separate ones.
    """
    from ..agents.seeds import OffPolicySeedBatch, OnPolicySeedBatch
    from .config import acts_in_latent_space
    from .pipeline import make_model_env
    from .loop import env_collector

    n = len(lanes)
    hashes = {lane.r.run.data_hash for lane in lanes}
    if len(hashes) != 1:
        raise ValueError("the seeds' runs read different data; they cannot share one model env")
    dirs = {lane.r.setting.model_info["model_dir"] for lane in lanes}
    if len(dirs) != 1:
        raise ValueError(f"the seeds' runs use different models ({sorted(map(str, dirs))}); they cannot share one model env")
    p = lanes[0].r.setting.parts
    agents = [lane.r.setting.agent for lane in lanes]
    kind = OffPolicySeedBatch if p.cfg["algo"]["name"] in OFF_POLICY else OnPolicySeedBatch
    batch = kind(agents, generators=[lane.rng for lane in lanes])
    latent = acts_in_latent_space(p.cfg)
    per_seed = model_env_batch(p.cfg)  # as each run's own model env (recipes.train)
    env = make_model_env(p.pcfg, p.ensemble, p.cvae if latent else None, p.data, batch_size=n * per_seed, latent=latent,
                         threshold=lanes[0].r.setting.threshold)  # the runs' own threshold, not calibrated again
    p.add_reward_transforms(agents[0].attach(env))
    env.set_seed(p.rc.seed + lanes[0].r.run.frames)

    class _Collects:  # what env_collector reads of an agent
        policy = batch.policy
        frames_per_batch = n * agents[0].frames_per_batch
        init_random_frames = n * agents[0].init_random_frames

    collector = env_collector(env, _Collects, n * remaining, frames_done=lanes[0].r.run.frames, device=p.device)
    try:
        _drive(lanes, batch, collector, lambda data: data.reshape(n, per_seed, *data.batch_size[1:]), evaluation)
    finally:
        collector.shutdown()
        env.close()
