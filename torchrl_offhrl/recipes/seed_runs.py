"""Several seeds of one config trained as one computation: ``offhrl train algo=iql seeds=[4,5,6,7,8]``.

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

For now the agents that learn from the dataset (BC, TD3+BC, IQL, CQL);
model-env agents run one seed per run (``offhrl sweep``).
"""
from __future__ import annotations

import time
from contextlib import ExitStack
from collections.abc import Mapping, Sequence

import torch

from ..agents.seeds import SeedBatch
from ..utils import to_plain
from .config import learns_from_dataset
from .schema import validate_config
from .sources import dataset_replay_buffer

__all__ = ["seed_configs", "train_seeds"]


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
    from .train import PreparedRun, run_directory  # the one-run steps, shared

    configs = seed_configs(cfg, seeds)
    for c in configs:
        validate_config(c)
    if not learns_from_dataset(configs[0]):
        raise NotImplementedError(f"seeds=[...] batches the agents that learn from the dataset (bc, td3bc, iql, cql) for now; algo="
                                  f"{configs[0]['algo']['name']} trains on an env: run one seed per run (offhrl train seed=S, or offhrl sweep)")
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
            raise ValueError(f"the seeds' runs stand at different steps ({[lane.r.run.step for lane in lanes]}): resume them one by one "
                             "(offhrl train seed=S) to the same step, or start the batch in new run directories")
        remaining = steps.pop()
        if remaining > 0:
            _train_batched(lanes, remaining)
        summaries = []
        for lane in lanes:
            with lane:
                summaries.append(lane.r.finish())
        return summaries


def _train_batched(lanes: list[_Lane], remaining: int) -> None:
    first = lanes[0].r.setting
    hashes = {lane.r.run.data_hash for lane in lanes}
    if len(hashes) != 1:
        raise ValueError("the seeds' runs read different data; they cannot share updates")
    batch = SeedBatch([lane.r.setting.agent for lane in lanes], generators=[lane.rng for lane in lanes])
    rb = dataset_replay_buffer(first.data, first.agent, first.device)
    phases = [lane.r.setting.phases[0] for lane in lanes]
    progress = [lane.r.loop.start(phase) for lane, phase in zip(lanes, phases)]
    try:
        for _ in range(remaining):
            t0 = time.time()
            run0 = lanes[0].r.run
            batch.worker.set_progress((run0.step - phases[0].start) / phases[0].total)
            data = batch.sample(rb)
            metrics = batch.update(data)
            dt = (time.time() - t0) / len(lanes)
            if any(lane.r.loop.evaluation_due(st, phase) for lane, st, phase in zip(lanes, progress, phases)):
                batch.sync()  # the evaluations and checkpoints act with each seed's own agent
            done = []
            for i, (lane, st, phase) in enumerate(zip(lanes, progress, phases)):
                lane.r.loop.timing["update_time_s"] += dt
                with lane:
                    done.append(lane.r.loop.account(st, phase, data[i], metrics[i]))
            if all(done):
                break
    finally:
        batch.sync()
        for st in progress:
            st.bar.close()
