"""Which offline signal ranks a run's intermediate policies as the real env does?

    python experiments/diagnostics/selection_probe.py RUN_DIR [RUN_DIR ...] [--out FILE.json]

For every ``snapshot-<frames>.pt`` of a run (``train.snapshot_frames``; the
runs of ``experiments/results/robustness.py`` keep one per evaluation), the policy is
rolled out deterministically in the run's pessimistic model env as its
training evaluations do (``eval.model_episodes`` episodes from the data's
start states, member ``i % K`` for episode ``i``, the evaluation's seed), and
candidate selection signals are computed from those rollouts alone: the
return (undiscounted, discounted with several gammas, truncated at several
horizons), each as the mean over episodes and as the worst member's mean (a
lower confidence bound over the ensemble), the reward per step, the
pessimistic-termination rate and the ensemble's discrepancy on the visited
model states (mean, 90th percentile: lower is picked, as for the rate). The real-env score is the run's own record at
that evaluation (read, never used to compute a signal). For each signal it
prints the real score of the evaluation it would pick and whether that is
within 5 points of the run's best.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import torch

from torchrl_offhrl.recipes.config import model_config, model_env_config, resolve_dataset
from torchrl_offhrl.recipes.evaluation import load_run_agent
from torchrl_offhrl.recipes.pipeline import fit_or_load_models, make_model_env
from torchrl_offhrl.rollouts import evaluate_policy, first_episode_mask

GAMMAS = (0.99, 0.995, 0.998)
HORIZONS = (100, 200, 300, 500, 1000)


#: signals where the smaller value is picked
LOWER_IS_BETTER = ("penalized", "disc_mean", "disc_p90")


def signals(reward: torch.Tensor, alive: torch.Tensor, member: torch.Tensor, penalized: torch.Tensor, discrepancy: torch.Tensor | None = None) -> dict:
    """Every candidate signal of one policy's model rollouts (``[E, T]`` rewards, discrepancies and first-episode mask, ``[E]`` members)."""
    r = reward * alive
    T = r.shape[1]
    per_episode = {"total": r.sum(1)}
    for g in GAMMAS:
        per_episode[f"disc{g}"] = (r * g ** torch.arange(T, dtype=r.dtype)).sum(1)
    for h in HORIZONS:
        per_episode[f"h{h}"] = r[:, :h].sum(1)
    out = {}
    for k, v in per_episode.items():
        out[f"{k}_mean"] = float(v.mean())
        out[f"{k}_lcb"] = min(float(v[member == m].mean()) for m in member.unique())
    out["rate_mean"] = float(r.sum() / alive.sum())
    out["len_mean"] = float(alive.sum(1).float().mean())
    out["penalized"] = float(penalized.float().mean())
    if discrepancy is not None:
        d = discrepancy[alive].double()
        out["disc_mean"] = float(d.mean())
        out["disc_p90"] = float(torch.quantile(d, 0.9))
    return out


def probe(run_dir: Path, episodes: int | None = None, horizon: int | None = None, pessimism: bool = True) -> list[dict]:
    cfg, _, agent, _, _ = load_run_agent(run_dir, num_envs=1)
    data = resolve_dataset(cfg)
    pcfg = model_config(cfg)
    ensemble, cvae, _ = fit_or_load_models(pcfg, data, progress=False)
    pcfg["env"], _ = model_env_config(cfg, data.metadata.get("level"), data)
    if horizon is not None:  # e.g. the real episode's 1000 steps where training cuts model episodes at 100
        pcfg["env"]["horizon"] = horizon
    n = int(episodes or cfg["eval"].get("model_episodes") or cfg["eval"]["episodes"])
    menv = make_model_env(pcfg, ensemble, cvae, data, batch_size=n, threshold=cfg["threshold"] if pessimism else float("inf"), reset_states="initial", member_draw="cyclic")
    agent.attach(menv)
    records = {r["frames"]: r for r in json.loads((run_dir / "evals.json").read_text())}
    rows = []
    for snap in sorted(run_dir.glob("snapshot-*.pt"), key=lambda p: int(re.findall(r"\d+", p.name)[0])):
        s = torch.load(snap, weights_only=True)
        agent.load_state_dict(s["agent"])
        with torch.random.fork_rng():
            _, td = evaluate_policy(menv, agent.policy, n, max_steps=int(cfg["eval"]["max_steps"]), seed=int(cfg["seed"]) * 1000 + 7,
                                    return_rollout=True)
        alive = first_episode_mask(td["next", "done"].reshape(n, -1))
        pen = (td["next", "penalized"].reshape(n, -1) & alive).any(1)
        sig = signals(td["next", "reward"].reshape(n, -1).double(), alive, td["model_member"][:, 0].reshape(-1), pen,
                      td["next", "discrepancy"].reshape(n, -1))
        rows.append({"run": str(run_dir), "frames": int(s["frames"]), "real": records[int(s["frames"])]["normalized_d4rl"], **sig})
    return rows


def picks(rows: list[dict]) -> dict[str, tuple[float, bool]]:
    """``{signal: (real score of the evaluation it picks, within 5 of the best)}`` for one run's rows."""
    best = max(r["real"] for r in rows)
    out = {}
    for k in rows[0]:
        if k in ("run", "frames", "real"):
            continue
        pick = (min if k in LOWER_IS_BETTER else max)(rows, key=lambda r: r[k])
        out[k] = (pick["real"], best - pick["real"] <= 5.0)
    out["last"] = (rows[-1]["real"], best - rows[-1]["real"] <= 5.0)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--model-episodes", type=int, default=None, help="model episodes per policy (default: the run's eval.model_episodes)")
    p.add_argument("--horizon", type=int, default=None, help="model episode length (default: the run's model_env.horizon)")
    p.add_argument("--no-pessimism", action="store_true", help="no pessimistic termination: the ensemble's members and the env's own termination alone")
    a = p.parse_args()
    torch.set_num_threads(1)
    allrows, table = [], {}
    for run in a.runs:
        rows = probe(run, a.model_episodes, a.horizon, pessimism=not a.no_pessimism)
        allrows += rows
        for k, (score, hit) in picks(rows).items():
            table.setdefault(k, []).append((run.name, score, hit))
    for k, vals in table.items():
        mean = sum(v[1] for v in vals) / len(vals)
        print(f"{k:14s} mean picked {mean:6.1f}  hits {sum(v[2] for v in vals)}/{len(vals)}  " + " ".join(f"{v[1]:.0f}" for v in vals))
    if a.out:
        a.out.write_text(json.dumps(allrows, indent=1))


if __name__ == "__main__":
    main()
