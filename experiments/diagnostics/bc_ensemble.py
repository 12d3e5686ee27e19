"""Is an ensemble of percentile BCs a steadier fallback than one? (issue 70; design data first, then the held-out data)

    python experiments/diagnostics/bc_ensemble.py RUN_DIR [RUN_DIR ...] [--fits 10] [--members 5] [--episodes 10] --out FILE.json

One run directory per dataset gives the data and its config. On it, the library's own percentile BC
(:func:`torchrl_offhrl.recipes.fallback.fit_or_load_bc`, not cached: the same episodes, split, settings and stopping
rule as a run's fallback) is fitted from seeds ``1..fits``. Each cloner is scored alone, and each consecutive group of
``members`` of them (their actions averaged) is scored as an ensemble: ``episodes`` deterministic real-env episodes
per policy, all from the same start states (the evaluation seed of tuning seed 1), D4RL-normalised with the data's own
reference returns as a run's evaluations are. Rows go to ``--out`` (JSON, one entry per dataset, rewritten after each).

A diagnostic: it reads real-env scores to judge a design, on the runs it is given; the rule that decides what it
would change is written on ``docs/results/offline_probes.md`` before it ran.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule

from torchrl_offhrl.recipes.config import model_config, resolve_dataset
from torchrl_offhrl.recipes.fallback import fit_or_load_bc
from torchrl_offhrl.recipes.pipeline import DEFAULT_ORIGIN_SHARE, make_real_env
from torchrl_offhrl.recipes.runs import read_json
from torchrl_offhrl.recipes.train import eval_seed
from torchrl_offhrl.rollouts import evaluate_policy
from torchrl_offhrl.scores import normalized_score


class MeanAction(torch.nn.Module):
    """The members' actions averaged (each already in the action box, so the mean is too)."""

    def __init__(self, members):
        super().__init__()
        self.members = torch.nn.ModuleList(members)

    def forward(self, observation):
        return torch.stack([m(observation) for m in self.members]).mean(0)


def score(policy, env_id: str, episodes: int, ref) -> float:
    env = make_real_env(env_id, None, num_envs=episodes)
    try:
        with torch.no_grad():
            rets = evaluate_policy(env, TensorDictModule(policy, in_keys=["observation"], out_keys=["action"]), episodes,
                                   max_steps=1000, deterministic=True, seed=eval_seed(1))
    finally:
        env.close()
    return normalized_score(env_id, float(rets.mean()), ref)


def dataset_row(run: Path, fits: int, members: int, episodes: int) -> dict:
    cfg = read_json(run / "config.json")
    data = resolve_dataset(cfg)
    share = (cfg.get("model_env") or {}).get("origin_share") or DEFAULT_ORIGIN_SHARE
    ref = (data.metadata.get("ref_min_return"), data.metadata.get("ref_max_return"))
    ref = None if None in ref else ref
    env_id, t0 = cfg["env"]["env_id"], time.time()
    bcs = [fit_or_load_bc(model_config(cfg), data, None, share, seed, progress=False) for seed in range(1, fits + 1)]
    singles = [score(bc, env_id, episodes, ref) for bc in bcs]
    groups = [bcs[i:i + members] for i in range(0, fits - members + 1, members)]
    ensembles = [score(MeanAction(g), env_id, episodes, ref) for g in groups]
    return {"run": run.name, "env_id": env_id, "dataset": cfg["dataset"], "dataset_seed": cfg.get("dataset_seed"), "share": share,
            "singles": singles, "ensembles": ensembles, "members": members, "episodes": episodes, "seconds": round(time.time() - t0, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--fits", type=int, default=10)
    ap.add_argument("--members", type=int, default=5)
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows = json.loads(args.out.read_text()) if args.out.is_file() else []
    done = {r["run"] for r in rows}
    for run in args.runs:
        if run.name in done:
            continue
        row = dataset_row(run, args.fits, args.members, args.episodes)
        rows.append(row)
        args.out.write_text(json.dumps(rows, indent=1))
        s, e = row["singles"], row["ensembles"]
        print(f"{run.name}: singles {sum(s) / len(s):.1f} (min {min(s):.1f}, max {max(s):.1f}), ensembles "
              f"{', '.join(f'{x:.1f}' for x in e)} ({row['seconds']:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
