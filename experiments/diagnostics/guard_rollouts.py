"""Every kept policy of a run and its start, rolled out in the run's evaluation model env, step by step, for guard designs.

    python experiments/diagnostics/guard_rollouts.py RUN_DIR [RUN_DIR ...] --out FOLDER

The guard (``torchrl_offhrl.recipes.selection``) compares a policy with the
run's start on whole-length model episodes, paired by start state and member.
To try other comparisons (returns truncated at a horizon, without the
pessimism's penalty, per member or pooled) without rolling the policies out
again, this keeps, for the start (the selector's step-0 agent in the run's
checkpoint) and every ``snapshot-<frames>.pt``, each model episode's rewards
per step, where it ended and why, and its member: the evaluation model env
is rebuilt as training built it (the offline rules from the run's data and
models, its latent origin, ``eval.model_episodes`` episodes from the data's
start states, member ``i % K``, ``eval.max_steps`` steps, the evaluation's
seed). The run's recorded real score of each policy is copied beside it
(read, never used to compute anything here). Writes ``FOLDER/<run>.pt``.
The start's recomputed episode returns are checked against the run's record
of them: a mismatch (another code version's env) is printed.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import torch

from torchrl_offhrl.recipes.evaluation import load_run_agent, run_models
from torchrl_offhrl.recipes.train import eval_seed
from torchrl_offhrl.rollouts import evaluate_policy, first_episode_mask
from torchrl_offhrl.utils import load_torch_file


def rollouts(run: Path) -> dict:
    cfg, env, agent, state, cvae = load_run_agent(run, num_envs=1)  # cvae: decoding from the run's latent origin
    env.close()
    rm = run_models(run)
    ev = cfg["eval"]
    n, steps = int(ev.get("model_episodes") or ev["episodes"]), int(ev["max_steps"])
    menv = rm.model_env(cvae)
    agent.attach(menv)
    records = {int(r["frames"]): r for r in json.loads((run / "evals.json").read_text())}
    policies = [(0, state["selection"]["start"]["agent"])]
    for p in sorted(run.glob("snapshot-*.pt"), key=lambda p: int(re.findall(r"\d+", p.name)[-1])):
        policies.append((int(re.findall(r"\d+", p.name)[-1]), load_torch_file(p, "snapshot", "")["agent"]))
    out = {"run": run.name, "config": {k: cfg[k] for k in ("algo", "env", "dataset", "dataset_seed", "seed", "threshold", "resolved_model_env")},
           "penalty": float(menv.base_env.penalty), "gamma": float(cfg["algo"].get("gamma", 0.99)), "policies": []}
    for frames, sd in policies:
        agent.load_state_dict(sd)
        with torch.random.fork_rng():
            rets, td = evaluate_policy(menv, agent.eval_policy, n, max_steps=steps, deterministic=True, seed=eval_seed(int(cfg["seed"])),
                                       return_rollout=True)
        alive = first_episode_mask(td["next", "done"].reshape(n, -1))
        rec = records[frames]
        out["policies"].append({
            "frames": frames, "real": rec["normalized_d4rl"],
            "reward": td["next", "reward"].reshape(n, -1).float() * alive,
            "alive": alive, "penalized": td["next", "penalized"].reshape(n, -1) & alive,
            "terminated": td["next", "terminated"].reshape(n, -1) & alive,
            "member": td["model_member"][:, 0].reshape(-1).clone(),
            "returns": rets.double().clone(), "recorded_returns": rec.get("model_episode_returns")})
        if rec.get("model_episode_returns") is not None:
            gap = (rets.double() - torch.tensor(rec["model_episode_returns"], dtype=torch.float64)).abs().max()
            if gap > 1e-2:
                print(f"{run.name} frames {frames}: recomputed model returns differ from the record by up to {float(gap):.3g}")
        print(f"{run.name} {frames:6d} real {rec['normalized_d4rl']:6.1f} model {float(rets.mean()):8.1f} "
              f"penalized {float(out['policies'][-1]['penalized'].any(1).float().mean()):.2f} "
              f"length {float(alive.sum(1).float().mean()):6.1f}", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    a.out.mkdir(parents=True, exist_ok=True)
    for run in a.runs:
        dest = a.out / f"{run.name}.pt"
        if dest.is_file():
            continue
        torch.save(rollouts(run), dest)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
