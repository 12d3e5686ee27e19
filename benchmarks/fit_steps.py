"""Model fits: one optimisation step of the ensemble and the CVAE as `SupervisedTrainer` runs it, against the matmul rate.

    python benchmarks/fit_steps.py [--threads N] [--steps 150] [--sizes demo paper] [--device cuda]

For the dynamics ensemble (5 members, dynamics and reward MLPs, the paper's L1 loss) and the CVAE, at the demo's widths
(256 x 256 both) and the paper's (ensemble 512 x 512, CVAE 720 x 720), Hopper-v5's sizes (11 observations, 3 actions),
on 100,000 random transitions:

* the step as a fit takes it: ``SupervisedTrainer.fit`` itself (a bootstrap minibatch of 256 per member drawn from the
  training TensorDict, ``model.loss``, backward, fused Adam), run for ``--steps`` steps in one epoch with no held-out
  set, wall time per step;
* the FLOPs of one step's matrix products, counted by ``torch.profiler`` (each product once, ``flops.py``), and the rate
  they run at as a fraction of two rates measured in the same run: a dense 2048 x 2048 matmul, and the batched
  product of the model's own widest layer (``[5, 256, H] x [5, H, H]`` for the ensemble, ``[256, H] x [H, H]`` for the
  CVAE: what any formulation of these layers runs at best on this machine);
* where a step's time goes (the profiler's self time per op, grouped): matrix products, elementwise and reductions,
  the optimiser, indexing and copies, and the rest (Python, dispatch, autograd bookkeeping: the wall time the ops do not
  account for).

The fit's length is a separate question: ``SupervisedTrainer`` stops on the held-out loss (``patience``, ``rel_tol``);
the last table multiplies a step by the steps the demo's fits took to a floor at 100% of the dense matmul rate.
"""
from __future__ import annotations

import argparse
import time

import torch
from ensemble_training import matmul_rate, sync, timeit  # the benchmarks' one timing helper and dense-matmul reference
from flops import leaf_flops
from tensordict import TensorDict

OBS, ACT, N, BATCH = 11, 3, 100_000, 256
WIDTHS = {"demo": (256, 256), "paper": (512, 720)}  # (ensemble, CVAE) hidden widths
#: steps the demo's hopper-medium fits took to stop (CHANGELOG 0.2.0: the ensemble at 138 epochs, ~48k steps; the CVAE at 20
#: epochs of 351 steps)
DEMO_FIT_STEPS = {"ensemble": 48_000, "cvae": 20 * 351}

MATMUL = ("aten::mm", "aten::bmm", "aten::addmm", "aten::baddbmm", "aten::linear", "aten::matmul")
OPTIMISER = ("aten::_fused_adam_", "aten::_foreach")
INDEXING = ("aten::index", "aten::copy_", "aten::cat", "aten::gather", "aten::index_select", "aten::randint", "aten::random_",
            "aten::_to_copy", "aten::clone", "aten::contiguous")


def transitions(device) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    return TensorDict({"observation": torch.randn(N, OBS, generator=g), "action": torch.rand(N, ACT, generator=g) * 2 - 1,
                       ("next", "observation"): torch.randn(N, OBS, generator=g), ("next", "reward"): torch.randn(N, 1, generator=g),
                       ("next", "done"): torch.zeros(N, 1, dtype=torch.bool), ("next", "terminated"): torch.zeros(N, 1, dtype=torch.bool)},
                      batch_size=[N], device=device)


def model(kind: str, width: int, device):
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble

    torch.manual_seed(0)
    if kind == "ensemble":
        return DynamicsEnsemble(OBS, ACT, num_models=5, hidden_sizes=(width, width), loss="l1").to(device)
    return ConditionalVAE(OBS, ACT, hidden_sizes=(width, width), kl_weight=0.05).to(device)


def fit(m, data, steps: int) -> float:
    """Wall seconds of ``steps`` optimisation steps of ``SupervisedTrainer.fit`` (one epoch, no held-out set)."""
    from torchrl_offhrl.models import SupervisedTrainer

    trainer = SupervisedTrainer(lr=1e-3, batch_size=BATCH, max_epochs=1, steps_per_epoch=steps, progress=False)
    sync(data.device)
    t = time.perf_counter()
    trainer.fit(m, data)
    sync(data.device)
    return time.perf_counter() - t


def rate(fn, flops: float, device, reps: int) -> float:
    """GFLOP/s of ``fn``, which computes ``flops``, over ``reps`` timed calls."""
    return flops / timeit(fn, device, reps) / 1e9


def layer_rate(kind: str, width: int, device) -> float:
    """GFLOP/s of the model's widest layer's product at a fit's minibatch (per member for the ensemble)."""
    if kind == "ensemble":
        a, b = torch.randn(5, BATCH, width, device=device), torch.randn(5, width, width, device=device)
        return rate(lambda: torch.bmm(a, b), 2 * 5 * BATCH * width * width, device, 200)
    a, b = torch.randn(BATCH, width, device=device), torch.randn(width, width, device=device)
    return rate(lambda: a @ b, 2 * BATCH * width * width, device, 400)


def breakdown(m, data, steps: int) -> tuple[float, dict[str, float]]:
    """(FLOPs per step, {group: share of the wall time}) from a profiled stretch of the fit."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if data.device.type == "cuda" else [])
    with profile(activities=acts, with_flops=True) as prof:
        wall = fit(m, data, steps)
    flops = leaf_flops(prof) / steps
    groups = dict.fromkeys(("matrix products", "elementwise and reductions", "optimiser", "indexing and copies"), 0.0)
    for e in prof.key_averages():
        if not e.key.startswith("aten::"):
            continue
        us = e.self_cpu_time_total
        if e.key in MATMUL:
            groups["matrix products"] += us
        elif e.key.startswith(OPTIMISER):
            groups["optimiser"] += us
        elif e.key in INDEXING:
            groups["indexing and copies"] += us
        else:
            groups["elementwise and reductions"] += us
    total = wall * 1e6
    shares = {k: v / total for k, v in groups.items()}
    shares["rest (Python, dispatch, autograd)"] = max(0.0, 1 - sum(shares.values()))
    return flops, shares


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's, every core, as the fits run)")
    p.add_argument("--steps", type=int, default=150, help="timed steps per model")
    p.add_argument("--sizes", nargs="+", default=["demo", "paper"], choices=sorted(WIDTHS))
    a = p.parse_args()
    if a.threads:
        torch.set_num_threads(a.threads)
    device = torch.device(a.device)
    data = transitions(device)
    mm = matmul_rate(device, steps=10)
    print(f"torch {torch.__version__}, {device}, {torch.get_num_threads()} thread(s); dense matmul 2048^2: {mm:.1f} GFLOP/s "
          f"(this run)\n")
    print("| model | width | ms per step | GFLOP per step | GFLOP/s | vs dense matmul | widest layer's product alone, GFLOP/s | vs it |")
    print("|---|---|---|---|---|---|---|---|")
    shares, per_step = {}, {}
    for size in a.sizes:
        for kind, width in zip(("ensemble", "cvae"), WIDTHS[size]):
            m = model(kind, width, device)
            fit(m, data, 20)  # warm-up: allocator, Adam's state
            flops, shares[(kind, size)] = breakdown(m, data, max(20, a.steps // 5))
            dt = fit(m, data, a.steps) / a.steps
            per_step[(kind, size)] = (dt, flops)
            lr = layer_rate(kind, width, device)
            gf = flops / dt / 1e9
            print(f"| {kind} | {width} | {dt * 1e3:.2f} | {flops / 1e9:.3f} | {gf:.1f} | {gf / mm:.0%} | {lr:.1f} | {gf / lr:.0%} |", flush=True)
    groups = list(next(iter(shares.values())))
    print("\nwhere a step's time goes (profiler self time per op, grouped; share of the wall time):\n")
    print("| model | width | " + " | ".join(groups) + " |")
    print("|---|---|" + "---|" * len(groups))
    for (kind, size), s in shares.items():
        print(f"| {kind} | {dict(zip(('ensemble', 'cvae'), WIDTHS[size]))[kind]} | " + " | ".join(f"{s[g]:.0%}" for g in groups) + " |")
    if "demo" in a.sizes:
        print("\nthe demo's fits (hopper-medium: the ensemble stopped after ~48k steps, the CVAE after ~7k):\n")
        print("| model | steps | at this run's step time | at 100% of the dense matmul rate |")
        print("|---|---|---|---|")
        for kind in ("ensemble", "cvae"):
            dt, flops = per_step[(kind, "demo")]
            steps = DEMO_FIT_STEPS[kind]
            print(f"| {kind} | {steps:,} | {steps * dt / 60:.1f} min | {steps * flops / (mm * 1e9) / 60:.1f} min |")


if __name__ == "__main__":
    main()
