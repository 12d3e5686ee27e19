"""Ensemble training throughput: batched-weight ensemble vs a loop over members.

    python benchmarks/ensemble_training.py [--device cuda] [--steps 60]

Measures, in one run on one machine:
  * the dense matmul rate (GFLOP/s) of a square fp32 matmul and of the batched
    matmul shape the ensemble actually runs ([K, B, 512] x [K, 512, 512]);
  * training steps of K=5 MLP(512,512) dynamics members on Hopper dims
    (11 obs + 3 actions -> 11), batch 256 per member, Adam, L1 loss:
    (a) our EnsembleMLP (one baddbmm per layer), (b) a Python loop over 5
    separate nn.Sequential models; both with fused Adam;
  * samples/s (member-samples: K x B per step), achieved GFLOP/s (forward +
    backward = 3x forward FLOPs) and the ratio to the measured matmul rates;
  * the library's own training step (``DynamicsEnsemble.loss`` with the reward
    members, Adam) for the paper's L1 ensemble of 5 and MOPO's Gaussian one
    (``loss="nll"``: mean and log-variance heads, learned bounds) of 5 and of
    7 members (MOPO's count), side by side: what MOPO's model costs.
"""
from __future__ import annotations

import argparse
import time

import torch
from torch import nn

from torchrl_offhrl.models import EnsembleMLP
from torchrl_offhrl.models.trainer import make_adam

OBS, ACT, K, B, H = 11, 3, 5, 256, 512


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def timeit(fn, device, steps, warmup=5):
    for _ in range(warmup):
        fn()
    sync(device)
    t = time.perf_counter()
    for _ in range(steps):
        fn()
    sync(device)
    return (time.perf_counter() - t) / steps


def matmul_rate(device, n=2048, steps=20):
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    dt = timeit(lambda: a @ b, device, steps)
    return 2 * n**3 / dt / 1e9


def bmm_rate(device, steps=50):
    a, b = torch.randn(K, B, H, device=device), torch.randn(K, H, H, device=device)
    dt = timeit(lambda: torch.bmm(a, b), device, steps)
    return 2 * K * B * H * H / dt / 1e9


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--batch", type=int, default=B)
    args = p.parse_args()
    device = torch.device(args.device)
    bsz = args.batch
    torch.manual_seed(0)

    x = torch.randn(K, bsz, OBS + ACT, device=device)
    y = torch.randn(K, bsz, OBS, device=device)

    ens = EnsembleMLP(K, OBS + ACT, OBS, (H, H)).to(device)
    opt = make_adam(ens.parameters(), lr=1e-4)

    def step_ens():
        loss = (ens(x) - y).abs().mean(dim=(1, 2)).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    members = [nn.Sequential(nn.Linear(OBS + ACT, H), nn.ReLU(), nn.Linear(H, H), nn.ReLU(), nn.Linear(H, OBS)).to(device) for _ in range(K)]
    opts = [make_adam(m.parameters(), lr=1e-4) for m in members]

    def step_loop():
        for k, (m, o) in enumerate(zip(members, opts)):
            loss = (m(x[k]) - y[k]).abs().mean()
            o.zero_grad(set_to_none=True)
            loss.backward()
            o.step()

    flops_step = 3 * ens.flops_per_sample() * bsz  # forward + backward (2x)
    mm = matmul_rate(device)
    bm = bmm_rate(device)
    t_ens = timeit(step_ens, device, args.steps)
    t_loop = timeit(step_loop, device, args.steps)

    print(f"device: {device} ({torch.cuda.get_device_name() if device.type == 'cuda' else f'{torch.get_num_threads()} threads'}), torch {torch.__version__}")
    print(f"dense matmul 2048^2 fp32: {mm:8.1f} GFLOP/s;  bmm [{K},{bsz},{H}]x[{K},{H},{H}]: {bm:8.1f} GFLOP/s")
    print(f"K={K} MLP({H},{H}) Hopper dims, batch {bsz}/member, Adam + L1, {flops_step / 1e9:.2f} GFLOP per step\n")
    print(f"{'variant':28s} {'steps/s':>9s} {'samples/s':>11s} {'GFLOP/s':>9s} {'vs matmul':>10s} {'vs bmm':>8s} {'speed-up':>9s}")
    for name, dt in (("EnsembleMLP (batched)", t_ens), ("loop over 5 nn.Sequential", t_loop)):
        gf = flops_step / dt / 1e9
        print(f"{name:28s} {1 / dt:9.1f} {K * bsz / dt:11,.0f} {gf:9.1f} {gf / mm:9.0%} {gf / bm:8.0%} {t_loop / dt:8.2f}x")

    # the library's training step (dynamics and reward members, as a fit runs it): the paper's L1 ensemble and MOPO's Gaussian one
    from tensordict import TensorDict

    from torchrl_offhrl.models import DynamicsEnsemble

    def library_step(loss: str, k: int):
        model = DynamicsEnsemble(OBS, ACT, num_models=k, hidden_sizes=(H, H), loss=loss).to(device)
        batch = TensorDict({"observation": torch.randn(k, bsz, OBS), "action": torch.randn(k, bsz, ACT),
                            ("next", "observation"): torch.randn(k, bsz, OBS), ("next", "reward"): torch.randn(k, bsz, 1)},
                           batch_size=[k, bsz], device=device)
        opt_m = make_adam(model.parameters(), lr=1e-3)

        def step():
            loss_k = model.loss(batch)
            opt_m.zero_grad(set_to_none=True)
            loss_k.sum().backward()
            opt_m.step()
        return timeit(step, device, args.steps)

    rows = [(f"{loss}, {k} members", k, library_step(loss, k)) for loss, k in (("l1", 5), ("nll", 5), ("nll", 7))]
    base = rows[0][2]
    print(f"\nDynamicsEnsemble.loss + Adam (dynamics and reward members), batch {bsz}/member:")
    print(f"{'variant':28s} {'steps/s':>9s} {'samples/s':>11s} {'time vs l1, 5':>14s}")
    for name, k, dt in rows:
        print(f"{name:28s} {1 / dt:9.1f} {k * bsz / dt:11,.0f} {dt / base:13.2f}x")


if __name__ == "__main__":
    main()
