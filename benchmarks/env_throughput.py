"""Composed-env step throughput vs its FLOP bound and vs the real Hopper-v5.

    python benchmarks/env_throughput.py [--device cuda] [--batches 1 64 1024 4096]

The composed env is TransformedEnv(PessimisticModelEnv, LatentActionTransform)
with the paper's sizes (K=5 MLP(512,512) dynamics + reward members, CVAE
decoder MLP(750,750)) on Hopper dims; weights are untrained (the cost does not
depend on them) and the threshold is infinite so episodes run to the horizon.
Transitions/s are measured through ``env.rollout`` (what users and collectors
run). The FLOP bound is the measured dense-matmul rate divided by the FLOPs of
one transition (ensemble + decoder forward). The real env is Gymnasium's
Hopper-v5 through TorchRL's GymWrapper over a synchronous vector env.
"""
from __future__ import annotations

import argparse
import time

import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from torchrl_offhrl.data import OfflineDataset, make_gym_env
from torchrl_offhrl.envs import LatentActionTransform, PessimisticModelEnv
from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
from torchrl_offhrl.recipes import GaussianLatentPolicy

OBS, ACT = 11, 3


def fake_hopper_dataset(n=5000):
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(n, OBS, generator=g)
    obs[:, 0] = 1.25  # healthy height, so Hopper's termination does not fire
    obs[:, 1] = 0.0
    td = TensorDict(
        {"observation": obs, "action": torch.rand(n, ACT, generator=g) * 2 - 1,
         "next": {"observation": obs + 0.01 * torch.randn(n, OBS, generator=g), "reward": torch.ones(n, 1),
                  "terminated": torch.zeros(n, 1, dtype=torch.bool), "truncated": (torch.arange(n) % 100 == 99)[:, None]}},
        batch_size=[n],
    )
    return OfflineDataset(td, {"env_id": "Hopper-v5"}, (-torch.ones(ACT), torch.ones(ACT)))


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def matmul_rate(device, n=2048, steps=20):
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    for _ in range(3):
        a @ b
    sync(device)
    t = time.perf_counter()
    for _ in range(steps):
        a @ b
    sync(device)
    return 2 * n**3 * steps / (time.perf_counter() - t)


def rollout_rate(env, policy, steps, device):
    with torch.no_grad():
        env.rollout(3, policy, break_when_any_done=False)
        sync(device)
        t = time.perf_counter()
        td = env.rollout(steps, policy, break_when_any_done=False)
        sync(device)
    return td.numel() / (time.perf_counter() - t)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 4096])
    p.add_argument("--real-batches", type=int, nargs="+", default=[1, 64, 1024])
    p.add_argument("--min-transitions", type=int, default=40_000)
    args = p.parse_args()
    device = torch.device(args.device)
    torch.manual_seed(0)
    data = fake_hopper_dataset()
    ens = DynamicsEnsemble.for_dataset(data, num_models=5, hidden_sizes=(512, 512))
    cvae = ConditionalVAE.for_dataset(data, hidden_sizes=(750, 750))
    ens_flops = ens.dynamics.flops_per_sample() + ens.reward_net.flops_per_sample()
    dec_flops = sum(2 * m.in_features * m.out_features for m in cvae.decoder.net if isinstance(m, torch.nn.Linear))
    flops = ens_flops + dec_flops
    rate = matmul_rate(device)
    bound = rate / flops
    policy = GaussianLatentPolicy(cvae.latent_dim)

    print(f"device: {device} ({torch.cuda.get_device_name() if device.type == 'cuda' else f'{torch.get_num_threads()} threads'}), torch {torch.__version__}")
    print(f"dense matmul: {rate / 1e9:.1f} GFLOP/s; one transition = {flops / 1e6:.2f} MFLOP "
          f"(ensemble {ens_flops / 1e6:.2f} + decoder {dec_flops / 1e6:.2f}) -> FLOP bound {bound:,.0f} transitions/s\n")
    print(f"{'batch':>6s} {'composed env (tr/s)':>20s} {'vs FLOP bound':>14s} {'unchunked (tr/s)':>17s} {'chunked/unchunked':>18s} "
          f"{'real Hopper-v5 (tr/s)':>22s} {'model/real':>11s}")
    for n in args.batches:
        env = TransformedEnv(
            PessimisticModelEnv(ens, data, threshold=float("inf"), batch_size=[n] if n > 1 else [], device=device, seed=0),
            LatentActionTransform(cvae.decoder),
        ).to(device)
        steps = max(20, min(1000, args.min_transitions // n))
        r_model = rollout_rate(env, policy, steps, device)
        r_whole = None
        chunk = env.base_env.predict_chunk
        if device.type == "cpu" and chunk is not None and n > chunk:  # the same env predicting all its envs in one batch
            env.base_env.predict_chunk = None
            r_whole = rollout_rate(env, policy, steps, device)
            env.base_env.predict_chunk = chunk
        r_real = None
        if n in args.real_batches:
            real = make_gym_env("Hopper-v5", num_envs=n)
            real.set_seed(0)
            r_real = rollout_rate(real, None, max(10, min(300, 20_000 // n)), torch.device("cpu"))
            real.close()
        real_s = f"{r_real:22,.0f}" if r_real else f"{'-':>22s}"
        ratio = f"{r_model / r_real:10.1f}x" if r_real else f"{'-':>11s}"
        whole_s = f"{r_whole:17,.0f} {r_model / r_whole:17.2f}x" if r_whole else f"{'-':>17s} {'-':>18s}"
        print(f"{n:6d} {r_model:20,.0f} {r_model / bound:13.0%} {whole_s} {real_s} {ratio}")


if __name__ == "__main__":
    main()
