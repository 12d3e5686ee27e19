"""Run directories as data: loading a run's records, archiving finished runs, reading its scalar logs.

A run directory (:class:`~torchrl_offhrl.recipes.rundir.RunDirectory`) holds
``config.json``, ``evals.json`` (one record per evaluation), ``summary.json``
and ``logs/``; :func:`load_run` reads it, :func:`archive_run` copies what a
report needs into the repository, :func:`expand_run_dirs` finds the runs in a
folder of them (a sweep's).
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

from ..utils import atomic_write, read_json, write_json  # noqa: F401  (read_json, write_json: re-exported, a run's records)

__all__ = ["archive_run", "archive_runs", "expand_run_dirs", "load_run", "logged_tail_mean", "read_json", "read_scalar_logs", "record_step", "run_unit"]


def record_step(record: dict) -> int:
    """Where an evaluation record sits on its run's x-axis: ``step`` (frames, or updates for dataset agents); older records: frames."""
    return record.get("step", record["frames"])


def run_unit(run: dict) -> str:
    """The unit of a loaded run's budget: ``"frames"`` or ``"updates"`` (older runs: frames)."""
    return ((run.get("summary") or {}).get("unit") or (run.get("config") or {}).get("unit") or "frames")


def load_run(run_dir) -> dict:
    """``{"dir", "config", "evals", "summary"}`` of a run directory (summary may be missing for unfinished runs)."""
    d = Path(run_dir)
    evals_path = d / "evals.json"
    if not evals_path.is_file():
        raise FileNotFoundError(f"{d} has no evals.json: not a run directory written by offline_train")
    cfg = read_json(d / "config.json") if (d / "config.json").is_file() else {}
    summary = read_json(d / "summary.json") if (d / "summary.json").is_file() else None
    evals = read_json(evals_path)
    if not isinstance(evals, list) or not evals:
        raise ValueError(f"{evals_path} holds no evaluation records ({evals!r}): the run has not evaluated yet; "
                         "let it run to its first evaluation, or leave it out")
    return {"dir": str(d), "config": cfg, "evals": evals, "summary": summary}


def archive_run(run_dir, dest, extra: Sequence[str] = ()) -> Path:
    """Copy what the reports read of a finished run into ``dest`` (a folder small enough to commit); returns ``dest``.

    A run directory holds checkpoints, models and logs (megabytes) and lives
    under ``outputs/``, which is not kept between machines; the archive keeps
    ``config.json``, ``evals.json`` and ``summary.json`` as they are, plus
    ``diagnostics.json``: the mean of the last 5 logged values of every
    training scalar (``{"train_tail_means": {key: value}}``, the numbers
    :func:`logged_tail_mean` gives), and the files named in ``extra`` that the
    run has (e.g. ``option_usage.pt``). :func:`load_run` reads the archive
    like the run directory it came from. An archive already at ``dest`` is
    overwritten only by the same run (the same
    :func:`~torchrl_offhrl.recipes.config.config_fingerprint`: resumed, or run
    longer); another run's raises :class:`FileExistsError`.
    """
    src, dest = Path(run_dir), Path(dest)
    if not (src / "summary.json").is_file():
        raise FileNotFoundError(f"{src} has no summary.json: the run has not finished; archive it once it has")
    run = load_run(src)  # fails with the reason if the run's files are damaged, before anything is written
    if (dest / "config.json").is_file():
        from .config import config_fingerprint

        kept = read_json(dest / "config.json")
        if config_fingerprint(kept) != config_fingerprint(run["config"]):
            raise FileExistsError(f"{dest} archives another run than {src} (their configs differ in more than budget, evaluation and "
                                  "speed settings): archiving would overwrite it; move the old archive to a name of its own "
                                  f"(e.g. {dest.parent / ('old_' + dest.name)}) or delete it, then archive again")
    dest.mkdir(parents=True, exist_ok=True)
    for name in ("config.json", "evals.json", "summary.json", *extra):
        if (src / name).is_file():
            with atomic_write(dest / name) as tmp:  # a temporary file of its own: two run loops may archive the same run at once
                Path(tmp).write_bytes((src / name).read_bytes())
    series = read_scalar_logs(src / "logs")
    tails = {k.split("/", 1)[1]: sum(v[-5:]) / len(v[-5:]) for k, (_, v) in sorted(series.items()) if k.startswith("train/") and v}
    with atomic_write(dest / "diagnostics.json") as tmp:
        Path(tmp).write_text(json.dumps({"train_tail_means": tails}, indent=1) + "\n")
    return dest


def archive_runs(base, dest, extra: Sequence[str] = ()) -> list[Path]:
    """:func:`archive_run` for every finished run (``summary.json`` written) named ``*-seed*`` under ``base``, to ``dest/<run>``."""
    done = sorted(d for d in Path(base).glob("*-seed*") if (d / "summary.json").is_file())
    return [archive_run(d, Path(dest) / d.name, extra=extra) for d in done]


def expand_run_dirs(paths: Sequence) -> list:
    """Run directories from ``paths``: a run directory (it has ``evals.json``) as given; a folder of runs (``offhrl sweep``'s, beside
    Ray's own files) as the run directories directly in it, sorted. Anything else is kept (:func:`load_run` then says what it is)."""
    out = []
    for p in paths:
        d = Path(p) if not isinstance(p, dict) else None
        if d is not None and d.is_dir() and not (d / "evals.json").is_file():
            inner = sorted(c for c in d.iterdir() if c.is_dir() and (c / "evals.json").is_file())
            if inner:
                out.extend(inner)
                continue
        out.append(p)
    return out


def read_scalar_logs(log_dir, keys: Sequence[str] | None = None) -> dict[str, tuple[list[float], list[float]]]:
    """A run's CSV logs (``log_dir/scalars/{train,eval}/*.csv``) as ``{"<group>/<key>": (frames, values)}``.

    ``keys`` picks series by key or by ``group/key`` (default: every file);
    empty files are left out, and so is everything when there are no CSV logs.
    """
    root = Path(log_dir) / "scalars"
    series = {}
    for f in sorted(root.glob("*/*.csv")) if root.is_dir() else []:
        name = f"{f.parent.name}/{f.stem}"
        if keys is not None and f.stem not in keys and name not in keys:
            continue
        rows = [line.split(",") for line in f.read_text().splitlines() if line]
        if rows:
            series[name] = ([float(r[0]) for r in rows], [float(r[1]) for r in rows])
    return series


def logged_tail_mean(run_dir, key: str, n: int = 5) -> float | None:
    """Mean of the last ``n`` logged values of the training scalar ``key`` of a run (None when it was not logged)."""
    series = read_scalar_logs(Path(run_dir) / "logs", [f"train/{key}"])
    if not series:
        return None
    tail = series[f"train/{key}"][1][-n:]
    return sum(tail) / len(tail)
