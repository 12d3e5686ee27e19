"""Multi-seed tables of recipe runs: scores, IQM with bootstrap CIs, the paper's table.

Plots live in :mod:`~torchrl_offhrl.recipes.plots`, loading and archiving
run directories in :mod:`~torchrl_offhrl.recipes.runs`, one run's
``summary.json`` and its printed paragraph in :mod:`~torchrl_offhrl.recipes.summary`
(their names are re-exported here). Each run directory written by :func:`~torchrl_offhrl.recipes.train.train`
holds ``config.json``, ``evals.json`` (one record per evaluation) and
``summary.json``. :func:`aggregate` groups runs by (algorithm, env, dataset,
ablation), and writes one table (Markdown + CSV: final normalised score,
mean and standard deviation over seeds) and one figure (learning curves,
mean ± std over seeds).
"""
from __future__ import annotations

import csv
import functools
import json
import statistics
from collections import defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from ..stats import iqm_ci, mean_std, paired_change, plot_performance_profiles
from .config import transfer_config, transfer_label
from .plots import UNIT_LABELS, plot_curve, plot_goal_success, plot_training_metrics, plot_transfer, pyplot
from .runs import archive_run, archive_runs, expand_run_dirs, load_run, logged_tail_mean, read_scalar_logs, record_step, run_unit
from .summary import fmt_number, format_summary, run_summary

__all__ = [
    "TABLE_COLUMNS", "TRANSFER_MARKS", "UNIT_LABELS", "aggregate", "archive_run", "archive_runs", "fmt_iqm", "fmt_number", "fmt_per_seed", "group_key", "format_summary", "group_stats", "load_run", "logged_tail_mean", "paper_table",
    "plot_curve", "plot_goal_success", "plot_training_metrics",
    "plot_transfer", "read_scalar_logs", "run_scores", "run_summary", "run_unit", "transfer_stats",
]


#: online frames after the switch at which :func:`transfer_stats` reports the return on the new task
TRANSFER_MARKS = (50_000, 100_000, 300_000)


def transfer_stats(rs: Sequence[dict], marks: Sequence[int] = TRANSFER_MARKS) -> dict:
    """Statistics over the seeds of one group of transfer runs: the new task's return at the switch, after each mark, final, best, area.

    Per run, the online records (``phase == "online"``) are read relative to
    the switch (the first online record): ``at_<k>`` is the return of the
    first evaluation at or after ``switch + k`` frames (evaluations fall on
    collector batch boundaries; None where a run did not get that far), ``area`` is the mean return over the
    online phase (the trapezoid area under the online curve divided by its
    length), ``best`` the best online evaluation after the switch (apart from
    the final one, never instead of it). ``offline_final`` is the last
    offline evaluation's return on the old task (None from scratch). Each
    entry is ``(mean, std, n)`` over the runs that have it.
    """
    per_run = []
    for r in rs:
        online = [e for e in r["evals"] if e.get("phase") == "online"]
        offline = [e for e in r["evals"] if e.get("phase") == "offline"]
        if not online:
            continue
        sw = record_step(online[0])
        xs = torch.tensor([record_step(e) - sw for e in online], dtype=torch.float64)
        ys = torch.tensor([e["return_mean"] for e in online], dtype=torch.float64)
        row = {
            "switch": sw, "online_frames": int(xs[-1]), "offline_final": offline[-1]["return_mean"] if offline else None,
            "at_switch": float(ys[0]), "final": float(ys[-1]), "best": float(ys[1:].max()) if len(ys) > 1 else None,
            "area": float(torch.trapezoid(ys, xs) / xs[-1]) if xs[-1] > 0 else None,
        }
        for k in marks:  # the first evaluation at or after the mark (evaluations fall on batch boundaries)
            row[f"at_{k}"] = next((float(y) for x, y in zip(xs, ys) if int(x) >= k), None)
        per_run.append(row)
    keys = ["offline_final", "at_switch", *[f"at_{k}" for k in marks], "final", "best", "area"]
    return {"seeds": len(per_run), "online_frames": min((p["online_frames"] for p in per_run), default=0),
            **{k: mean_std([p[k] for p in per_run]) for k in keys}}


def group_key(run: dict) -> tuple:
    """``(algo label, env id, dataset, ablations and transfer label or "-")``: the row a loaded run belongs to in the tables."""
    cfg = run["config"]
    abl = ",".join(k for k, v in sorted((cfg.get("ablation") or {}).items()) if v)
    transfer = transfer_label(cfg)
    abl = ",".join(x for x in (abl, transfer) if x) or "-"
    algo = cfg.get("algo", {})
    return (str(algo.get("label") or algo.get("name", "?")), cfg.get("env", {}).get("env_id", "?"), str(cfg.get("dataset", "?")), abl)


def _score(rec: dict | None):
    return None if rec is None else rec.get("normalized_d4rl")


def run_scores(run: dict, last_n: int = 5) -> dict:
    """One loaded run's scores (D4RL-normalised; None where it has none): how a run is scored beyond its last point.

    ``final``: the last evaluation; ``best``: the best after training began;
    ``start``: the evaluation at step 0 (the untrained agent); ``last5``: the
    mean of the last ``last_n`` evaluations after step 0 (a run that
    swings between evaluations is not judged by one of them); ``selected``:
    the policy the run returned by offline policy selection
    (``summary["selected"]``, chosen without the real env), else None;
    ``sampled``: the last evaluation of the *sampled* policy (actions and
    options drawn, ``eval.sampled``) on the same start states, else None.
    """
    evals = run["evals"]
    trained = [e for e in evals if record_step(e) > 0 and _score(e) is not None]
    tail = trained[-last_n:]
    summary = run.get("summary") or {}
    return {
        "seed": (run.get("config") or {}).get("seed"),
        "final": _score(evals[-1]),
        "best": max(_score(e) for e in trained) if trained else None,
        "start": _score(evals[0]) if record_step(evals[0]) == 0 else None,
        # a run known only by a few evaluations (``partial``: start, best, final) has no last five to average
        "last5": sum(_score(e) for e in tail) / len(tail) if tail and not run.get("partial") else None,
        "selected": _score(summary.get("selected")),
        "sampled": evals[-1].get("normalized_d4rl_sampled"),
        "rebuilt": bool(run.get("partial")),
    }


def _stat(values: Sequence, prefix: str) -> dict:
    """``{prefix_iqm, prefix_ci}`` of the values that are not None (None, None when there are none)."""
    vals = [v for v in values if v is not None]
    if not vals:
        return {f"{prefix}_iqm": None, f"{prefix}_ci": None}
    m, lo, hi = iqm_ci(vals)
    return {f"{prefix}_iqm": m, f"{prefix}_ci": (lo, hi)}


def group_stats(rs: Sequence[dict]) -> dict:
    """Statistics over the seeds of one group of loaded runs (:func:`load_run`).

    Every score is D4RL-normalised; each comes as mean +- std and as the
    interquartile mean with its 95% stratified-bootstrap CI
    (:mod:`torchrl_offhrl.stats`), per seed in ``per_seed``
    (:func:`run_scores`). The final evaluation is each run's last; the best
    is the best evaluation after training began (reported apart from the
    final one, never instead of it); the untrained score is the evaluation at
    step 0; ``last5`` the mean of each run's last 5 evaluations;
    ``selected`` the policy each run returned by offline policy selection;
    ``change`` the paired change of the final score over the run's own
    untrained start (mean, CI, and how many runs went up).
    """
    finals = torch.tensor([r["evals"][-1]["return_mean"] for r in rs], dtype=torch.float64)
    per = [run_scores(r) for r in rs]
    scores = [p["final"] for p in per]
    sc = torch.tensor([s for s in scores if s is not None], dtype=torch.float64)
    unit = run_unit(rs[0])
    beh = [r["summary"]["behaviour_normalized_d4rl"] for r in rs if r["summary"] and r["summary"].get("behaviour_normalized_d4rl") is not None]
    best = [p["best"] for p in per if p["best"] is not None]
    start = [p["start"] for p in per if p["start"] is not None]
    bt, st = torch.tensor(best, dtype=torch.float64), torch.tensor(start, dtype=torch.float64)
    pairs = [(p["final"], p["start"]) for p in per if None not in (p["final"], p["start"])]
    change = paired_change([a for a, _ in pairs], [b for _, b in pairs]) if pairs else None
    return {
        "seeds": len(rs), "budget": f"{min(record_step(r['evals'][-1]) for r in rs)} {unit}",
        "return_mean": float(finals.mean()), "return_std": float(finals.std()) if len(rs) > 1 else 0.0,
        "score_mean": float(sc.mean()) if sc.numel() else None,
        "score_std": float(sc.std()) if sc.numel() > 1 else 0.0,
        **_stat(scores, "score"),
        **_stat([p["last5"] for p in per], "last5"),
        **_stat([p["selected"] for p in per], "selected"),
        **_stat([p["sampled"] for p in per], "sampled"),
        "behaviour_score": float(sum(beh) / len(beh)) if beh else None,
        "best_score_mean": float(bt.mean()) if bt.numel() else None,
        "best_score_std": float(bt.std()) if bt.numel() > 1 else 0.0,
        **_stat(best, "best_score"),
        "untrained_score_mean": float(st.mean()) if st.numel() else None,
        "change_mean": None if change is None else change["mean"],
        "change_ci": None if change is None else change["ci"],
        "change_up": None if change is None else f"{change['up']}/{change['n']}",
        "per_seed": per,
    }


def fmt_iqm(m, ci, n: int | None = None) -> str:
    """``IQM [lo, hi] (n)``; one value has no interval: ``x (1)``; ``—`` for None."""
    if m is None:
        return "—"
    tail = "" if n is None else f" ({n})"
    if ci is None or n == 1 or ci[0] == ci[1]:  # one run, or runs that agree: no interval to show
        return f"{m:.1f}{tail}"
    return f"{m:.1f} [{ci[0]:.1f}, {ci[1]:.1f}]{tail}"


def fmt_per_seed(per: Sequence[dict], key: str = "final") -> str:
    """``s4: 95.9, s5: 83.8`` (seed order) of one score of each run."""
    rows = sorted(per, key=lambda p: (p["seed"] is None, p["seed"] if p["seed"] is not None else 0))
    return ", ".join(f"s{'?' if p['seed'] is None else p['seed']}: {fmt_number(p[key])}" for p in rows)


def _load_runs(run_dirs: Sequence, out_dir, who: str) -> tuple[list[dict], Path]:
    """The loaded runs (:func:`load_run`; a dict is taken as an already loaded run) and the output folder, created.

    A folder of run directories (a sweep's) stands for the runs in it (:func:`expand_run_dirs`).

    A loaded run with ``"partial": True`` (a run known only by a few of its
    evaluations, e.g. rebuilt from a committed report after its directory was
    lost) counts in the tables but draws no curve.
    """
    runs = [d if isinstance(d, dict) else load_run(d) for d in expand_run_dirs(run_dirs)]
    if not runs:
        raise ValueError(f"{who}: no run directories given")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return runs, out


def _panel(rs: Sequence[dict]) -> str:
    """Which row of ``curves.png`` a group of runs goes to: its budget's unit, or ``"transfer"`` for two-phase runs."""
    return "transfer" if transfer_config(rs[0]["config"]) is not None else run_unit(rs[0])


def _mstd(stat: tuple, spec: str = ".1f") -> str:
    mean, std, _ = stat
    return "n/a" if mean is None else f"{mean:{spec}} ± {std:{spec}}"


def transfer_table(groups: dict[tuple, list[dict]], marks: Sequence[int] = TRANSFER_MARKS) -> tuple[str, list[dict]]:
    """The Markdown table (and its CSV rows) of the transfer groups: returns on the new task, mean ± std over seeds."""
    header = ("| algo | env | dataset | runs | seeds | online frames | offline final (old task) | at the switch | "
              + " | ".join(f"after {k // 1000}k" for k in marks) + " | final | best | mean over the online phase |")
    lines = [header, "|" + "---|" * (11 + len(marks))]
    rows = []
    for key, rs in sorted(groups.items()):
        st = transfer_stats(rs, marks)
        rows.append({"algo": key[0], "env": key[1], "dataset": key[2], "runs": key[3], "seeds": st["seeds"], "online_frames": st["online_frames"],
                     **{f"{k}_{w}": v for k in st if isinstance(st[k], tuple) for w, v in zip(("mean", "std", "n"), st[k])}})
        lines.append(f"| {key[0]} | {key[1]} | {key[2]} | {key[3]} | {st['seeds']} | {st['online_frames']} | {_mstd(st['offline_final'])} | "
                     f"{_mstd(st['at_switch'])} | " + " | ".join(_mstd(st[f"at_{k}"]) for k in marks)
                     + f" | {_mstd(st['final'])} | {_mstd(st['best'])} | {_mstd(st['area'])} |")
    return "\n".join(lines), rows


def aggregate(run_dirs: Sequence, out_dir, made_by: str | None = None) -> str:
    """Aggregate seeds: writes ``out_dir/results.md``, ``results.csv`` and ``curves.png``; returns the Markdown table(s).

    Transfer runs (two phases, ``transfer.task`` set) get their own table
    (:func:`transfer_table`: returns on the new task, also in ``transfer.csv``)
    and their own row of curves (:func:`plot_transfer`; from-scratch runs
    start at the switch of the transfer runs of the same env).
    ``made_by``: the command that rebuilds the page, named on its first line.
    """
    runs, out = _load_runs(run_dirs, out_dir, "aggregate")
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in runs:
        key = group_key(r)
        if transfer_config(r["config"]) is None and made_with_paper_settings(r["config"]) and not key[0].endswith(PAPER_SUFFIX):
            key = (key[0] + PAPER_SUFFIX, *key[1:])  # as Table I's columns: a paper-preset run is not the default's row
        groups[key].append(r)
    standard = {k: rs for k, rs in groups.items() if _panel(rs) != "transfer"}
    transfer = {k: rs for k, rs in groups.items() if _panel(rs) == "transfer"}
    tables = []
    if standard:
        rows = [{"algo": key[0], "env": key[1], "dataset": key[2], "ablation": key[3], **group_stats(rs)} for key, rs in sorted(standard.items())]
        header = ("| algo | env | dataset | ablation | seeds | budget | final return (mean ± std) | final D4RL: IQM [95% CI] | final D4RL (mean ± std) | "
                  "last 5 evals: IQM [95% CI] | selected policy: IQM [95% CI] | best D4RL: IQM [95% CI] | untrained score | "
                  "change over untrained [95% CI] (runs up) | behaviour score | final per seed |")
        lines = [header, "|" + "---|" * 16]
        for r in rows:
            score = "n/a" if r["score_mean"] is None else f"{r['score_mean']:.1f} ± {r['score_std']:.1f}"
            change = "n/a" if r["change_mean"] is None else f"{r['change_mean']:+.1f} [{r['change_ci'][0]:+.1f}, {r['change_ci'][1]:+.1f}] ({r['change_up']})"
            lines.append(
                f"| {r['algo']} | {r['env']} | {r['dataset']} | {r['ablation']} | {r['seeds']} | {r['budget']} | "
                f"{r['return_mean']:.1f} ± {r['return_std']:.1f} | {fmt_iqm(r['score_iqm'], r['score_ci'])} | {score} | "
                f"{fmt_iqm(r['last5_iqm'], r['last5_ci'])} | {fmt_iqm(r['selected_iqm'], r['selected_ci'])} | "
                f"{fmt_iqm(r['best_score_iqm'], r['best_score_ci'])} | {fmt_number(r['untrained_score_mean'])} | {change} | "
                f"{fmt_number(r['behaviour_score'])} | {fmt_per_seed(r['per_seed'])} |"
            )
        tables.append("D4RL-normalised real-env scores over seeds: interquartile mean with its 95% stratified-bootstrap confidence "
                      "interval, and mean ± std. *Final*: each run's last evaluation; *last 5 evals*: the mean of its last five; "
                      "*selected policy*: the policy chosen by offline policy selection, without the real env; *best*: its best "
                      "evaluation after training began (never instead of the final one).\n\n" + "\n".join(lines))
        rows = [{**r, "per_seed": json.dumps(r["per_seed"])} for r in rows]
        with open(out / "results.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
            w.writeheader()
            w.writerows(rows)
    if transfer:
        ttable, trows = transfer_table(transfer)
        tables.append("Transfer runs: real-env return on the new task (online phase), mean ± std over seeds; "
                      "'offline final' is the last evaluation on the old task.\n\n" + ttable)
        with open(out / "transfer.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(trows[0].keys()))
            w.writeheader()
            w.writerows(trows)
    table = "\n\n".join(tables)
    (out / "results.md").write_text((f"Made by `{made_by}`.\n\n" if made_by else "") + table + "\n")
    if all(r.get("partial") for r in runs):  # nothing to draw: runs known only by a few evaluations draw no curves
        return table
    plt = pyplot()
    envs = sorted({k[1] for k in groups})
    panels = sorted({_panel(rs) for rs in groups.values()})  # one row of panels per x-axis: frames, gradient steps, transfer
    fig, axes = plt.subplots(len(panels), len(envs), figsize=(6 * len(envs), 4 * len(panels)), squeeze=False)
    for row, panel in zip(axes, panels):
        for ax, env_id in zip(row, envs):
            switches = [next(e["frames"] for e in r["evals"] if e.get("phase") == "online") for key, rs in transfer.items() if key[1] == env_id
                        for r in rs if any(e.get("phase") == "online" for e in r["evals"])]
            for key, rs in sorted(groups.items()):
                rs = [r for r in rs if not r.get("partial")]
                if key[1] != env_id or not rs or _panel(rs) != panel:
                    continue
                label = f"{key[0]} {key[2]}" + ("" if key[3] == "-" else f" [{key[3]}]")
                if panel == "transfer":
                    scratch = transfer_config(rs[0]["config"])["from_scratch"]
                    plot_transfer([r["evals"] for r in rs], None, label=label, title=env_id, ax=ax, x_offset=max(switches, default=0) if scratch else 0)
                else:
                    plot_curve([r["evals"] for r in rs], None, label=label, title=env_id, ax=ax, xlabel=UNIT_LABELS.get(panel, panel))
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=110)
    plt.close(fig)
    return table


#: Table I's columns: run label -> column title, in the paper's order (ours on the P-MDP, then the peers)
TABLE_COLUMNS: dict[str, str] = {
    "moc": "MOC", "ppo": "PPO", "sac": "SAC", "morel": "MOReL", "mopo": "MOPO", "iql": "IQL", "cql": "CQL", "td3bc": "TD3+BC", "bc": "BC",
}
#: columns outside Table I's standard ones that have a title of their own
EXTRA_COLUMNS: dict[str, str] = {"moc_1opt": "MOC, 1 option", "ppoc": "PPOC (eta 0)", "morel_style": "MOReL-style (old)"}
#: a model-env run made with the paper's per-dataset settings (``preset=paper``, or before the offline rules became the
#: default on 2026-12-06) is not what ``offhrl train`` runs now: its own column, ``<label>_paper``
PAPER_SUFFIX = "_paper"


def made_with_paper_settings(cfg: Mapping) -> bool:
    """Whether a model-env run's config is the paper's per-dataset tables rather than the offline rules: its latent origin is
    the paper's (``zero``, what ``preset=paper`` sets, or chosen by hand) or absent (a run made before the rules,
    2026-12-06). Dataset agents (IQL, CQL, TD3+BC, BC) use no model, so no preset changes them: never; nor block-stacking
    runs, whose shipped setting is the paper's (``configs/env/blockstack*.yaml``)."""
    from ..registry import task_of
    from .config import learns_from_dataset

    try:
        if learns_from_dataset(cfg) or task_of((cfg.get("env") or {}).get("env_id")).goal_conditioned:
            return False
    except (KeyError, ValueError):  # an algorithm this version no longer ships
        return False
    return (cfg.get("model_env") or {}).get("latent_origin", "zero") == "zero"


def table_column(run: dict) -> str:
    """A run's Table I column: its label, with its ablations in brackets. MOReL runs from before the config followed MOReL's
    official code (no behaviour-cloned start: PPO in real actions from a random policy, threshold max / 3) are
    ``morel_style``, apart from ``morel``."""
    label, _, _, abl = group_key(run)
    if label == "morel" and not (run["config"].get("algo") or {}).get("bc_init_steps"):
        return "morel_style"
    paper = PAPER_SUFFIX if made_with_paper_settings(run["config"]) and not label.endswith(PAPER_SUFFIX) else ""
    if label == "morel":  # MOReL acts in real actions by design: no_cvae is part of it
        return label + paper
    label += paper
    own = _own_ablations(str((run["config"].get("algo") or {}).get("name", "")))  # MOPO is SAC without CVAE or P-MDP by design
    parts = [a for a in abl.split(",") if a != "-"]
    abl = ",".join([*(a for a in parts if a not in own), *(f"{a}=false" for a in sorted(own - set(parts)))]) or "-"
    return label if abl == "-" else f"{label} [{abl}]"


@functools.lru_cache(maxsize=None)
def _own_ablations(algo: str) -> frozenset[str]:
    """The ablation switches an algorithm's shipped config turns on itself (``configs/algo/mopo.yaml``: no_cvae,
    no_pessimism): part of what the algorithm is, not an ablation of it. Read from the composed config, defaults included."""
    from .config import compose, config_dir

    if not algo or not (config_dir() / "algo" / f"{algo}.yaml").is_file():
        return frozenset()
    return frozenset(k for k, v in (compose("offline_train", [f"algo={algo}"]).get("ablation") or {}).items() if v)


def column_title(column: str) -> str:
    if column.endswith(PAPER_SUFFIX) and column not in EXTRA_COLUMNS:
        base = column[: -len(PAPER_SUFFIX)]
        return f"{TABLE_COLUMNS.get(base) or EXTRA_COLUMNS.get(base) or base} (paper preset)"
    return TABLE_COLUMNS.get(column) or EXTRA_COLUMNS.get(column) or column


def seed_cost(runs: Sequence[dict]) -> str | None:
    """What one seed of these runs cost, measured: the median of their ``total_s`` less the data and model fits (cached and
    shared by every seed of a dataset), with the device and thread count they ran on; None without a timed run."""
    timed = [r for r in runs if r.get("summary") and r["summary"].get("total_s") is not None]
    if not timed:
        return None
    med = statistics.median(float(r["summary"]["total_s"]) - float(r["summary"].get("models_s") or 0) - float(r["summary"].get("data_s") or 0)
                            for r in timed)
    where = sorted({f"{r['config'].get('device', 'cpu')}, {r['config'].get('torch_threads') or 'default'} threads" for r in timed})
    return f"{med / 3600:.1f} h per seed ({'; '.join(where)}; median of {len(timed)} timed run{'s' if len(timed) != 1 else ''})"


def _env_name(env_id: str) -> str:
    return env_id.split("-v")[0].lower()


def _dataset_name(dataset: str) -> str:
    """A level name as it is; a file path or Minari id by its last part without suffix (for row labels and file names)."""
    return Path(dataset).stem if "/" in dataset or Path(dataset).suffix else dataset


#: the :func:`run_scores` key behind each kind of table cell
PER_SEED_KEY = {"score": "final", "best_score": "best", "last5": "last5", "selected": "selected", "sampled": "sampled"}


def _seeds_by(groups: Mapping[tuple, list], columns: Sequence[str], value) -> list[tuple[tuple, dict]]:
    """Each cell ``(env_id, dataset, column)`` of the page's ``columns``, in its order, with its runs' seeds split by ``value(config)``:
    ``[(key, {value: [seed, ...]})]`` (the sections on cells that pool runs of different kinds)."""
    out = []
    cells = [(key, rs) for key, rs in groups.items() if key[2] in columns]  # the page's columns only
    for key, rs in sorted(cells, key=lambda kv: (kv[0][0], kv[0][1], columns.index(kv[0][2]))):
        split = defaultdict(list)
        for r in rs:
            cfg = r.get("config") or {}
            split[value(cfg)].append(cfg.get("seed"))
        out.append((key, split))
    return out


def _dataset_instances(groups: Mapping[tuple, list], row_name: Mapping[tuple, str], columns: Sequence[str]) -> tuple[list[str], set]:
    """Which generated instance of its dataset (the runs' ``data_hash``) each run of a row used: the page's section on rows
    whose runs used more than one, and the cells ``(env_id, dataset, column)`` whose seeds mix instances (marked ``‡``).

    Data generated on another machine differ in their floating-point details, so two instances of "hopper-medium" are
    two datasets: runs on different ones are not the same experiment, and a cell that pools them says so.
    """
    per_row: dict[str, dict[str, list[str]]] = defaultdict(lambda: defaultdict(list))
    mixed = set()
    for key, hashes in _seeds_by(groups, columns, lambda cfg: cfg.get("data_hash") or "unknown"):
        env_id, dataset, c = key
        if len(hashes) > 1:
            mixed.add(key)
        for h, seeds in hashes.items():
            per_row[row_name[env_id, dataset]][h].append(
                f"{column_title(c)} " + " ".join(f"s{s}" for s in sorted(x for x in seeds if x is not None)))
    rows = {row: hs for row, hs in per_row.items() if len(hs) > 1}
    if not rows:
        return [], mixed
    lines = ["## Dataset instances", "",
             "Data generated on another machine differ in their floating-point details (the runs' `data_hash`): runs on two "
             "instances of one dataset are runs on two datasets. Rows whose runs used more than one instance (`unknown`: a run "
             "rebuilt from an earlier page, whose data were not recorded); a cell marked ‡ pools seeds from more than one:", ""]
    for row, hs in sorted(rows.items()):
        lines.append(f"- {row}: " + "; ".join(f"`{h}`: {', '.join(cols)}" for h, cols in sorted(hs.items(), key=lambda x: -len(x[1]))))
    return [*lines, ""], mixed


def _eval_episodes(groups: Mapping[tuple, list], row_name: Mapping[tuple, str], columns: Sequence[str]) -> tuple[list[str], set]:
    """The cells ``(env_id, dataset, column)`` whose seeds were evaluated on different numbers of episodes (the runs'
    ``eval.episodes``; marked ``§``), and the page's section listing them with each count's seeds.

    A score over 10 episodes is a noisier estimate of the same policy's return than one over 30: the cell's IQM pools
    them as equals, so the page says which seeds had which.
    """
    lines, mixed = [], set()
    for key, counts in _seeds_by(groups, columns, lambda cfg: (cfg.get("eval") or {}).get("episodes")):
        if len(counts) > 1:
            mixed.add(key)
            env_id, dataset, c = key
            lines.append(f"- {row_name[env_id, dataset]}, {column_title(c)}: " + "; ".join(
                f"{n if n is not None else 'unknown'} episodes: " + " ".join(f"s{x}" for x in sorted(v for v in seeds if v is not None))
                for n, seeds in sorted(counts.items(), key=lambda kv: (kv[0] is None, kv[0] or 0))))
    if not lines:
        return [], mixed
    return ["## Evaluation episodes", "",
            "A cell marked § pools seeds evaluated on different numbers of episodes (`unknown`: a run rebuilt from an earlier "
            "page): each seed's score is the mean over its own episodes, the fewer the noisier.", "", *lines, ""], mixed


def paper_table(run_dirs: Sequence, out_dir, title: str = "Offline RL on our datasets", min_seeds: int = 3,
                missing_reasons: Mapping[str, str] | None = None, made_by: str | None = None) -> str:
    """The paper's Table I from run directories: rows env x dataset, one column per algorithm, the behaviour data last.

    Writes ``out_dir/table.md`` (the final evaluations, the best evaluations
    in a second table, and the published scores, measured on D4RL's own data,
    in a separate block), ``table.csv`` (one row per env, dataset and
    algorithm) and ``curves_<env>-<dataset>.png`` (mean +- std over seeds; one
    panel per budget unit: model-env frames, gradient steps). Cells are
    ``mean ± std (seeds)`` of the D4RL-normalised score; ``—`` marks an
    algorithm with no run for that dataset. Runs with an ablation get their
    own column (``label [ablation]``), except MOReL-style runs, whose config
    is that ablation.

    A section *Missing cells* lists, row by row, every standard column with
    no run or fewer than ``min_seeds`` seeds, each with its reason from
    ``missing_reasons``: keyed ``"<row>:<algo>"`` for one cell (e.g.
    ``"hopper-medium-expert:cql"``) or ``"<row>"`` for the rest of a row;
    a cell with neither says that no reason was given.

    ``table.md`` holds the standard columns only (:data:`TABLE_COLUMNS`: each
    algorithm as its shipped default runs it). Every other column (the paper
    preset, ablations, tuning variants) goes to ``variants.md`` beside it, in
    the same layout, so that the headline table measures what a user runs and
    nothing else; a run set with no such column leaves no ``variants.md``.
    """
    from ..scores import PUBLISHED_SCORES

    runs, out = _load_runs(run_dirs, out_dir, "paper_table")
    runs = [r for r in runs if transfer_config(r["config"]) is None]  # transfer runs end on another task: `offhrl aggregate` reports them
    if not runs:
        raise ValueError("paper_table: every run given is a transfer run (transfer.task set); report those with `offhrl aggregate`")
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in runs:
        _, env_id, dataset, _ = group_key(r)
        groups[(env_id, dataset, table_column(r))].append(r)
    stats = {key: group_stats(rs) for key, rs in groups.items()}
    datasets = sorted({(k[0], k[1]) for k in groups})
    row_name = {(e, d): f"{_env_name(e)}-{_dataset_name(d)}" for e, d in datasets}  # "hopper-medium": table rows, missing cells, figures
    present = {k[2] for k in groups}
    paper = [c + PAPER_SUFFIX for c in TABLE_COLUMNS if c + PAPER_SUFFIX in present]  # the same agents on the paper preset
    headline = list(TABLE_COLUMNS)  # every standard column (missing: —): table.md
    variants = [*paper, *sorted(present - set(TABLE_COLUMNS) - set(paper))]  # the rest: variants.md
    columns = [*headline, *variants]
    # each page's sections on cells that pool runs of different kinds, and the cells they mark (a mark is per cell: either page)
    pages = {"table": headline, "variants": variants}
    instances = {page: _dataset_instances(groups, row_name, cols) for page, cols in pages.items()}  # page -> (section, marked cells)
    episodes = {page: _eval_episodes(groups, row_name, cols) for page, cols in pages.items()}
    mixed, mixed_episodes = instances["table"][1] | instances["variants"][1], episodes["table"][1] | episodes["variants"][1]

    behaviour = {}  # the behaviour data's score per row: the first of its columns' (in column order) that has one
    for (e, d, c), st in sorted(stats.items(), key=lambda kv: columns.index(kv[0][2])):
        if st["behaviour_score"] is not None:
            behaviour.setdefault((e, d), st["behaviour_score"])

    def table(kind: str, columns: list[str]) -> list[str]:
        lines = ["| dataset | " + " | ".join(column_title(c) for c in columns) + " | behaviour data |", "|" + "---|" * (len(columns) + 2)]
        for env_id, dataset in datasets:
            cells = []
            for c in columns:
                st = stats.get((env_id, dataset, c))
                if st is None:
                    cells.append("—")
                    continue
                n = sum(p[PER_SEED_KEY[kind]] is not None for p in st["per_seed"])
                mark = (" ‡" if (env_id, dataset, c) in mixed else "") + (" §" if (env_id, dataset, c) in mixed_episodes else "")
                cells.append(fmt_iqm(st[f"{kind}_iqm"], st[f"{kind}_ci"], n) + mark if n else "—")
            lines.append(f"| {row_name[env_id, dataset]} | " + " | ".join(cells) + f" | {fmt_number(behaviour.get((env_id, dataset)))} |")
        return lines

    budgets: dict[str, set[str]] = defaultdict(set)  # column -> its distinct budgets ("MOC: 200 frames")
    for k, st in stats.items():
        budgets[k[2]].add(f"{column_title(k[2])}: {st['budget']}")
    reasons = dict(missing_reasons or {})
    short: list[str] = []
    # what one seed of a column cost, over all its runs on the page (the same for every row it is missing from)
    cost_of = {c: seed_cost([r for k, rs in groups.items() if k[2] == c for r in rs]) for c in TABLE_COLUMNS}
    for env_id, dataset in datasets:
        row = row_name[env_id, dataset]
        by_reason: dict[str, list[tuple[str, int]]] = defaultdict(list)
        for c in TABLE_COLUMNS:
            n = stats[(env_id, dataset, c)]["seeds"] if (env_id, dataset, c) in stats else 0
            if n < min_seeds:
                why = reasons.get(f"{row}:{c}", reasons.get(row, "No reason given."))
                by_reason[why].append((c, n))
        for why, cols in by_reason.items():
            cells = [f"{TABLE_COLUMNS[c]} ({n} seed{'s' if n != 1 else ''})" if n else f"{TABLE_COLUMNS[c]} (no run)" for c, n in cols]
            costs = [f"{TABLE_COLUMNS[c]} {cost_of[c]}" for c, _ in cols if cost_of[c]]
            short.append(f"- {row}: {', '.join(cells)}. {why}" + (f" Measured on this page's runs: {'; '.join(costs)}." if costs else ""))
    missing = [f"## Missing cells (fewer than {min_seeds} seeds)", "", *(short or ["None: every column has its seeds."]), ""]
    def seeds_of(columns: list[str]):
        return [p for (_, _, c), st in stats.items() if c in columns for p in st["per_seed"]]

    def has(key: str, columns: list[str]) -> bool:  # a table only where some run of the page's columns has that score
        return any(p[key] is not None for p in seeds_of(columns))

    def per_seed(columns: list[str]) -> list[str]:
        sampled = has("sampled", columns)
        rebuilt = any(p["rebuilt"] for p in seeds_of(columns))  # the legend only where a row carries the mark
        lines = [f"## Per-seed values (final / selected / last-5 mean / best / untrained{' / final sampled' if sampled else ''})", "",
                 *(["`*`: a run known only from an earlier page (start, best and final: no last five, no selection).", ""] if rebuilt else [])]
        for env_id, dataset in datasets:
            for c in columns:
                st = stats.get((env_id, dataset, c))
                if st is None:
                    continue
                vals = "; ".join(f"s{p['seed']}{'*' if p['rebuilt'] else ''}: {fmt_number(p['final'])} / {fmt_number(p['selected'])} / "
                                 f"{fmt_number(p['last5'])} / {fmt_number(p['best'])} / {fmt_number(p['start'])}" + (f" / {fmt_number(p['sampled'])}" if sampled else "")
                                 for p in sorted(st["per_seed"], key=lambda p: (p["seed"] is None, p["seed"] or 0)))
                change = "" if st["change_mean"] is None else (f"; change over untrained {st['change_mean']:+.1f} "
                                                               f"[{st['change_ci'][0]:+.1f}, {st['change_ci'][1]:+.1f}], {st['change_up']} runs up")
                lines.append(f"- {row_name[env_id, dataset]}, {column_title(c)}: {vals}{change}")
        return [*lines, ""]

    def tables(columns: list[str]) -> list[str]:
        sampled = has("sampled", columns)  # the sampled policy's final score, on pages whose runs evaluated it
        return ["## Final evaluation", "", *table("score", columns), "",
                *(["## Selected policy (offline policy selection, without the real env)", "", *table("selected", columns), ""]
                  if has("selected", columns) else []),
                *(["## Mean of the last 5 evaluations", "", *table("last5", columns), ""] if has("last5", columns) else []),
                *(["## Final evaluation of the sampled policy (actions and options drawn, on the same start states as the deterministic one)", "",
                   "The deterministic evaluation runs each policy's mode; what the agents' losses train is the sampled policy. "
                   "Read a row beside the same row of the final evaluation above: where the sampled score stays at the data's and the "
                   "deterministic one rises, training moved the mode, not the policy it trains.", "",
                   *table("sampled", columns), ""] if sampled else []),
                "## Best evaluation during training (after step 0; reported apart from the final one, never instead of it)", "",
                *table("best_score", columns), "",
                "Budgets: " + "; ".join(b for c in columns for b in sorted(budgets.get(c, []))) + ".", "", *per_seed(columns)]

    legend = ("D4RL-normalised real-env return, deterministic evaluation: interquartile mean over seeds with its 95% stratified-bootstrap "
              "confidence interval, [lower, upper], (number of seeds); mean ± std per cell in table.csv.")
    md = [f"# {title}", "", *([f"Made by `{made_by}`.", ""] if made_by else []), legend, "",
          *([f"Each column is an algorithm as its shipped default runs it. The paper preset, ablations and tuning variants "
             f"({len(variants)} columns) are on [variants.md](variants.md), not here.", ""] if variants else []),
          *tables(headline), *missing, *instances["table"][0], *episodes["table"][0],
          "## Published scores (measured on D4RL's datasets, not ours: for orientation only)", "",
          "| method | " + " | ".join(k for k in next(iter(PUBLISHED_SCORES.values()))) + " |",
          "|" + "---|" * (1 + len(next(iter(PUBLISHED_SCORES.values())))),
          *[f"| {m} | " + " | ".join(f"{v:g}" for v in row.values()) + " |" for m, row in PUBLISHED_SCORES.items()], ""]
    text = "\n".join(md)
    (out / "table.md").write_text(text)
    if variants:  # the same layout for every column that is not a shipped default
        (out / "variants.md").write_text("\n".join([
            f"# {title}: variants, ablations and the paper preset", "", *([f"Made by `{made_by}`.", ""] if made_by else []), legend, "",
            "These columns are not what `offhrl train algo=<algo>` runs: the paper preset (the paper's per-dataset settings, kept "
            "to reproduce its columns), ablations and tuning variants, on the same data as the headline table, "
            "[table.md](table.md) (the shipped algorithms; the missing cells and the published scores are there).", "", *tables(variants),
            *instances["variants"][0], *episodes["variants"][0]]))
    elif (out / "variants.md").is_file():
        (out / "variants.md").unlink()  # an earlier report's variants: gone with their runs
    with open(out / "table.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["env", "dataset", "algo", *next(iter(stats.values())).keys()])
        w.writeheader()
        for (env_id, dataset, c), st in sorted(stats.items()):
            w.writerow({"env": env_id, "dataset": dataset, "algo": c, **st, "per_seed": json.dumps(st["per_seed"])})
    plt = pyplot()  # performance profiles: one panel per dataset row, one curve per column (its runs' final scores)
    fig, axes = plt.subplots(1, len(datasets), figsize=(5.5 * len(datasets), 4), squeeze=False)
    for ax, (env_id, dataset) in zip(axes[0], datasets):
        curves = {column_title(c): [p["final"] for p in stats[(e, d, c)]["per_seed"] if p["final"] is not None]
                  for (e, d, c) in sorted(stats) if (e, d) == (env_id, dataset)}
        beh = next((stats[k]["behaviour_score"] for k in stats if k[:2] == (env_id, dataset) and stats[k]["behaviour_score"] is not None), None)
        plot_performance_profiles({k: v for k, v in curves.items() if v}, ax=ax, title=f"{row_name[env_id, dataset]}: final scores",
                                  reference=beh)
    fig.tight_layout()
    fig.savefig(out / "performance_profile.png", dpi=100)
    plt.close(fig)
    plt = pyplot()
    for env_id, dataset in datasets:
        keys = [k for k in sorted(groups) if k[:2] == (env_id, dataset)]
        if all(r.get("partial") for k in keys for r in groups[k]):
            continue  # no curve to draw (see _load_runs)
        units = sorted({run_unit(groups[k][0]) for k in keys})
        fig, axes = plt.subplots(1, len(units), figsize=(6 * len(units), 4), squeeze=False)
        beh = next((stats[k]["behaviour_score"] for k in keys if stats[k]["behaviour_score"] is not None), None)
        for ax, unit in zip(axes[0], units):
            if beh is not None:
                ax.axhline(beh, color="gray", ls="--", label="behaviour data")
            for k in keys:
                whole = [r for r in groups[k] if not r.get("partial")]
                if whole and run_unit(groups[k][0]) == unit:
                    plot_curve([r["evals"] for r in whole], None, label=column_title(k[2]), key="normalized_d4rl", ax=ax,
                               title=row_name[env_id, dataset], xlabel=UNIT_LABELS.get(unit, unit))
            ax.set_ylabel("D4RL-normalised score")
        fig.tight_layout()
        fig.savefig(out / f"curves_{row_name[env_id, dataset]}.png", dpi=110)
        plt.close(fig)
    return text
