"""Is UOF's shortfall on the last goal the high level's choice of options, or the low level's execution of them?

    python experiments/diagnostics/uof_oracle_options.py RUN_DIR [RUN_DIR ...] [--episodes 30] [--out FILE.json]

Each run directory is a finished UOF run of `offhrl train` / `offhrl results blockstack run` (its `checkpoint.pt`
and `config.json`; the CVAE from the model cache). Its last policy is evaluated twice in the real env, as the
run's own evaluations do (`GoalEvaluator`: `--episodes` episodes per goal, deterministic, success within the
training horizon of 25 steps and within 50, the run's evaluation seed):

* `greedy`: DIOL picks the options (what every result reports);
* `oracle`: the options follow the goal's abstract demonstration (UOF's `[[0], [0, 1], [0, 1, 2]]`), i.e. the
  low level is handed the right sub-goals in the right order (`UOFPolicy.oracle_options`).

If `oracle` is about `greedy`, the high level chooses well and the low level is what fails; if `oracle` is
well above, the high level's choices cost the difference. Printed per run and as an IQM over runs per goal.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def evaluate(run: Path, episodes: int) -> dict:
    from torchrl_offhrl.recipes.config import latent_bound
    from torchrl_offhrl.recipes.evaluation import GoalEvaluator, load_run_agent
    from torchrl_offhrl.recipes.pipeline import make_real_env
    from torchrl_offhrl.recipes.train import eval_seed

    cfg, env, agent, _state, cvae = load_run_agent(run, num_envs=1, policy="last")
    n_goals = int(env.observation_spec["desired_goal"].shape[-1])  # one flag per goal
    env.close(raise_if_closed=False)
    if cfg["algo"]["name"] != "uof":
        raise SystemExit(f"{run}: a {cfg['algo']['name']} run; this diagnostic reads UOF runs (its option policy)")
    env_id = cfg["env"]["env_id"]
    goals = [k for k in range(n_goals) for _ in range(episodes)]
    max_steps, horizon = int(cfg["eval"]["max_steps"]), int(cfg["env"].get("horizon", 25))
    out = {}
    for mode in ("greedy", "oracle"):
        eval_env = agent.attach(make_real_env(env_id, cvae, num_envs=len(goals), latent_bound=latent_bound(cfg), goals=goals,
                                              max_episode_steps=max_steps))
        agent.policy.oracle_options = mode == "oracle"
        rec = GoalEvaluator(eval_env, env_id, episodes, n_goals, horizon, max_steps, seed=eval_seed(cfg["seed"]))(agent)
        eval_env.close(raise_if_closed=False)
        out[mode] = {"success_per_goal": rec["success_per_goal"], f"success_per_goal_h{max_steps}": rec[f"success_per_goal_h{max_steps}"]}
    agent.policy.oracle_options = False
    return out


def main() -> None:
    from torchrl_offhrl.stats import iqm_ci

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--episodes", type=int, default=30, help="episodes per goal (the results' 30)")
    p.add_argument("--out", type=Path, help="also write the per-run numbers to this JSON file")
    args = p.parse_args()
    torch.set_num_threads(1)
    res = {}
    for run in args.runs:
        res[run.name] = r = evaluate(run, args.episodes)
        print(f"{run.name}: greedy {' / '.join(f'{x:.2f}' for x in r['greedy']['success_per_goal'])}, "
              f"oracle {' / '.join(f'{x:.2f}' for x in r['oracle']['success_per_goal'])} (horizon 25)", flush=True)
    by_goals: dict[int, list[dict]] = {}  # runs of one task together (task 1: 3 goals, task 2: 6)
    for r in res.values():
        by_goals.setdefault(len(r["greedy"]["success_per_goal"]), []).append(r)
    for n, group in sorted(by_goals.items()):
        for mode in ("greedy", "oracle"):
            cells = []
            for k in range(n):
                m, lo, hi = iqm_ci([r[mode]["success_per_goal"][k] for r in group])
                cells.append(f"{m:.2f} [{lo:.2f}, {hi:.2f}]")
            print(f"{n} goals, IQM over {len(group)} runs, {mode}: " + " / ".join(cells))
        change = [r["oracle"]["success_per_goal"][-1] - r["greedy"]["success_per_goal"][-1] for r in group]
        m, lo, hi = iqm_ci(change)
        print(f"{n} goals, last goal, oracle - greedy: {m:+.2f} [{lo:+.2f}, {hi:+.2f}], {sum(c > 0 for c in change)} of {len(change)} up")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1) + "\n")
        print(f"written: {args.out}")


if __name__ == "__main__":
    main()
