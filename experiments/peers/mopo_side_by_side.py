"""MOPO, ours and OfflineRL-Kit's, on the same data at the same budget: one table per dataset (issue 72).

    python experiments/peers/mopo_side_by_side.py run --checkout PATH/TO/OfflineRL-Kit [--who ours|kit|both] [--kit DIR]
        [--datasets hopper-medium halfcheetah-medium] [--seeds 4 5 6]
    python experiments/peers/mopo_side_by_side.py [report] [--ours docs/results/demo/runs] [--kit docs/results/mopo_side_by_side_runs]
        [--datasets hopper-medium halfcheetah-medium] [--out docs/results/mopo_side_by_side.md]

``run`` makes every run the page needs that is not finished yet, and can be stopped and started again (across sessions:
hours of CPU per seed) without losing more than the run in progress's last stretch:

* ours: ``offhrl results table1 run --scale demo --algos mopo`` for each dataset and seed not yet archived (the scale's
  100,000 transitions, its model fit cached once per dataset, every run resuming from its checkpoint and archived in
  ``docs/results/demo/runs/`` when done);
* the kit's: ``experiments/peers/offlinerlkit_mopo.py`` on the same HDF5 file, with our config's rollout length, penalty,
  rollouts, rollout size, updates between rollouts and real-data share (read from ``algo=mopo``'s composed config, so the
  two budgets cannot drift apart); the kit's own dynamics fit runs once per dataset (its first seed) and the other seeds
  load it (``--load-dynamics-path``), as ours share one fit. A seed with ``final_eval.json`` is done; an unfinished one
  starts again (the kit keeps no checkpoint of its policy), on the fit it may have finished (saved before the policy's
  training; moved to ``<kit>/<dataset>/dynamics/`` before the run's folder is cleared). The fit is also kept with the
  archive (``docs/results/mopo_side_by_side_runs/<dataset>/dynamics/``, ~7 MB with SHA-256s, committed): on a fresh
  machine the remaining seeds load it instead of fitting again (the kit's fit of hopper-medium's 100,000 transitions
  took 392 epochs, 1 h 52 min of one core on a 2-core AMD EPYC).

``--who ours`` and ``--who kit`` split the work into two background jobs, one core each.

``report`` (the default) reads what the two runs left (by default their committed archives: ours in
``docs/results/demo/runs/``, the kit's in ``docs/results/mopo_side_by_side_runs/``), runs nothing:

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
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from torchrl_offhrl.stats import iqm_ci
from torchrl_offhrl.utils import atomic_write, write_json



ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script: the sibling scripts import as experiments.peers.*, one module each
    sys.path.insert(0, str(ROOT))
#: where ``run`` keeps what the page reads of each finished kit run (committed; the runs' folders stay on the machine)
KIT_ARCHIVE = ROOT / "docs" / "results" / "mopo_side_by_side_runs"
#: where ``table1 run`` archives ours (the demo scale's finished runs)
OURS_ARCHIVE = ROOT / "docs" / "results" / "demo" / "runs"


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


def model_results(kit_root: Path, datasets) -> dict[str, dict]:
    """Dataset -> the model comparison kept beside the kit's runs (``<kit>/<dataset>/models.json``, written by
    ``mopo_models.py --out``), where there is one."""
    return {ds: json.loads((kit_root / ds / "models.json").read_text()) for ds in datasets if (kit_root / ds / "models.json").is_file()}


def _models_section(ds: str, result: dict) -> list[str]:
    from experiments.peers.mopo_models import markdown_tables  # (run as a script, the checkout's root is put on sys.path below)

    who = " and the kit's" if "kit" in result["models"] else " (the kit's once its fit is kept: `--kit-model`)"
    return [f"### {ds}: the models on real transitions neither saw", "",
            f"Our Gaussian ensemble{who}, made by `python experiments/peers/mopo_models.py --ours ... --run ... --out "
            f"docs/results/mopo_side_by_side_runs/{ds}/models.json` (see its docstring): the elites' next-state error (L2, "
            "the state's units), MOPO's penalty (the largest norm of the elites' predicted std of state and reward), how well "
            "the penalty ranks the error (Spearman), the share of transitions it under-states, the reward's bias, and the "
            "share of the real falls the model predicts one step ahead.", "", *markdown_tables(result), ""]


def page(table: list[dict], models: dict[str, dict] | None = None) -> str:
    lines = ["# MOPO: ours and OfflineRL-Kit's on the same data and budget", "",
             "Made by `python experiments/peers/mopo_side_by_side.py` from the runs' own files (nothing reruns). Ours: "
             "`offhrl results table1 run --scale demo --envs <env> --datasets medium --algos mopo` (the shipped `algo=mopo`: "
             "7 Gaussian members fitted by likelihood with learned log-variance bounds, 5 elites, MOPO's penalty on the "
             "largest norm of their predicted standard deviations, SAC with MOPO's rollout schedule: every 1,000 steps a rollout "
             "from 50,000 dataset states, the last 5 kept; 205 rollouts, 205,000 updates). The kit's: "
             "its `run_example/run_mopo.py` unchanged (`experiments/peers/offlinerlkit_mopo.py`), on the same HDF5 file, with "
             "our config's rollout length, penalty, rollout size, real-data share and schedule (205 epochs of 1,000 updates, "
             "a rollout per epoch: the same 205 rollouts and 205,000 updates; `mopo_side_by_side.py run` passes them), its own "
             "model fit (once per dataset, loaded by the later seeds, as ours) and evaluations. Scores: D4RL-normalised on the data's reference returns; IQM [95% bootstrap CI] over "
             "seeds, then the per-seed values in seed order.", ""]
    for ds in dict.fromkeys(r["dataset"] for r in table):
        sub = [r for r in table if r["dataset"] == ds]
        data = sub[0]["data"]
        lines += [f"## {ds} (demo scale: 100,000 transitions, dataset seed 0; the data: "
                  f"{'-' if data is None else f'{data:.1f}'})", "",
                  "| who | what | seeds | IQM [95% CI] | per seed |", "|---|---|---|---|---|"]
        lines += [f"| {r['who']} | {r['what']} | {' '.join(map(str, r['seeds'])) or '-'} | {r['cell']} | {r['per_seed']} |" for r in sub]
        lines.append("")
        for who, flag in (("ours", "--who ours"), ("OfflineRL-Kit", "--checkout PATH/TO/OfflineRL-Kit --who kit")):
            if not any(r["seeds"] for r in sub if r["who"] == who):
                lines += [f"No finished run of {who} on {ds} yet: `python experiments/peers/mopo_side_by_side.py run "
                          f"{flag} --datasets {ds}` makes them.", ""]
        if models and ds in models:
            lines += _models_section(ds, models[ds])
    return "\n".join(lines)


def kit_settings(dataset: str) -> dict:
    """What the kit's run takes from ours for ``dataset`` (``hopper-medium``): our demo-scale MOPO config's data (file
    name, size, seed) and schedule, as the kit's arguments."""
    from torchrl_offhrl.data.catalog import dataset_path
    from torchrl_offhrl.recipes.config import compose

    env, level = dataset.split("-", 1)
    cfg = compose("demo", ["algo=mopo", f"env={env}", f"dataset={level}"])
    own = compose("offline_train", ["algo=mopo", f"env={env}", f"dataset={level}"])  # the rollout budget MOPO's config states
    horizon, size, freq = int(cfg.model_env.horizon), int(cfg.algo.rollout_batch_size), int(cfg.algo.rollout_freq)
    rollouts = int(own.train.total_frames) // (size * horizon)
    args = ["--rollout-length", str(horizon), "--penalty-coef", str(float(cfg.model_env.reward_penalty)),
            "--rollout-batch-size", str(size), "--rollout-freq", str(freq), "--real-ratio", str(float(cfg.algo.real_ratio)),
            "--model-retain-epochs", str(int(cfg.algo.model_retain_rollouts)), "--epoch", str(rollouts), "--step-per-epoch", str(freq)]
    return {"env": env, "level": level, "num_transitions": int(cfg.num_transitions), "dataset_seed": int(cfg.dataset_seed),
            "file": dataset_path(dataset, int(cfg.num_transitions), seed=int(cfg.dataset_seed)), "args": args,
            "task": f"{dataset}-v2"}


#: the kit's fit as its ``dynamics.save`` writes it (``dynamics.pth``: the members, their learned log-variance bounds and
#: elites; ``mu.npy``, ``std.npy``: its input scaler)
KIT_DYNAMICS_FILES = ("dynamics.pth", "mu.npy", "std.npy")


def _kit_dynamics(root: Path, archived: Path | None = None) -> Path | None:
    """The kit's fitted dynamics for a dataset's runs under ``root``: ``root/dynamics/`` (kept there when the run that fitted
    them was started again), else a seed's (``<seed>/log/<task>/<algo>/<run>/model/dynamics.pth``), else the fit kept in
    the archive (``archived``: ``<archive>/<dataset>/dynamics/``, committed, so that a fresh machine's seeds load the
    kit's one fit instead of fitting again; its files are checked against their SHA-256 and copied to ``root/dynamics``);
    None before any fit."""
    if (root / "dynamics" / "dynamics.pth").is_file():
        return root / "dynamics"
    found = sorted(root.glob("seed*/log/*/*/*/model/dynamics.pth"))
    if found:
        return found[0].parent
    if archived is not None and (archived / "dynamics.pth").is_file():
        from torchrl_offhrl.utils import checksum_mismatch

        bad = [f for f in KIT_DYNAMICS_FILES if checksum_mismatch(archived / f) is not None or not (archived / f).is_file()]
        if bad:
            raise SystemExit(f"{archived}: the kit's archived fit is damaged or incomplete ({', '.join(bad)}); restore it with "
                             f"git checkout -- {archived}, or delete the folder to fit again")
        (root / "dynamics").mkdir(parents=True, exist_ok=True)
        for f in KIT_DYNAMICS_FILES:
            shutil.copy2(archived / f, root / "dynamics" / f)
        return root / "dynamics"
    return None


def archive_kit_dynamics(fitted: Path, to: Path) -> None:
    """Keep the kit's fit (:data:`KIT_DYNAMICS_FILES` of ``fitted``, ~7 MB) under ``to`` with each file's SHA-256 beside
    it, once: the first fit of a dataset is the one every later seed loads, on this machine or another."""
    from torchrl_offhrl.utils import write_checksum

    if (to / "dynamics.pth").is_file() or not all((fitted / f).is_file() for f in KIT_DYNAMICS_FILES):
        return
    to.mkdir(parents=True, exist_ok=True)
    for f in KIT_DYNAMICS_FILES:
        shutil.copy2(fitted / f, to / f)
        write_checksum(to / f)


def _kit_fit_kept(root: Path, archived: Path) -> Path | None:
    """:func:`_kit_dynamics` of ``root`` (or the archived fit), archived under ``archived`` if it is not yet."""
    fitted = _kit_dynamics(root, archived)
    if fitted is not None:
        archive_kit_dynamics(fitted, archived)
    return fitted


def run(kit: Path, datasets: Sequence[str], seeds: Sequence[int], who: str, kit_root: Path, archive: Path = KIT_ARCHIVE) -> None:
    """Every missing run of the page, ours then the kit's per dataset (``who``: ``ours``, ``kit`` or ``both``); each finished
    kit run is archived under ``archive`` (:func:`archive_kit_run`), ours are by ``table1 run``."""
    if who in ("kit", "both") and not (kit / "run_example" / "run_mopo.py").is_file():
        raise SystemExit(f"--checkout {kit}: not a checkout of OfflineRL-Kit (no run_example/run_mopo.py); fetch "
                         "https://github.com/yihaosun1124/OfflineRL-Kit and pass its folder")
    for ds in datasets:
        s = kit_settings(ds)
        if who in ("ours", "both"):
            for seed in seeds:
                if (OURS_ARCHIVE / f"mopo-{ds}-seed{seed}" / "summary.json").is_file():  # finished (its folder may be gone)
                    print(f"ours {ds} seed {seed}: done ({OURS_ARCHIVE / f'mopo-{ds}-seed{seed}'})", flush=True)
                    continue
                subprocess.run([sys.executable, "-m", "experiments.results", "table1", "run", "--scale", "demo", "--envs", s["env"],
                                "--datasets", s["level"], "--algos", "mopo", "--seeds", str(seed)], check=True, cwd=ROOT)
        if who in ("kit", "both"):
            if not s["file"].is_file():  # the same data as ours: generated (and cached) as our runs generate it
                from torchrl_offhrl.data import named_dataset

                named_dataset(ds, s["num_transitions"], seed=s["dataset_seed"])
            for seed in seeds:
                out = kit_root / ds / f"seed{seed}"
                if (out / "final_eval.json").is_file():
                    print(f"kit {ds} seed {seed}: done ({out / 'final_eval.json'})", flush=True)
                    archive_kit_run(out, archive / ds / f"seed{seed}")  # (again: a run finished by an earlier call or by hand)
                    continue
                fitted = _kit_fit_kept(kit_root / ds, archive / ds / "dynamics")  # (also a fit left by a run killed after it)
                if fitted is not None and out in fitted.parents:  # the fit (saved before the policy's training) outlives its run
                    shutil.copytree(fitted, kit_root / ds / "dynamics", dirs_exist_ok=True)
                    fitted = kit_root / ds / "dynamics"
                if out.exists():  # an unfinished run (no checkpoint to resume from)
                    shutil.rmtree(out)
                load = ["--load-dynamics-path", str(fitted)] if fitted is not None else []
                print(f"kit {ds} seed {seed}: {'loading its dynamics from ' + str(fitted) if load else 'fitting its dynamics'}", flush=True)
                subprocess.run([sys.executable, str(Path(__file__).with_name("offlinerlkit_mopo.py")), "--kit", str(kit),
                                "--dataset", str(s["file"]), "--task", s["task"], "--out", str(out), "--",
                                "--seed", str(seed), *s["args"], *load], check=True)
                archive_kit_run(out, archive / ds / f"seed{seed}")
                _kit_fit_kept(kit_root / ds, archive / ds / "dynamics")  # (the fit this run made, if it made one)


def archive_kit_run(run: Path, to: Path) -> None:
    """Keep what the page reads of a finished kit run (``final_eval.json`` and the kit's per-epoch progress CSV, a few
    kB, at their paths in the run) under ``to``, to commit: the run's own folder (logs, models) stays on the machine."""
    for f in [run / "final_eval.json", *run.glob("log/*/*/*/record/policy_training_progress.csv")]:
        dest = to / f.relative_to(run)
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(f, dest)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = argv.pop(0) if argv and argv[0] in ("run", "report") else "report"
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ours", type=Path, default=OURS_ARCHIVE, help="our runs (report; default: their archive)")
    ap.add_argument("--kit", type=Path, default=None,
                    help="the kit's runs (run: where they are made, default outputs/peers/offlinerlkit_mopo; report: where "
                         "they are read, default their archive, docs/results/mopo_side_by_side_runs)")
    ap.add_argument("--datasets", nargs="+", default=["hopper-medium", "halfcheetah-medium"])
    ap.add_argument("--out", type=Path, default=Path("docs/results/mopo_side_by_side.md"))
    if command == "run":
        ap.add_argument("--checkout", type=Path, default=None, help="a checkout of OfflineRL-Kit (needed with --who kit|both)")
        ap.add_argument("--who", choices=("ours", "kit", "both"), default="both")
        ap.add_argument("--seeds", type=int, nargs="+", default=[4, 5, 6])
    a = ap.parse_args(argv)
    if command == "run":
        run(a.checkout or Path("."), a.datasets, a.seeds, a.who, a.kit or Path("outputs/peers/offlinerlkit_mopo"))
        return 0
    table = rows(a.ours, a.kit or KIT_ARCHIVE, a.datasets)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(a.out) as tmp:
        Path(tmp).write_text(page(table, model_results(a.kit or KIT_ARCHIVE, a.datasets)))
    write_json(a.out.with_suffix(".json"), table)
    print(f"wrote {a.out} and {a.out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
