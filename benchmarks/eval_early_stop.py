"""Real-env evaluation with and without the early stop (``evaluate_policy(stop_early=...)``), side by side.

    .venv/bin/python benchmarks/eval_early_stop.py [--episodes 30] [--max-steps 1000] [--threads 1]

Each row: one evaluation protocol (Hopper-v5, ``--episodes`` parallel envs, ``--max-steps``, seeded) run by a policy in
both modes, best of 2 repeats each; the returns are checked equal (to float32's last digit) before the times are
printed. The stop saves the steps after the last env's first episode ended, so it gains most on policies that fall
(an untrained or collapsed agent) and nothing on one whose episodes all run to ``--max-steps``.
"""
from __future__ import annotations

import argparse
import time

import torch

from torchrl_offhrl.data import load_policy, make_gym_env
from torchrl_offhrl.rollouts import evaluate_policy


def _linear():
    from tensordict.nn import TensorDictModule

    g = torch.Generator().manual_seed(0)
    lin = torch.nn.Linear(11, 3)
    with torch.no_grad():
        lin.weight.copy_(torch.randn(3, 11, generator=g))
        lin.bias.zero_()
    return TensorDictModule(torch.nn.Sequential(lin, torch.nn.Tanh()), in_keys=["observation"], out_keys=["action"])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=30)
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    medium, _ = load_policy("hopper-medium")
    cases = [("random actions, sampled", None, False), ("falling linear policy, deterministic", _linear(), True),
             ("hopper-medium actor, deterministic", medium, True), ("hopper-medium actor, sampled", medium, False)]
    env = make_gym_env("Hopper-v5", num_envs=a.episodes)
    print(f"Hopper-v5, {a.episodes} envs, max_steps {a.max_steps}, {a.threads} thread(s), torch {torch.__version__}")
    print(f"{'policy':40s} {'steps run':>9s} {'full s':>8s} {'stopped s':>9s} {'speed-up':>8s}")
    for name, policy, det in cases:
        times, out = {}, {}
        for stop in (False, True):
            best = float("inf")
            for _ in range(2):
                t = time.perf_counter()
                rets, td = evaluate_policy(env, policy, a.episodes, max_steps=a.max_steps, deterministic=det, seed=7, return_rollout=True,
                                           stop_early=stop)
                best = min(best, time.perf_counter() - t)
            times[stop], out[stop] = best, (rets, td.shape[-1])
        torch.testing.assert_close(out[True][0], out[False][0], rtol=1e-6, atol=0.0)
        print(f"{name:40s} {out[True][1]:9d} {times[False]:8.2f} {times[True]:9.2f} {times[False] / times[True]:7.2f}x")


if __name__ == "__main__":
    main()
