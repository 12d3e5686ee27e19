"""Seeds as a batch dimension: N seeds of a dataset agent as one vmapped update (SeedBatch) against one seed alone.

    .venv/bin/python benchmarks/seed_batch.py [--algos bc td3bc iql cql] [--seeds 1 5 10] [--threads 1 2] [--updates 100] [--device cpu]
    python benchmarks/seed_batch.py --device cuda --cudagraphs   # on a GPU: every update (separate and batched) captured as CUDA graphs

For each algorithm and thread count, in one run: the time of one update of
one agent alone, of N agents updated one after the other (what N separate
runs cost on one core), and of N agents as one SeedBatch update. Hopper's
dimensions, the agents' default networks (MLP 256x256) and batch 256 per
seed. Prints updates/s per seed and the batched time over one seed's
(the goal of issue 38: 5 seeds in <= 2x the time of one on CPU).
"""
from __future__ import annotations

import argparse
import time

import torch
from tensordict import TensorDict

from torchrl_offhrl.agents import make_agent
from torchrl_offhrl.agents.seeds import SeedBatch
from torchrl_offhrl.data import make_gym_env

OBS, ACT, B = 11, 3, 256


def batch(n: int, device) -> TensorDict:
    shape = (n, B) if n else (B,)
    nxt = TensorDict(observation=torch.randn(*shape, OBS), reward=torch.randn(*shape, 1), done=torch.zeros(*shape, 1, dtype=torch.bool),
                     terminated=torch.zeros(*shape, 1, dtype=torch.bool), batch_size=shape)
    return TensorDict(observation=torch.randn(*shape, OBS), action=torch.rand(*shape, ACT) * 2 - 1, next=nxt, batch_size=shape).to(device)


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def timed(fn, updates: int, device="cpu") -> float:
    """Seconds per call of ``fn`` (each call gets its own copy of the batch: a loss writes its outputs into it, and a
    captured update refuses a batch holding tensors that require gradients)."""
    for _ in range(5):  # warm-up: optimiser states, allocator, CUDA graph capture (after 2 eager updates)
        fn()
    _sync(device)
    t = time.perf_counter()
    for _ in range(updates):
        fn()
    _sync(device)  # a GPU runs behind the Python that launches its work: the time is the GPU's once it has caught up
    return (time.perf_counter() - t) / updates


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--algos", nargs="+", default=["bc", "td3bc", "iql", "cql"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 5, 10])
    ap.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    ap.add_argument("--updates", type=int, default=100)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--cudagraphs", action="store_true", help="algo.cudagraphs=true for every agent (a GPU's speed switch; the "
                    "seed batch then captures its vmapped update)")
    a = ap.parse_args(argv)
    env = make_gym_env("Hopper-v5")
    name = torch.cuda.get_device_name() if torch.device(a.device).type == "cuda" else "cpu"
    print(f"torch {torch.__version__}, device {a.device} ({name}), cudagraphs={a.cudagraphs}, batch {B} per seed, Hopper dims, "
          f"default networks; {a.updates} timed updates\n")
    print(f"{'algo':7s} {'threads':>7s} {'seeds':>5s} {'separate ms':>12s} {'batched ms':>11s} {'upd/s/seed sep':>15s} "
          f"{'upd/s/seed bat':>15s} {'batched / 1 seed':>17s} {'speed-up':>9s}")
    for algo in a.algos:
        for threads in a.threads:
            torch.set_num_threads(threads)
            one = None
            for n in a.seeds:
                agents = []
                for s in range(n):
                    torch.manual_seed(s)
                    agents.append(make_agent(algo, env, {"cudagraphs": a.cudagraphs}, action_key="action", device=a.device))
                single = batch(0, a.device)
                t_sep = timed(lambda: [ag.update(single.clone()) for ag in agents], a.updates, a.device)
                if n == 1:
                    one = t_sep
                sb = SeedBatch(agents)
                stacked = batch(n, a.device)
                t_bat = timed(lambda: sb.update(stacked.clone()), a.updates, a.device)
                one = one or t_sep / n
                print(f"{algo:7s} {threads:7d} {n:5d} {1e3 * t_sep:12.2f} {1e3 * t_bat:11.2f} {n / t_sep:15.1f} {n / t_bat:15.1f} "
                      f"{t_bat / one:16.2f}x {t_sep / t_bat:8.2f}x", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
