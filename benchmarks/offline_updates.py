"""Gradient updates per second of the model-free offline agents (BC, TD3+BC, IQL, CQL), side by side in one run.

    python benchmarks/offline_updates.py [--device cuda] [--threads 1] [--updates 200]

Each agent with its config values (``configs/algo/*.yaml``: MLP(256, 256),
batch 256, Hopper-v5 dimensions) takes ``--updates`` updates on one random
batch (the update's cost does not depend on the values), three times in the
same process: "before" with torch's per-tensor Adam (``fused_adam=false``),
"after" with the default fused Adam, and "compiled": fused Adam with
``compile=true`` (``torch.compile`` of the loss, built during the untimed
warm-up); on CUDA also "cuda-graphs": ``compile=reduce-overhead`` (the
compiled loss replayed as CUDA graphs), "captured": ``cudagraphs=true``
(the whole update, loss, backward, Adam and target steps, captured as one
CUDA graph per form of the update and replayed), "captured+compiled" (both
switches) and "captured, sampled": "captured" with each batch sampled from a
TorchRL replay buffer on the device holding ``--buffer`` transitions, as the
training loop does. The FLOPs of one update's matrix
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
from flops import leaf_flops


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--updates", type=int, default=200, help="timed updates per agent and variant (CQL: a fifth)")
    p.add_argument("--algos", nargs="+", default=["bc", "td3bc", "iql", "cql"])
    p.add_argument("--variants", nargs="+", default=None, help="a subset of the variants (default: all on this device)")
    p.add_argument("--buffer", type=int, default=100_000, help="transitions in the replay buffer of the 'sampled' variant")
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
    print(f"\ndevice: {dev}, {torch.get_num_threads()} torch threads, dense matmul 2048^2: {matmul:.1f} GFLOP/s")
    print("| agent | variant | GFLOP per update | updates/s | GFLOP/s | vs matmul | 100k updates take | speed-up |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    variants = (("before", "after", "compiled", "cuda-graphs", "captured", "captured+compiled", "captured, sampled") if dev.type == "cuda"
                else ("before", "after", "compiled"))
    variants = [v for v in variants if a.variants is None or v in a.variants]
    for algo in a.algos:
        cfg = to_plain(compose("offline_train", [f"algo={algo}"]))["algo"]
        cfg.pop("reward_scale", None)
        n, b = (a.updates // 5 if algo == "cql" else a.updates), int(cfg["batch_size"])
        batch = TensorDict({"observation": torch.randn(b, 11), "action": torch.rand(b, 3) * 2 - 1, "next": {
            "observation": torch.randn(b, 11), "reward": torch.randn(b, 1), "done": torch.zeros(b, 1, dtype=torch.bool),
            "terminated": torch.zeros(b, 1, dtype=torch.bool)}}, [b], device=dev)
        rb, first = None, None
        for variant in variants:
            torch.manual_seed(0)
            compiled = {"compiled": True, "cuda-graphs": "reduce-overhead", "captured+compiled": True}.get(variant, False)
            captured = variant.startswith("captured")
            agent = make_agent(algo, env, {**cfg, "fused_adam": variant != "before", "compile": compiled, "cudagraphs": captured},
                               action_key="action", device=dev)
            if variant == "captured, sampled" and rb is None:
                from torchrl.data import LazyTensorStorage, ReplayBuffer

                rb = ReplayBuffer(storage=LazyTensorStorage(a.buffer, device=dev), batch_size=b)
                rb.extend(batch.expand(a.buffer // b, b).reshape(-1).clone())
            # a fresh copy per update, as the loop's sampled batches: TorchRL's losses write their own entries into their input
            draw = rb.sample if variant == "captured, sampled" else batch.clone
            for _ in range(50 if captured else 5):  # warm-up (captured: each form's eager runs, its capture, its first replays)
                agent.update(draw())
            if not compiled and not captured:  # the same products as in the other variants (the profiler does not see them all)
                with profile(with_flops=True) as prof:  # the matrix products' FLOPs (mm, addmm, bmm), forward and backward
                    agent.update(draw())
                    agent.update(draw())  # TD3+BC: one critic-only and one critic + actor update
                flops = leaf_flops(prof) / 2  # each product once, not again at the vmap levels above it (flops.py)
            sync()
            t = time.perf_counter()
            for _ in range(n):
                agent.update(draw())
            sync()
            rate = n / (time.perf_counter() - t)
            first = rate if variant == variants[0] else first
            gfs = rate * flops / 1e9  # each row as it is measured: a run stopped at a time limit keeps the rows before
            print(f"| {algo} | {variant} | {flops / 1e9:.3f} | {rate:,.1f} | {gfs:.1f} | {gfs / matmul:.0%} | {100_000 / rate / 60:,.1f} min | "
                  f"{rate / first:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
