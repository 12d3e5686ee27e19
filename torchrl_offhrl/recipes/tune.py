"""Hyper-parameter searches and multi-seed sweeps on Ray Tune: ``offhrl tune`` and ``offhrl sweep``.

Ray is the engine (``pip install 'torchrl-offhrl[tune]'``); nothing else in
the library needs it. By default Ray starts on this machine with as many
CPUs as it has cores: each trial asks for ``cpus_per_trial`` CPUs (1) and
runs with as many torch threads, so trials never oversubscribe the machine.
``address=`` (``--address``, or the ``RAY_ADDRESS`` env var) joins an
existing Ray cluster instead, where the same command spreads trials over its
nodes (``gpus_per_trial`` for GPU trials).

Searches (``offhrl tune <preset>``) are described by YAML files
(``configs/tune/<preset>.yaml`` or any path), see :func:`load_search`:

* ``kind: models``: each trial fits (or loads from the model cache) the
  dynamics ensemble and the CVAE with the trial's settings and scores both
  on the held-out split (the paper's search, ``configs/tune/models.yaml``);
  the ensemble's settings are chosen by the ensemble's validation loss and
  the CVAE's by the CVAE's (each model by its own loss, as the paper). Every
  trial's models stay in the model cache, so ``offhrl fit`` / ``offhrl
  train`` with the printed overrides load them (an ensemble and a CVAE of
  different trials are combined without fitting again);
* ``kind: agent``: each trial is an ordinary ``offhrl train`` run with the
  trial's overrides, scored by its final real-env evaluation (e.g. the
  pessimism search, scored by a short SAC run as the paper tuned it, and
  MOC's ``lr`` and ``eta``).

Sweeps (``offhrl sweep``) run algorithms x datasets x seeds as trials, each
an ordinary run directory under ``<out_root>/sweeps/<name>/`` (``outputs/sweeps/``) that
``offhrl aggregate`` / ``offhrl report`` read; a finished run directory is
not trained again, and an interrupted sweep (or search) resumes with Ray
Tune's experiment restore when the same command is run again.
"""
from __future__ import annotations

import itertools
import json
import os
import random
import shlex
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..utils import to_plain
from .config import config_dir

__all__ = ["TUNE_EXTRA_HINT", "SearchInterrupted", "finished_run", "load_search", "require_ray", "search_grid", "sweep", "tune_search"]

TUNE_EXTRA_HINT = "offhrl tune and offhrl sweep need Ray Tune: pip install 'torchrl-offhrl[tune]' (or pip install 'ray[tune]')"
KINDS = ("models", "agent")
#: Ray Tune schedulers a search may name (null: every trial runs its whole budget)
SCHEDULERS = (None, "asha")


def require_ray():
    """``(ray, ray.tune)``, or ``ImportError`` pointing at the ``tune`` extra."""
    try:
        import ray
        from ray import tune
    except ImportError as err:
        raise ImportError(TUNE_EXTRA_HINT) from err
    return ray, tune


# ----------------------------------------------------------------------------- search descriptions
def load_search(name_or_path: str) -> dict:
    """A search description: ``configs/tune/<name>.yaml`` or a YAML file path.

    Keys: ``kind`` (``models`` | ``agent``), ``grid`` (config key path ->
    list of values), ``num_samples`` (that many distinct combinations of the
    grid drawn at random with ``sample_seed``; null: the whole grid), ``tie``
    (key -> the grid key whose drawn value it takes), ``overrides`` (hydra
    overrides of ``configs/offline_train.yaml`` for every trial, before the
    command line's), and for ``agent`` searches ``metric`` / ``mode`` (a key
    of the final evaluation record, ``max`` or ``min``) and ``scheduler``
    (null: every trial runs its budget; ``asha``: Ray Tune's ASHA stops the
    trials behind at their evaluations, each reported as it is made).
    """
    from omegaconf import OmegaConf

    path = Path(name_or_path)
    if not path.suffix:
        path = config_dir() / "tune" / f"{name_or_path}.yaml"
    if not path.is_file():
        presets = sorted(p.stem for p in (config_dir() / "tune").glob("*.yaml"))
        raise FileNotFoundError(f"no search description {name_or_path!r}: give a preset ({', '.join(presets)}) or a YAML file path")
    spec = to_plain(OmegaConf.load(path))
    problems = []
    if spec.get("kind") not in KINDS:
        problems.append(f"kind must be one of {KINDS}, got {spec.get('kind')!r}")
    grid = spec.get("grid")
    if not isinstance(grid, Mapping) or not grid or not all(isinstance(v, list) and v for v in grid.values()):
        problems.append("grid must map config keys to non-empty lists of values")
    for k, src in (spec.get("tie") or {}).items():
        if not isinstance(grid, Mapping) or src not in grid:
            problems.append(f"tie {k}: {src!r} is not a key of the grid")
    if spec.get("kind") == "agent" and spec.get("mode", "max") not in ("max", "min"):
        problems.append(f"mode must be max or min, got {spec.get('mode')!r}")
    if spec.get("scheduler") not in SCHEDULERS:
        problems.append(f"scheduler must be one of {SCHEDULERS}, got {spec.get('scheduler')!r}")
    elif spec.get("scheduler") and spec.get("kind") != "agent":
        problems.append(f"scheduler {spec['scheduler']!r} stops agent trials at their evaluations; a {spec.get('kind')!r} search has none")
    if problems:
        raise ValueError(f"{path}: " + "; ".join(problems))
    spec.setdefault("scheduler", None)
    spec.setdefault("num_samples", None)
    spec.setdefault("sample_seed", 0)
    spec.setdefault("tie", {})
    spec.setdefault("overrides", [])
    spec.setdefault("metric", "val_loss" if spec["kind"] == "models" else "normalized_d4rl")
    spec.setdefault("mode", "min" if spec["kind"] == "models" else "max")
    spec["name"] = path.stem
    spec["path"] = str(path)
    return spec


def search_grid(spec: Mapping) -> list[dict]:
    """The trials of a search: dicts of config key -> value (ties applied), ``num_samples`` distinct grid points drawn with ``sample_seed``."""
    keys = list(spec["grid"])
    points = [dict(zip(keys, vals)) for vals in itertools.product(*(spec["grid"][k] for k in keys))]
    n = spec.get("num_samples")
    if n is not None and n < len(points):
        points = random.Random(int(spec.get("sample_seed", 0))).sample(points, int(n))
    for p in points:
        for k, src in (spec.get("tie") or {}).items():
            p[k] = p[src]
    return points


def _override(key: str, value: Any) -> str:
    """A hydra override ``++key=value``: set whether or not the key exists (e.g. inside ``model_env.pessimism``).

    Values as compact JSON (``[1024,1024]``, no spaces): one shell word as printed.
    """
    return f"++{key}={json.dumps(value, separators=(',', ':'))}"


def _compose(overrides: Sequence[str]) -> dict:
    from .config import compose

    return to_plain(compose("offline_train", list(overrides), "tune"))


# ----------------------------------------------------------------------------- trials (run in Ray workers)
def _setup(config: Mapping) -> None:
    """In a trial's worker: the driver's environment (model cache), and as many torch threads as CPUs reserved."""
    import torch

    os.environ.update(config.get("environ") or {})
    torch.set_num_threads(max(1, int(config["threads"])))


def _models_trial(config: dict) -> None:
    """Fit (or load) the ensemble and the CVAE of this trial's settings; report their validation losses."""
    from ray import tune

    from ..models import SupervisedTrainer
    from .config import model_config, resolve_dataset
    from .pipeline import fit_or_load_models

    _setup(config)
    cfg = _compose(config["overrides"])
    data = resolve_dataset(cfg)
    mcfg = model_config(cfg)
    t0 = time.time()
    ensemble, cvae, info = fit_or_load_models(mcfg, data, progress=False)
    _, val = data.split(mcfg["dataset"]["val_ratio"], seed=mcfg["seed"])  # the split the fits held out
    ev = SupervisedTrainer().evaluate
    e_loss = float(ev(ensemble, val.data).mean())
    c_loss = float(ev(cvae, val.data).mean())
    tune.report({"ensemble_val_loss": e_loss, "cvae_val_loss": c_loss, "val_loss": e_loss + c_loss, "model_dir": info["model_dir"],
                 "fit_s": round(time.time() - t0, 1), "ensemble": info["ensemble"], "cvae": info["cvae"]})


def _train_trial(config: dict) -> None:
    """One ordinary run of ``offhrl train`` (resumed from its checkpoint if any); report its final evaluation."""
    from ray import tune

    from .train import train

    _setup(config)
    run_dir = Path(config["run_dir"])
    cfg = _compose([*config["overrides"], f"run_dir={run_dir}", f"torch_threads={config['threads']}"])
    done = finished_run(run_dir, cfg)
    if done is not None:  # a finished run directory is not trained again
        tune.report(_metrics(done, skipped=True))
        return
    # every evaluation reported as it is made (a scheduler such as ASHA may stop the trial there), then the summary
    tune.report(_metrics(train(cfg, progress=False, on_record=lambda rec: tune.report(_record_metrics(rec, run_dir))), skipped=False))


def _record_metrics(rec: Mapping, run_dir) -> dict:
    """What a trial reports at each evaluation: the record's numbers, its step and run directory."""
    out = {k: v for k, v in rec.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    out.update({"run_dir": str(run_dir), "skipped": False, "finished": False})  # finished: False until the summary (a scheduler may stop it here)
    return out


def finished_run(run_dir, cfg: Mapping) -> dict | None:
    """The summary of ``run_dir`` if it already finished the budget of ``cfg`` (frames, or updates for dataset agents), else None."""
    path = Path(run_dir) / "summary.json"
    if not path.is_file():
        return None
    done = json.loads(path.read_text())
    return done if done.get("step", 0) >= _budget(cfg) else None


def _budget(cfg: Mapping) -> int:
    from .config import learns_from_dataset
    from .schema import parse_section

    return parse_section("train", cfg.get("train")).total("updates" if learns_from_dataset(cfg) else "frames")


def _metrics(summary: Mapping, skipped: bool) -> dict:
    final = summary.get("final") or {}
    best = summary.get("best") or {}
    out = {k: v for k, v in final.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    out.update({f"best_{k}": v for k, v in best.items() if k in ("normalized_d4rl", "return_mean", "success_rate") and isinstance(v, (int, float))})
    out.update({"run_dir": summary.get("run_dir"), "skipped": skipped, "step": summary.get("step"), "finished": True})
    return out


# ----------------------------------------------------------------------------- the engine
def _init_ray(address: str | None, num_cpus: int | None):
    """``(ray, started)``: Ray connected to ``address`` (or ``$RAY_ADDRESS``) or started here; ``started`` when this call started it.

    A session the caller already opened (``ray.init`` in a notebook, a test
    fixture) is used as it is and left open.
    """
    ray, _ = require_ray()
    address = address or os.environ.get("RAY_ADDRESS")
    if ray.is_initialized():
        return ray, False
    if address:  # a cluster: its nodes and resources
        try:
            ray.init(address=address, log_to_driver=False)
        except (ConnectionError, RuntimeError) as err:
            raise ConnectionError(
                f"could not join the Ray cluster at {address!r} ({str(err).splitlines()[0][:200] if str(err) else type(err).__name__}). "
                "Check that its head runs (`ray status` on it) and this machine reaches it; Ray >= 2.59 clusters started with "
                "token authentication need the same RAY_AUTH_MODE=token and token here; a ray:// address needs `pip install "
                "'ray[client]'` (in the [tune] extra)") from None
    else:  # this machine: one CPU per core, a small object store (trials exchange only metrics); workers inherit the environment.
        # address="local": a new local Ray even where a `ray start` head already runs (joining it would forbid num_cpus)
        ray.init(address="local", num_cpus=num_cpus or os.cpu_count() or 1, include_dashboard=False, object_store_memory=200 * 1024 * 1024,
                 log_to_driver=False)
    return ray, True


def _run_trials(trainable, trials: list[dict], name: str, storage: Path, cpus_per_trial: int, gpus_per_trial: float, address: str | None,
                num_cpus: int | None, max_concurrent: int | None, verbose: int, scheduler: str | None = None, metric: str | None = None,
                mode: str = "max"):
    """Run ``trials`` (one dict each) as Ray Tune trials of experiment ``name`` under ``storage``; restore it if it was interrupted."""
    ray, started = _init_ray(address, num_cpus)
    from ray import tune

    storage = Path(storage).resolve()
    exp = storage / name
    resources = {"cpu": cpus_per_trial, **({"gpu": gpus_per_trial} if gpus_per_trial else {})}
    wrapped = tune.with_resources(trainable, resources)
    environ = {k: os.environ[k] for k in ("TORCHRL_OFFHRL_CACHE", "MUJOCO_GL") if k in os.environ}
    for t in trials:  # in place: the trainable reads the same list
        t["threads"] = cpus_per_trial
        t["environ"] = environ  # the driver's cache: workers of a Ray started earlier (or remote ones) do not inherit it
    spec_file = exp / "offhrl_trials.json"
    same = spec_file.is_file() and json.loads(spec_file.read_text()) == trials
    try:
        if same and tune.Tuner.can_restore(str(exp)):  # the same experiment again: Ray's restore runs only what did not finish
            tuner = tune.Tuner.restore(str(exp), trainable=wrapped, resume_unfinished=True, resume_errored=True)
        else:
            exp.mkdir(parents=True, exist_ok=True)
            spec_file.write_text(json.dumps(trials, indent=1, default=str))
            sched = None
            if scheduler == "asha":  # stops the trials behind at their evaluations (grace: the first one after the untrained)
                from ray.tune.schedulers import ASHAScheduler

                sched = ASHAScheduler(metric=metric, mode=mode, grace_period=2, max_t=10_000)
            tuner = tune.Tuner(
                wrapped,
                # each trial's settings in Ray's config too (its tables and loggers show them), beside its index
                param_space={"trial": tune.grid_search([{"index": i, **{k: v for k, v in t["params"].items()}} for i, t in enumerate(trials)])},
                tune_config=tune.TuneConfig(max_concurrent_trials=max_concurrent, scheduler=sched),
                run_config=tune.RunConfig(name=name, storage_path=str(storage), verbose=verbose),
            )
        return tuner.fit(), trials
    finally:
        if started:
            ray.shutdown()


def _with_specs(fn, trials: list[dict]):
    def trainable(config):
        return fn(trials[trial_index(config)])

    trainable.__name__ = fn.__name__.strip("_")
    return trainable


def trial_index(config: Mapping) -> int:
    """A trial's index in its experiment's trial list, from its Ray config (``{"index": i, ...settings}``; an int before the settings were added)."""
    t = config["trial"]
    return int(t["index"]) if isinstance(t, Mapping) else int(t)


class SearchInterrupted(RuntimeError):
    """An interrupted search or sweep (Ctrl-C): some trials did not finish; the same command resumes it."""


def _rows(results, trials: list[dict], keys: Sequence[str], name: str = "the search") -> list[dict]:
    """One row per finished trial; raises :class:`SearchInterrupted` (before any table is written) if any trial did not finish.

    A trial that never started (its config is None) or that stopped without
    reporting or failing was cut by an interrupt: the tables of a finished
    experiment are not overwritten with blank rows.
    """
    unfinished = [r for r in results if r.config is None or (r.error is None and not r.metrics)]
    if unfinished or len(results) < len(trials):
        done = len(results) - len(unfinished)
        raise SearchInterrupted(f"{name}: interrupted with {done} of {len(trials)} trials finished; run the same command again "
                                "to resume it (finished trials are not run again)")
    rows = []
    for r in results:
        idx = trial_index(r.config)
        m = dict(r.metrics or {})
        rows.append({"trial": idx, **{k: trials[idx]["params"].get(k) for k in keys}, **{k: v for k, v in m.items() if not k.startswith(("time", "timestamp",
                     "date", "hostname", "node_ip", "pid", "training_iteration", "iterations_since", "trial_id", "done", "config", "checkpoint_dir_name",
                     "should_checkpoint"))}, "error": None if r.error is None else type(r.error).__name__})
    return sorted(rows, key=lambda row: row["trial"])


def _write_table(rows: list[dict], out: Path, title: str) -> str:
    import csv

    out.mkdir(parents=True, exist_ok=True)
    cols = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)

    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return "" if v is None else str(v)

    lines = [f"# {title}", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in rows]
    text = "\n".join(lines) + "\n"
    (out / "results.md").write_text(text)
    return text


def tune_search(preset: str, overrides: Sequence[str] = (), *, name: str | None = None, out_root: str | None = None, address: str | None = None,
                num_cpus: int | None = None, cpus_per_trial: int = 1, gpus_per_trial: float = 0.0, max_concurrent: int | None = None,
                verbose: int = 1, num_samples: int | None = None) -> dict:
    """Run the search ``preset`` (:func:`load_search`) on the config of ``overrides``; returns the best settings and the table.

    ``num_samples`` replaces the preset's number of grid points drawn (``offhrl tune ... --num-samples N``).

    Writes ``results.csv`` / ``results.md`` (one row per trial: its settings
    and scores) and ``best.json`` into ``<out_root>/tune/<name>/`` (``out_root``:
    ``outputs`` by default); Ray's
    experiment (restorable) lives in the same folder.
    """
    spec = load_search(preset)
    search_keys = [o for o in overrides if o.split("=", 1)[0].lstrip("+") in spec]  # a key of the search itself, not of the config
    if search_keys:
        raise ValueError(f"{search_keys}: overrides set the training config of every trial; the search's own settings are not in it "
                         "(the number of trials: --num-samples N; the rest: in the search YAML)")
    if num_samples is not None:
        if int(num_samples) < 1:
            raise ValueError(f"--num-samples must be >= 1, got {num_samples}")
        spec["num_samples"] = int(num_samples)
    base = [*spec["overrides"], *overrides]
    cfg = _compose(base)  # a bad override fails here, before Ray starts
    name = name or f"{spec['name']}-{cfg['env']['name']}-{Path(str(cfg['dataset'])).stem}"
    root = Path(out_root or "outputs") / "tune"
    keys = list(spec["grid"]) + list(spec["tie"])
    points = search_grid(spec)
    trials = []
    for i, p in enumerate(points):
        extra = [_override(k, v) for k, v in p.items()]
        t = {"params": p, "overrides": [*base, *extra]}
        if spec["kind"] == "agent":
            t["run_dir"] = str((root / name / "runs" / f"trial{i:03d}").resolve())
        trials.append(t)
    fn = _models_trial if spec["kind"] == "models" else _train_trial
    t0 = time.time()
    results, trials = _run_trials(_with_specs(fn, trials), trials, name, root, cpus_per_trial, gpus_per_trial, address, num_cpus, max_concurrent,
                                  verbose, scheduler=spec["scheduler"], metric=spec["metric"], mode=spec["mode"])
    rows = _rows(results, trials, keys, name)
    table = _write_table(rows, root / name, f"offhrl tune {spec['name']}: {len(rows)} trials ({time.time() - t0:.0f} s)")
    ok = [r for r in rows if r["error"] is None]
    if not ok:
        raise RuntimeError(f"every trial of {name} failed; see Ray's logs under {root / name}")
    best: dict = {"search": spec["name"], "wall_s": round(time.time() - t0, 1), "trials": len(rows)}
    if spec["kind"] == "models":  # each model by its own validation loss
        e = min(ok, key=lambda r: r["ensemble_val_loss"])
        c = min(ok, key=lambda r: r["cvae_val_loss"])
        chosen = {k: e[k] for k in keys if k.startswith("ensemble.")}
        chosen.update({k: c[k] for k in keys if k.startswith("cvae.")})
        best.update({"ensemble_trial": e["trial"], "ensemble_val_loss": e["ensemble_val_loss"], "cvae_trial": c["trial"],
                     "cvae_val_loss": c["cvae_val_loss"]})
    else:
        pick = (max if spec["mode"] == "max" else min)
        scored = [r for r in ok if isinstance(r.get(spec["metric"]), (int, float))]
        if not scored:
            raise RuntimeError(f"no trial of {name} reported {spec['metric']!r}")
        b = pick(scored, key=lambda r: r[spec["metric"]])
        chosen = {k: b[k] for k in keys}
        best.update({"trial": b["trial"], spec["metric"]: b[spec["metric"]]})
    best["settings"] = chosen
    best["overrides"] = [_override(k, v) for k, v in chosen.items()]
    command = "offhrl fit" if spec["kind"] == "models" else "offhrl train"
    # pasted into a shell as printed; the trials' own order (the preset's overrides, then the user's: the user's win), then the winner's
    best["command"] = shlex.join([*command.split(), *spec["overrides"], *overrides, *best["overrides"]])
    (root / name / "best.json").write_text(json.dumps(best, indent=2, default=str))
    best["table"] = table
    best["out"] = str(root / name)
    return best


def sweep(algos: Sequence[str], envs: Sequence[str], datasets: Sequence[str], seeds: Sequence[int], overrides: Sequence[str] = (), *,
          name: str = "sweep", out_root: str | None = None, address: str | None = None, num_cpus: int | None = None, cpus_per_trial: int = 1,
          gpus_per_trial: float = 0.0, max_concurrent: int | None = None, verbose: int = 1) -> dict:
    """Algorithms x envs x datasets x seeds as Ray Tune trials, each an ordinary run directory under ``<out_root>/sweeps/<name>/``.

    A run directory that already finished its budget is reported without
    training (``skipped``); an unfinished one resumes from its checkpoint.
    Returns ``{"out", "table", "rows"}`` and writes ``results.csv`` /
    ``results.md`` next to the runs.
    """
    axes = {"algo": "--algos", "env": "--envs", "dataset": "--datasets", "seed": "--seeds"}
    keyed = [(o, o.split("=", 1)[0].lstrip("+~")) for o in overrides]
    clash = sorted({k for _, k in keyed if k in axes})
    if clash:  # the grid's value would be replaced under the grid's label and run directory name (a file trained as 'medium')
        raise ValueError(f"{[o for o, k in keyed if k in axes]}: {', '.join(clash)} is an axis of the sweep; give it as "
                         f"{', '.join(axes[k] for k in clash)} (e.g. --datasets /path/to/file.hdf5)")
    for algo, env, ds in itertools.product(algos, envs, datasets):  # every combination composes: errors before Ray starts
        _compose([f"algo={algo}", f"env={env}", f"dataset={ds}", *overrides])
    root = Path(out_root or "outputs") / "sweeps"
    trials = []
    for algo, env, ds, seed in itertools.product(algos, envs, datasets, seeds):
        p = {"algo": algo, "env": env, "dataset": ds, "seed": int(seed)}
        run_dir = (root / name / f"{algo}-{env}-{Path(str(ds)).stem}-seed{seed}").resolve()
        trials.append({"params": p, "overrides": [f"algo={algo}", f"env={env}", f"dataset={ds}", f"seed={seed}", *overrides], "run_dir": str(run_dir)})
    t0 = time.time()
    results, trials = _run_trials(_with_specs(_train_trial, trials), trials, name, root, cpus_per_trial, gpus_per_trial, address, num_cpus,
                                  max_concurrent, verbose)
    rows = _rows(results, trials, ["algo", "env", "dataset", "seed"], name)
    table = _write_table(rows, root / name, f"offhrl sweep {name}: {len(rows)} runs ({time.time() - t0:.0f} s)")
    return {"out": str(root / name), "table": table, "rows": rows}
