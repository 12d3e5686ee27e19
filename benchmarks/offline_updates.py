"""Gradient updates per second of the model-free offline agents (BC, TD3+BC, IQL, CQL), side by side in one run.

    python benchmarks/offline_updates.py [--device cuda] [--threads 1] [--updates 200]

Each agent with its config values (``configs/algo/*.yaml``: MLP(256, 256),
batch 256, Hopper-v5 dimensions) takes ``--updates`` updates on one random
batch (the update's cost does not depend on the values), three times in the
same process: "before" with torch's per-tensor Adam (``fused_adam=false``),
"after" with the default fused Adam, and "compiled": fused Adam with
``compile=true`` (``torch.compile`` of the loss, built during the untimed
warm-up); on CUDA also "cuda-graphs": ``compile=reduce-overhead`` (the
compiled loss replayed as CUDA graphs). The FLOPs of one update's matrix
products are counted by ``torch.profiler`` (``with_flops``; forward and
backward), so the table also
shows how close each update runs to this machine's dense matmul rate: on a
CPU these updates are bound by their matrix products, so the 100k-update
budgets are a matter of FLOPs (CQL evaluates its critics on 10 random and
2 x 10 policy actions per state).
"""
from __future__ import annotations

import argparse
import time

import torch


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--updates", type=int, default=200, help="timed updates per agent and variant (CQL: a fifth)")
    a = p.parse_args()
    if a.threads:
        torch.set_num_threads(a.threads)
    from tensordict import TensorDict
    from torch.profiler import profile

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.utils import to_plain

    dev = torch.device(a.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    x = torch.randn(2048, 2048, device=dev)
    for _ in range(3):
        x @ x
    sync()
    t = time.perf_counter()
    for _ in range(10):
        x @ x
    sync()
    matmul = 10 * 2 * 2048**3 / (time.perf_counter() - t) / 1e9
    env = make_gym_env("Hopper-v5")
    rows = []
    variants = ("before", "after", "compiled", "cuda-graphs") if dev.type == "cuda" else ("before", "after", "compiled")
    for algo in ("bc", "td3bc", "iql", "cql"):
        cfg = to_plain(compose("offline_train", [f"algo={algo}"]))["algo"]
        cfg.pop("reward_scale", None)
        n, b = (a.updates // 5 if algo == "cql" else a.updates), int(cfg["batch_size"])
        batch = TensorDict({"observation": torch.randn(b, 11), "action": torch.rand(b, 3) * 2 - 1, "next": {
            "observation": torch.randn(b, 11), "reward": torch.randn(b, 1), "done": torch.zeros(b, 1, dtype=torch.bool),
            "terminated": torch.zeros(b, 1, dtype=torch.bool)}}, [b], device=dev)
        for variant in variants:
            torch.manual_seed(0)
            compiled = {"compiled": True, "cuda-graphs": "reduce-overhead"}.get(variant, False)
            agent = make_agent(algo, env, {**cfg, "fused_adam": variant != "before", "compile": compiled}, action_key="action",
                               device=dev)
            for _ in range(5):  # warm-up
                agent.update(batch)
            if not compiled:  # the compiled update does the same products (its kernels are not all counted by the profiler)
                with profile(with_flops=True) as prof:  # the matrix products' FLOPs (mm, addmm, bmm), forward and backward
                    agent.update(batch)
                    agent.update(batch)  # TD3+BC: one critic-only and one critic + actor update
                flops = sum(e.flops for e in prof.key_averages() if e.flops) / 2
            sync()
            t = time.perf_counter()
            for _ in range(n):
                agent.update(batch)
            sync()
            rate = n / (time.perf_counter() - t)
            rows.append((algo, variant, flops / 1e9, rate, rate * flops / 1e9))
    print(f"\ndevice: {dev}, {torch.get_num_threads()} torch threads, dense matmul 2048^2: {matmul:.1f} GFLOP/s")
    print("| agent | variant | GFLOP per update | updates/s | GFLOP/s | vs matmul | 100k updates take | speed-up |")
    print("|---|---|---|---|---|---|---|---|")
    before = {r[0]: r[3] for r in rows if r[1] == "before"}
    for algo, variant, gf, rate, gfs in rows:
        print(f"| {algo} | {variant} | {gf:.3f} | {rate:,.1f} | {gfs:.1f} | {gfs / matmul:.0%} | {100_000 / rate / 60:,.0f} min | "
              f"{rate / before[algo]:.2f}x |")


if __name__ == "__main__":
    main()
