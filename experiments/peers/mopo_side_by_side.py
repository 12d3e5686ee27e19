"""MOPO, ours and OfflineRL-Kit's, on the same data at the same budget: one table per dataset (issue 72).

    python experiments/peers/mopo_side_by_side.py [--ours outputs/results/demo] [--kit outputs/peers/offlinerlkit_mopo]
        [--datasets hopper-medium halfcheetah-medium] [--out docs/results/mopo_side_by_side.md]

Reads what the two runs left, runs nothing:

* ours: ``<ours>/mopo-<dataset>-seed<N>/`` (``offhrl results table1 run --scale demo --algos mopo``): the last
  policy's evaluation (``summary.json``: ``final``), the policy the run returns (``selected``: the guard's choice), the
  best of its evaluations (``evals.json``, the initial one aside) and the data's own score;
* the kit's: ``<kit>/<dataset>/seed<N>/`` (``experiments/peers/offlinerlkit_mopo.py``): our evaluation of its last
  policy (``final_eval.json``, 30 episodes as ours), and its own per-epoch evaluations (its progress CSV, 10 episodes
  each: the last, and the best of those nearest to our runs' evaluation points, so that "best" picks from as many
  evaluations on both sides).

Each row: IQM [95% bootstrap CI] over seeds and the per-seed values, D4RL-normalised on the data's reference returns.
Writes the page and a JSON of the rows beside it (``.json``).
"""
from __future__ import annotations

import argparse
import csv
import json
from collections.abc import Sequence
from pathlib import Path

from torchrl_offhrl.stats import iqm_ci
from torchrl_offhrl.utils import atomic_write, write_json



def our_runs(root: Path, dataset: str) -> dict[int, dict]:
    """Seed -> the scores of our finished MOPO runs on ``dataset`` (those with a summary)."""
    out = {}
    for d in sorted(root.glob(f"mopo-{dataset}-seed*")):
        summary = d / "summary.json"
        if not summary.is_file():
            continue
        s = json.loads(summary.read_text())
        evals = json.loads((d / "evals.json").read_text()) if (d / "evals.json").is_file() else []
        trained = [e["normalized_d4rl"] for e in evals if e.get("step", 0) > 0 and "normalized_d4rl" in e]
        out[int(s["seed"])] = {"last": s["final"]["normalized_d4rl"], "returned": (s.get("selected") or s["final"])["normalized_d4rl"],
                               "best": max(trained) if trained else None, "data": s.get("behaviour_normalized_d4rl"),
                               "updates": s["final"].get("updates"),
                               "points": [e["updates"] for e in evals if e.get("step", 0) > 0 and "updates" in e]}
    return out


def kit_runs(root: Path, dataset: str, points: Sequence[int] = ()) -> dict[int, dict]:
    """Seed -> the scores of the kit's finished MOPO runs on ``dataset`` (those with our final evaluation); ``points``: our
    runs' evaluation points in gradient steps, where the kit's own evaluations (one per epoch) are read for "best" (at
    each point the kit's evaluation nearest to it; none without points)."""
    out = {}
    for d in sorted((root / dataset).glob("seed*")):
        final = d / "final_eval.json"
        if not final.is_file():
            continue
        f = json.loads(final.read_text())
        rows = []
        for path in d.glob("log/*/*/*/record/policy_training_progress.csv"):
            with open(path, newline="") as fh:
                rows = [r for r in csv.DictReader(fh) if r.get("eval/normalized_episode_reward")]
        own = [(int(float(r["timestep"])), float(r["eval/normalized_episode_reward"])) for r in rows]
        at_ours = [min(own, key=lambda tv: abs(tv[0] - p))[1] for p in points] if own else []  # nearest to each of ours
        out[int(f["seed"])] = {"last": f["normalized_mean"], "own_last": own[-1][1] if own else None,
                               "own_best": max(at_ours) if at_ours else None, "updates": own[-1][0] if own else None,
                               "episodes": f["episodes"]}
    return out


def _cell(values: list[float | None]) -> str:
    v = [x for x in values if x is not None]
    if not v:
        return "-"
    m, lo, hi = iqm_ci(v)
    return f"{m:.1f} [{lo:.1f}, {hi:.1f}]"


def _seeds(runs: dict[int, dict], key: str) -> str:
    return ", ".join(f"{runs[s][key]:.1f}" for s in sorted(runs) if runs[s].get(key) is not None) or "-"


def rows(ours_root: Path, kit_root: Path, datasets) -> list[dict]:
    out = []
    for ds in datasets:
        ours = our_runs(ours_root, ds)
        kit = kit_runs(kit_root, ds, sorted({p for r in ours.values() for p in r["points"]}))
        data = next((r["data"] for r in ours.values() if r.get("data") is not None), None)
        for who, runs, what in (("ours", ours, (("last", "last policy, 30 episodes"), ("best", "best evaluation (5, 30 episodes each)"),
                                                  ("returned", "returned by the run (the guard)"))),
                                ("OfflineRL-Kit", kit, (("last", "last policy, 30 episodes (our evaluation)"),
                                                        ("own_last", "last policy, its own evaluation (10 episodes)"),
                                                        ("own_best", "best of its own evaluations at our evaluation points (10 episodes each)")))):
            for key, label in what:
                vals = [runs[s].get(key) for s in sorted(runs)]
                out.append({"dataset": ds, "who": who, "what": label, "key": key, "seeds": sorted(runs), "values": vals,
                            "iqm_ci": list(iqm_ci([v for v in vals if v is not None])) if any(v is not None for v in vals) else None,
                            "cell": _cell(vals), "per_seed": _seeds(runs, key), "data": data})
    return out


def page(table: list[dict]) -> str:
    lines = ["# MOPO: ours and OfflineRL-Kit's on the same data and budget", "",
             "Made by `python experiments/peers/mopo_side_by_side.py` from the runs' own files (nothing reruns). Ours: "
             "`offhrl results table1 run --scale demo --envs <env> --datasets medium --algos mopo` (the shipped `algo=mopo`: "
             "7 Gaussian members fitted by likelihood with learned log-variance bounds, 5 elites, MOPO's penalty on the "
             "largest norm of their predicted standard deviations, SAC with MOPO's rollout schedule: every 1,000 steps a rollout "
             "from 50,000 dataset states, the last 5 kept; 205 rollouts, 205,000 updates). The kit's: "
             "its `run_example/run_mopo.py` unchanged (`experiments/peers/offlinerlkit_mopo.py`), on the same HDF5 file, "
             "MOPO's rollout length and penalty for the dataset, 200 epochs of 1,024 updates (the same 204,800), its own "
             "model fit and evaluations. Scores: D4RL-normalised on the data's reference returns; IQM [95% bootstrap CI] over "
             "seeds, then the per-seed values in seed order.", ""]
    for ds in dict.fromkeys(r["dataset"] for r in table):
        sub = [r for r in table if r["dataset"] == ds]
        data = sub[0]["data"]
        lines += [f"## {ds} (demo scale: 100,000 transitions, dataset seed 0; the data: "
                  f"{'-' if data is None else f'{data:.1f}'})", "",
                  "| who | what | seeds | IQM [95% CI] | per seed |", "|---|---|---|---|---|"]
        lines += [f"| {r['who']} | {r['what']} | {' '.join(map(str, r['seeds'])) or '-'} | {r['cell']} | {r['per_seed']} |" for r in sub]
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ours", type=Path, default=Path("outputs/results/demo"))
    ap.add_argument("--kit", type=Path, default=Path("outputs/peers/offlinerlkit_mopo"))
    ap.add_argument("--datasets", nargs="+", default=["hopper-medium", "halfcheetah-medium"])
    ap.add_argument("--out", type=Path, default=Path("docs/results/mopo_side_by_side.md"))
    a = ap.parse_args(argv)
    table = rows(a.ours, a.kit, a.datasets)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(a.out) as tmp:
        Path(tmp).write_text(page(table))
    write_json(a.out.with_suffix(".json"), table)
    print(f"wrote {a.out} and {a.out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
