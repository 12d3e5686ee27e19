"""Gradient updates per second of the behaviour-policy trainers, side by side in one run.

    python benchmarks/behaviour_updates.py [--threads 1] [--device cpu] [--updates 300]

For SAC and CrossQ (``torchrl_offhrl.agents.behaviour.BehaviourLearner``,
the exact update rule of ``scripts/train_behaviour.py``) at HalfCheetah-v5
dimensions (17 observations, 6 actions), batch 256, actor MLP(256, 256), it
times ``--updates`` updates drawn from a TorchRL replay buffer of random
transitions (sampling included), for several critic widths. The last column
is each row's speed relative to SAC with a 256-wide critic measured in the
same run. One environment step costs one update in these trainers, so
updates/s bounds the trainers' environment steps/s.
"""
from __future__ import annotations

import argparse
import time

import torch


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    p.add_argument("--updates", type=int, default=300)
    a = p.parse_args()
    torch.set_num_threads(a.threads)

    from tensordict import TensorDict
    from torchrl.data import Bounded, LazyTensorStorage, ReplayBuffer

    from torchrl_offhrl.agents.behaviour import BehaviourLearner
    from torchrl_offhrl.data.policies.actors import make_behaviour_actor

    dev = torch.device(a.device)
    obs_dim, act_dim, n = 17, 6, 100_000
    spec = Bounded(-torch.ones(act_dim), torch.ones(act_dim), shape=(act_dim,), device=dev)
    data = TensorDict(
        observation=torch.randn(n, obs_dim),
        action=torch.rand(n, act_dim) * 2 - 1,
        next=TensorDict(
            observation=torch.randn(n, obs_dim),
            reward=torch.randn(n, 1),
            done=torch.zeros(n, 1, dtype=torch.bool),
            terminated=torch.zeros(n, 1, dtype=torch.bool),
            batch_size=[n],
        ),
        batch_size=[n],
    )
    rb = ReplayBuffer(storage=LazyTensorStorage(n, device=dev), batch_size=256)
    rb.extend(data)

    rows = []
    for algorithm, width in (("sac", 256), ("crossq", 256), ("sac", 512), ("crossq", 512)):
        torch.manual_seed(0)
        actor = make_behaviour_actor(obs_dim, act_dim, -torch.ones(act_dim), torch.ones(act_dim)).to(dev)
        learner = BehaviourLearner(actor, obs_dim, act_dim, spec, algorithm, critic_hidden=(width, width), device=dev)
        for _ in range(20):  # warm-up
            learner.update(rb.sample())
        if dev.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(a.updates):
            learner.update(rb.sample())
        if dev.type == "cuda":
            torch.cuda.synchronize()
        rows.append((algorithm, width, a.updates / (time.perf_counter() - t0)))

    base = rows[0][2]
    print(f"device {dev}, torch threads {torch.get_num_threads()}, {a.updates} updates per row, batch 256, actor MLP(256, 256)\n")
    print("| algorithm | critic | updates/s | vs SAC 256 |")
    print("|---|---|---|---|")
    for algorithm, width, ups in rows:
        print(f"| {algorithm} | MLP({width}, {width}) | {ups:.1f} | {ups / base:.2f} |")


if __name__ == "__main__":
    main()
