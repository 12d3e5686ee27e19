"""Which fallback should a fired guard return, the start or the percentile BC, and can the model tell them apart?

    python experiments/diagnostics/fallback_choice.py RUN_DIR [RUN_DIR ...] [--out FILE.json]

For a finished run with a guard (its step-0 evaluation holds the start's
model episodes), the library's own fallback is fitted or loaded
(:func:`torchrl_offhrl.recipes.fallback.fit_or_load_bc`, cached beside the
CVAE) and evaluated as the run evaluated its agent
(:func:`~torchrl_offhrl.recipes.fallback.evaluate_fallback`: the run's
real-env episodes and seed, its model episodes from the same start states
under the same members). Printed per run: the start's and the BC's real
scores (read afterwards, never used to choose), their model returns, and the
capped worst-member bounds of the start's gain over the BC and of the BC's
over the start (``selection.paired_gain_lcb`` with the data's return cap),
then the last policy's real score and its bounds over each. ``--score
FILE.json`` (a file this script wrote) prints what each ``selection.fallback``
returns on those runs (the mean real score of the returned policies, and how
often it returned the BC): ``start`` (the trained policy if it shows a gain
over the start, else the start), ``bc_unless_start`` and ``start_unless_bc``
(the trained policy if it shows a gain over both, else the BC unless the
start shows a gain over it / the start unless the BC shows one).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from torchrl_offhrl.recipes.evaluation import run_models
from torchrl_offhrl.recipes.fallback import evaluate_fallback, fit_or_load_bc
from torchrl_offhrl.recipes.pipeline import DEFAULT_ORIGIN_SHARE, origin_share
from torchrl_offhrl.recipes.selection import data_return_cap, paired_gain_lcb
from torchrl_offhrl.recipes.train import eval_seed


def probe(run: Path, bc_seed: str = "data") -> dict:
    rm = run_models(run)
    cfg, data, pcfg, ens = rm.cfg, rm.data, rm.pcfg, rm.ensemble
    ev = cfg["eval"]
    share = origin_share(pcfg["env"]) or DEFAULT_ORIGIN_SHARE
    # bc_seed "data": the dataset's seed, as the rows committed on the probes page in session 7 were made (every run on the
    # data was then given the cloner fitted from it); "run": the run's own seed, as a run fits its cloner since session 8
    seed = int(pcfg["seed"]) if bc_seed == "data" else int(cfg["seed"])
    bc = fit_or_load_bc(pcfg, data, rm.model_dir, share, seed, progress=False)

    rec = evaluate_fallback(bc, cfg["env"]["env_id"], int(ev["episodes"]), int(ev["max_steps"]), eval_seed(int(cfg["seed"])), pcfg, ens, data,
                            float(cfg["threshold"]), model_episodes=int(ev.get("model_episodes") or ev["episodes"]),
                            gamma=float(cfg["algo"].get("gamma", 0.99)))
    evals = json.loads((run / "evals.json").read_text())
    start, last = evals[0], evals[-1]
    cap = data_return_cap(data, int(ev["max_steps"]))
    return {
        "run": run.name, "cap": cap, "bc_seed": seed,
        "real_start": start["normalized_d4rl"], "real_bc": rec["normalized_d4rl"], "real_last": last["normalized_d4rl"],
        "model_start": start["model_return_mean"], "model_bc": rec["model_return_mean"], "model_last": last["model_return_mean"],
        "start_over_bc": paired_gain_lcb(start, rec, cap=cap), "bc_over_start": paired_gain_lcb(rec, start, cap=cap),
        "last_over_start": paired_gain_lcb(last, start, cap=cap), "last_over_bc": paired_gain_lcb(last, rec, cap=cap),
    }


def returned(row: dict, rule: str) -> tuple[str, float]:
    """What ``selection.fallback=rule`` returns on a row of :func:`probe`: ``(which, its real score)``."""
    if rule == "start":
        which = "trained" if row["last_over_start"] > 0 else "start"
    else:
        fallback = (("start" if row["start_over_bc"] > 0 else "bc") if rule == "bc_unless_start" else
                    ("bc" if row["bc_over_start"] > 0 else "start"))
        which = "trained" if min(row["last_over_start"], row["last_over_bc"]) > 0 else fallback
    return which, row[{"trained": "real_last", "start": "real_start", "bc": "real_bc"}[which]]


def score(rows: list[dict]) -> None:
    print(f"{len(rows)} runs: start {sum(r['real_start'] for r in rows) / len(rows):.2f}, percentile BC "
          f"{sum(r['real_bc'] for r in rows) / len(rows):.2f}, last policy {sum(r['real_last'] for r in rows) / len(rows):.2f}")
    for rule in ("start", "bc_unless_start", "start_unless_bc"):
        got = [returned(r, rule) for r in rows]
        print(f"  {rule:16s} returns {sum(v for _, v in got) / len(got):6.2f}  (trained {sum(w == 'trained' for w, _ in got)}, "
              f"start {sum(w == 'start' for w, _ in got)}, BC {sum(w == 'bc' for w, _ in got)})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--score", type=Path, help="a file this script wrote: what each selection.fallback returns on its runs")
    ap.add_argument("--bc-seed", choices=("data", "run"), default="data",
                    help="the cloner's seed: the dataset's (as the committed rows were made) or the run's (as a run fits it now)")
    a = ap.parse_args(argv)
    if a.score:
        score(json.loads(a.score.read_text()))
        return 0
    rows = []
    for run in a.runs:
        rows.append(probe(run, a.bc_seed))
        print(json.dumps({k: round(v, 2) if isinstance(v, float) else v for k, v in rows[-1].items()}), flush=True)
        if a.out:
            a.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
