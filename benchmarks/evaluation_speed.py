"""Real-env evaluation: with and without the early stop, and N seeds' evaluations apart or as one rollout, side by side.

    .venv/bin/python benchmarks/evaluation_speed.py [--episodes 30] [--max-steps 1000] [--threads 1] [--seeds 1 5 10]

Table 1, the early stop (``evaluate_policy(stop_early=...)``).
Each row: one evaluation protocol (Hopper-v5, ``--episodes`` parallel envs, ``--max-steps``, seeded) run by a policy in
both modes, best of 2 repeats each; the returns are checked equal (to float32's last digit) before the times are
printed. The stop saves the steps after the last env's first episode ended, so it gains most on policies that fall
(an untrained or collapsed agent) and nothing on one whose episodes all run to ``--max-steps``.

Table 2, seeds' evaluations as one rollout (``SeedsEvaluation``'s path: ``SeedBatchedPolicy`` over N copies of the
hopper-medium actor, each with its own weight noise, on one env of N x ``--episodes`` envs seeded per block) against
the same N evaluations one after the other, deterministic, early stop on in both; best of 2 each.
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
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 5, 10])
    p.add_argument("--seeds-envs", nargs="+", default=["hopper", "halfcheetah"], help="table 2's envs (their medium actors)")
    p.add_argument("--skip-stop", action="store_true", help="table 2 only")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    medium, _ = load_policy("hopper-medium")
    for name in a.seeds_envs:
        seeds_table(name, a)
    if a.skip_stop:
        return
    cases = [("random actions, sampled", None, False), ("falling linear policy, deterministic", _linear(), True),
             ("hopper-medium actor, deterministic", medium, True), ("hopper-medium actor, sampled", medium, False)]
    env = make_gym_env("Hopper-v5", num_envs=a.episodes)
    print(f"\nHopper-v5, {a.episodes} envs, max_steps {a.max_steps}, {a.threads} thread(s), torch {torch.__version__}")
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


def seeds_table(name: str, a) -> None:
    import copy

    from torchrl_offhrl.agents.seeds import SeedBatchedPolicy, stacked_module_params
    from torchrl_offhrl.registry import task_of

    actor, _ = load_policy(f"{name}-medium")
    env_id = task_of(name).env_id
    print(f"\n{env_id}: N seeds' deterministic evaluations ({a.episodes} episodes each, {name}-medium actor with per-seed weight noise)")
    print(f"{'seeds':>5s} {'apart s':>8s} {'one rollout s':>13s} {'speed-up':>8s} {'IQM |diff| of returns':>22s}")
    for n in a.seeds:
        policies = []
        for i in range(n):
            p = copy.deepcopy(actor)
            g = torch.Generator().manual_seed(100 + i)
            with torch.no_grad():
                for w in p.parameters():
                    w.add_(0.05 * torch.randn(w.shape, generator=g))
            policies.append(p)
        seeds = [1000 * (i + 4) + 7 for i in range(n)]  # the runs' eval seeds (seed * 1000 + 7)
        envs = [make_gym_env(env_id, num_envs=a.episodes) for _ in range(n)]
        both = make_gym_env(env_id, num_envs=n * a.episodes)
        batched = SeedBatchedPolicy(policies[0], stacked_module_params(policies))
        env_seeds = [s + j for s in seeds for j in range(a.episodes)]
        t_apart = t_one = float("inf")
        for _ in range(2):
            t = time.perf_counter()
            apart = torch.cat([evaluate_policy(e, p, a.episodes, max_steps=a.max_steps, seed=s) for e, p, s in zip(envs, policies, seeds)])
            t_apart = min(t_apart, time.perf_counter() - t)
            t = time.perf_counter()
            one = evaluate_policy(both, batched, n * a.episodes, max_steps=a.max_steps, seed=0, env_seeds=env_seeds)
            t_one = min(t_one, time.perf_counter() - t)
        diff = (one - apart).abs().sort().values
        iqm = float(diff[len(diff) // 4: len(diff) - len(diff) // 4].mean())
        print(f"{n:5d} {t_apart:8.2f} {t_one:13.2f} {t_apart / t_one:7.2f}x {iqm:22.3g}")


if __name__ == "__main__":
    main()
