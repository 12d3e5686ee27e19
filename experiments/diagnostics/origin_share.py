"""Can the model tell which latent origin starts an agent best? The start policy of several origin shares, scored in the model and in the real env.

    python experiments/diagnostics/origin_share.py RUN_DIR [RUN_DIR ...] [--shares 0.05 0.1 0.25 0.5 1.0] [--out FILE.json]

An agent's start (its untrained policy, whose latent sits near 0) decodes to
the latent origin's action: ``model_env.latent_origin=best`` clones the
data's highest-return episodes covering ``origin_share`` of the data (0.1
shipped, from the literature, not tuned), ``behaviour`` (share 1) all of it.
For each run's data and models and each share, the origin is fitted (or
loaded from the cache), the run's start agent acts through it, and its
deterministic policy is rolled out in the run's evaluation model env
(``eval.model_episodes`` whole-length episodes from the data's start states,
member ``i % K``) and in the real env (``eval.episodes`` episodes). Printed
per share: the model's mean and worst-member return, the worst member's
95% lower bound on the paired gain over share 0.1 (the guard's statistic),
and the real D4RL score (read to judge the model's ranking, never inside
it). Evaluation seeds: the tuning seed 1's, whatever the run's seed.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from torchrl_offhrl.models import ConditionalVAE
from torchrl_offhrl.recipes.evaluation import load_run_agent, run_models
from torchrl_offhrl.recipes.pipeline import apply_latent_origin, make_real_env
from torchrl_offhrl.recipes.selection import paired_gain_lcb
from torchrl_offhrl.recipes.train import eval_seed
from torchrl_offhrl.rollouts import evaluate_policy
from torchrl_offhrl.scores import normalized_score


def score_shares(run: Path, shares: list[float]) -> list[dict]:
    cfg, env, agent, state, _ = load_run_agent(run, num_envs=1)
    env.close()
    agent.load_state_dict(state["selection"]["start"]["agent"])
    rm = run_models(run)  # as training: the rules see the CVAE without an origin
    data, mcfg, model_dir = rm.data, rm.pcfg, rm.model_dir
    bound = float(mcfg["env"]["latent_bound"])
    ev, seed, env_id = cfg["eval"], eval_seed(1), cfg["env"]["env_id"]
    n, episodes, steps = int(ev.get("model_episodes") or ev["episodes"]), int(ev["episodes"]), int(ev["max_steps"])
    rows, base = [], None
    for share in shares:
        c = ConditionalVAE.load(model_dir / "cvae.pt")
        origin = {"latent_origin": "behaviour"} if share >= 1.0 else {"latent_origin": "best", "origin_share": share}
        apply_latent_origin({**mcfg, "env": {**mcfg["env"], **origin}}, data, c, model_dir, progress=False)
        menv = agent.attach(rm.model_env(c, batch_size=n, threshold=mcfg["env"].get("threshold")))
        real = agent.attach(make_real_env(env_id, c, num_envs=episodes, latent_bound=bound))
        with torch.random.fork_rng():
            rets, td = evaluate_policy(menv, agent.eval_policy, n, max_steps=steps, deterministic=True, seed=seed, return_rollout=True)
            real_rets = evaluate_policy(real, agent.eval_policy, episodes, max_steps=steps, deterministic=True, seed=seed)
        real.close()
        member = td["model_member"][:, 0].reshape(-1)
        rec = {"model_episode_returns": [float(x) for x in rets.double()], "model_episode_members": [int(x) for x in member]}
        if abs(share - 0.1) < 1e-9:
            base = rec
        worst = min(float(rets[member == k].mean()) for k in member.unique())
        rows.append({"run": run.name, "share": share, "model_mean": float(rets.mean()), "model_worst_member": worst, "rec": rec,
                     "real": normalized_score(env_id, float(real_rets.mean()))})
    for r in rows:
        r["gain_lcb_vs_0.1"] = None if base is None else paired_gain_lcb(r["rec"], base)
        print(f"{r['run']:40s} share {r['share']:5.2f} model mean {r['model_mean']:8.1f} worst member {r['model_worst_member']:8.1f} "
              f"gain lcb vs 0.1 {r['gain_lcb_vs_0.1'] if r['gain_lcb_vs_0.1'] is None else round(r['gain_lcb_vs_0.1'], 1)!s:>8s} "
              f"real {r['real']:6.1f}", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--shares", nargs="+", type=float, default=[0.05, 0.1, 0.25, 0.5, 1.0])
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for run in a.runs:
        rows += score_shares(run, a.shares)
        if a.out:
            a.out.write_text(json.dumps([{k: v for k, v in r.items() if k != "rec"} for r in rows], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
