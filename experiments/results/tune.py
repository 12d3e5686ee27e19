"""The paper's model search on hopper-medium, with 1 and with 2 concurrent trials, then its report.

    offhrl results tune run [--concurrent 1 2] [--steps 2000]   # two searches (Ray Tune, this machine)
    offhrl results tune report                                 # docs/results/tune.md

``run`` runs ``offhrl tune models env=hopper dataset=medium`` (the paper's
search space, ``configs/tune/models.yaml``: 10 random combinations of lr x
transition width x reward width x CVAE width) once per ``--concurrent``
value, each with its own empty model cache (``outputs/tune_caches/<n>/``; the
1M-transition dataset is shared through a link to the default cache), so the
two searches fit the same 10 pairs of models from scratch and only the
number of trials running side by side differs. Each fit is bounded to
``--steps`` gradient steps (the default 20k per model is ~10x that; on the
2-core CPU the search at 20k steps would take many hours), which is stated
in the report. A search that was interrupted resumes with the same command
(Ray Tune's restore: finished trials are not fitted again).

``report`` reads ``outputs/tune/models-hopper-medium-{n}concurrent/`` and
writes the trial table, each search's wall time, the winners and whether the
two searches found the same losses (they fit with the same seeds and one
torch thread per trial, so they should, up to floating-point noise).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

from .paths import ROOT  # noqa: E402  (the checkout the pages and runs live in)
OUT = ROOT / "docs" / "results" / "tune.md"


def name(n: int) -> str:
    return f"models-hopper-medium-{n}concurrent"


def run(concurrent: list[int], steps: int) -> None:
    from torchrl_offhrl.utils import cache_dir  # the default cache: where hopper-medium already is, or gets generated once

    datasets = cache_dir() / "datasets"
    datasets.mkdir(parents=True, exist_ok=True)
    for n in concurrent:
        cache = ROOT / "outputs" / "tune_caches" / str(n)
        cache.mkdir(parents=True, exist_ok=True)
        link = cache / "datasets"
        if not link.exists():
            link.symlink_to(datasets.resolve(), target_is_directory=True)
        cmd = [sys.executable, "-m", "torchrl_offhrl.cli", "tune", "models", "env=hopper", "dataset=medium",
               f"ensemble.fit.max_steps={steps}", f"cvae.fit.max_steps={steps}", "--name", name(n), "--max-concurrent", str(n)]
        print("+", shlex.join(cmd), flush=True)
        subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "TORCHRL_OFFHRL_CACHE": str(cache)})


def _source(n: int) -> Path | None:
    """The search's folder: its run under ``outputs/tune/`` where this machine ran it, else the copy the report keeps
    under ``docs/results/tune/`` (so the page rebuilds from a fresh clone)."""
    for d in (ROOT / "outputs" / "tune" / name(n), OUT.parent / "tune" / name(n)):
        if (d / "results.csv").is_file() and (d / "best.json").is_file():
            return d
    return None


def _read(n: int) -> tuple[list[dict], dict] | None:
    d = _source(n)
    if d is None:
        return None
    with open(d / "results.csv") as f:
        rows = list(csv.DictReader(f))
    return rows, json.loads((d / "best.json").read_text())


def report() -> None:
    found = {n: r for n in (1, 2) if (r := _read(n)) is not None}
    if not found:
        raise SystemExit("no finished search under outputs/tune/ or docs/results/tune/: run `offhrl results tune run` first")
    # the fits' step bound: an override of every trial, which the winners' command repeats
    steps = next((o.split("=")[1] for o in shlex.split(found[min(found)][1]["command"]) if o.startswith("ensemble.fit.max_steps=")), "?")
    rows, best = found[min(found)]  # the table: the search with the fewest trials at a time (fit times least disturbed by each other)
    lines = ["# The paper's model search on hopper-medium (Ray Tune)", "",
             "Made by `offhrl results tune report` from the searches of `offhrl results tune run` "
             "(`offhrl tune models env=hopper dataset=medium`, `configs/tune/models.yaml`): 10 random combinations of the paper's "
             f"grid, each trial fitting the ensemble and the CVAE on the 1M-transition hopper-medium dataset for at most {steps} "
             "gradient steps each (batch 256; the fits' default bound is 20k steps, out of reach for 20 models on this 2-core CPU), "
             "scored on the held-out 10% (at most 50k transitions). Each model is chosen by its own validation loss, as the paper "
             "does. One torch thread per trial. A trial whose CVAE (or ensemble) settings an earlier trial already fitted loads that "
             "model from the cache instead of fitting it again (the `cvae` column of the search's `results.csv` says which); "
             f"the table is the search run with {min(found)} trial(s) at a time.", "",
             "| trial | lr | transition width | reward width | CVAE width | ensemble val loss | CVAE val loss | fit (s) |", "|---|---|---|---|---|---|---|---|"]

    def width(v):
        return v.strip("[]").split(",")[0].strip()

    for r in rows:
        lines.append(f"| {r['trial']} | {float(r['ensemble.fit.lr']):g} | {width(r['ensemble.hidden_sizes'])} | {width(r['ensemble.reward_hidden_sizes'])} | "
                     f"{width(r['cvae.hidden_sizes'])} | {float(r['ensemble_val_loss']):.4f} | {float(r['cvae_val_loss']):.4f} | {float(r['fit_s']):.0f} |")
    s = best["settings"]
    lines += ["", f"Winners: the ensemble of trial {best['ensemble_trial']} (lr {s['ensemble.fit.lr']:g}, transition "
              f"{s['ensemble.hidden_sizes']}, reward {s['ensemble.reward_hidden_sizes']}; val loss {best['ensemble_val_loss']:.4f}) and the CVAE "
              f"of trial {best['cvae_trial']} (lr {s['cvae.fit.lr']:g}, {s['cvae.hidden_sizes']}; val loss {best['cvae_val_loss']:.4f}). "
              "The command that loads them from the search's model cache:", "", "```bash", found[max(found)][1]["command"], "```", "",  # the latest search's: printed shell-quoted
              "## One or two trials at a time", "",
              "| concurrent trials | wall time (min) | sum of the trials' fit times (min) | speed-up |", "|---|---|---|---|"]
    base = found[min(found)][1]["wall_s"]
    for n, (r, b) in sorted(found.items()):
        fit = sum(float(x["fit_s"]) for x in r) / 60
        lines.append(f"| {n} | {b['wall_s'] / 60:.1f} | {fit:.1f} | {base / b['wall_s']:.2f}x |")
    if len(found) == 2:
        (r1, _), (r2, _) = found[1], found[2]
        diff = max(abs(float(a[k]) - float(b[k])) for a, b in zip(r1, r2) for k in ("ensemble_val_loss", "cvae_val_loss"))
        lines += ["", f"Both searches scored every trial alike: their validation losses differ by at most {diff:.2g} (one torch thread "
                  "per trial, the same seeds: the fits are deterministic)."]
    notes = ROOT / "docs" / "results" / "tune_notes.md"
    if notes.is_file():  # what the runs showed, written by hand after looking at them
        lines += ["", notes.read_text().strip()]
    for n in found:  # the searches' own tables next to the report (outputs/ is not kept in git)
        keep, src = OUT.parent / "tune" / name(n), _source(n)
        if src == keep:
            continue
        keep.mkdir(parents=True, exist_ok=True)
        for f in ("results.csv", "results.md", "best.json"):
            shutil.copy2(src / f, keep / f)
    lines += ["", "Each search's own table (every column Ray reported) and `best.json`: `docs/results/tune/<search>/`."]
    OUT.write_text("\n".join(lines) + "\n")
    print(f"wrote {OUT}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results tune", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--concurrent", type=int, nargs="+", default=[1, 2])
    r.add_argument("--steps", type=int, default=2000)
    sub.add_parser("report")
    a = p.parse_args(argv)
    run(a.concurrent, a.steps) if a.cmd == "run" else report()
    return 0

