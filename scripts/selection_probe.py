"""Which offline signal ranks a run's intermediate policies as the real env does?

    python scripts/selection_probe.py RUN_DIR [RUN_DIR ...] [--model-episodes 100 --real-episodes 30 --out FILE.json]

For every ``snapshot-<frames>.pt`` of a run (``train.snapshot_frames``), the
policy is rolled out deterministically in the real env (``--real-episodes``,
seed 12345: not the training evaluation's seed) and in the run's pessimistic
model env (``--model-episodes`` from the data's start states), and the
candidate selection signals are printed next to the real score: the model's
mean return, its mean minus one standard error, the worst member's mean (a
lower confidence bound over the ensemble), the model episodes' mean length and
their pessimistic-termination rate. Rank correlations within each run tell
which signal picks the best real policy without the real env.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import torch

from torchrl_offhrl.recipes.config import model_config, model_env_config, resolve_dataset
from torchrl_offhrl.recipes.evaluation import load_run_agent
from torchrl_offhrl.recipes.pipeline import fit_or_load_models, make_model_env
from torchrl_offhrl.rollouts import evaluate_policy, first_episode_mask
from torchrl_offhrl.scores import normalized_score


def probe(run_dir: Path, model_episodes: int, real_episodes: int) -> list[dict]:
    cfg, env, agent, state, cvae = load_run_agent(run_dir, num_envs=real_episodes)
    data = resolve_dataset(cfg)
    pcfg = model_config(cfg)
    ensemble, cvae, _ = fit_or_load_models(pcfg, data, progress=False)
    pcfg["env"], _ = model_env_config(cfg, data.metadata.get("level"), data)
    menv = make_model_env(pcfg, ensemble, cvae, data, batch_size=model_episodes, threshold=cfg["threshold"], reset_states="initial")
    agent.attach(menv)
    rows = []
    snaps = sorted(run_dir.glob("snapshot-*.pt"), key=lambda p: int(re.findall(r"\d+", p.name)[0]))
    for snap in snaps:
        s = torch.load(snap, weights_only=True)
        agent.load_state_dict(s["agent"])
        real = evaluate_policy(env, agent.policy, real_episodes, max_steps=1000, seed=12345)
        rets, td = evaluate_policy(menv, agent.policy, model_episodes, max_steps=1000, seed=777, return_rollout=True)
        alive = first_episode_mask(td["next", "done"].reshape(model_episodes, -1))
        length = alive.sum(1).float()
        pen = (td["next", "penalized"].reshape(model_episodes, -1) & alive).any(1).float()
        member = td["model_member"][:, 0].reshape(-1)
        r = rets.double()
        per_member = [float(r[member == k].mean()) for k in member.unique()]
        rows.append({
            "run": run_dir.name, "frames": int(s["frames"]),
            "train_eval": s["record"].get("normalized_d4rl"),
            "real": normalized_score(cfg["env"]["env_id"], float(real.mean())), "real_std": float(real.std()),
            "model_mean": float(r.mean()), "model_se_lcb": float(r.mean() - r.std() / len(r) ** 0.5),
            "model_min_member": min(per_member), "model_len": float(length.mean()), "model_penalized": float(pen.mean()),
        })
        print(json.dumps(rows[-1]))
    env.close()
    return rows


def spearman(a, b) -> float:
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1]) if len(a) > 2 else float("nan")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--model-episodes", type=int, default=100)
    p.add_argument("--real-episodes", type=int, default=30)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args()
    torch.set_num_threads(1)
    allrows = []
    for run in a.runs:
        rows = probe(run, a.model_episodes, a.real_episodes)
        allrows += rows
        real = [x["real"] for x in rows]
        for key in ("model_mean", "model_se_lcb", "model_min_member", "model_len", "model_penalized", "train_eval"):
            vals = [x[key] for x in rows]
            pick = rows[int(np.argmax(vals))]["real"] if key != "model_penalized" else rows[int(np.argmin(vals))]["real"]
            print(f"{run.name} {key:18s} spearman {spearman(vals, real):+.2f}  picks real {pick:.1f} (best {max(real):.1f}, last {real[-1]:.1f})")
    if a.out:
        a.out.write_text(json.dumps(allrows, indent=1))


if __name__ == "__main__":
    main()
