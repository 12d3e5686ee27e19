"""Plots and multi-seed aggregation of recipe runs.

Each run directory written by :func:`~torchrl_offhrl.recipes.train.train`
holds ``config.json``, ``evals.json`` (one record per evaluation) and
``summary.json``. :func:`aggregate` groups runs by (algorithm, env, dataset,
ablation), and writes one table (Markdown + CSV: final normalised score,
mean and standard deviation over seeds) and one figure (learning curves,
mean ± std over seeds).
"""
from __future__ import annotations

import csv
import json
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import torch

__all__ = ["BEHAVIOUR_LEVELS", "aggregate", "behaviour_figure", "load_run", "plot_behaviour_run", "plot_curve", "plot_option_usage"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _curve_stats(runs: Sequence[Sequence[dict]], key: str):
    """Mean and std over runs at the evaluation points every run has."""
    common = sorted(set.intersection(*[{r["frames"] for r in recs} for recs in runs])) if runs else []
    if not common:
        return [], torch.zeros(0), torch.zeros(0)
    vals = torch.tensor([[next(r[key] for r in recs if r["frames"] == f) for f in common] for recs in runs], dtype=torch.float64)
    std = vals.std(0) if vals.shape[0] > 1 else torch.zeros(vals.shape[1], dtype=torch.float64)
    return common, vals.mean(0), std


def plot_curve(runs: Sequence[Sequence[dict]], path, label: str = "", title: str = "", behaviour: float | None = None, key: str = "return_mean", ax=None):
    """Learning curve(s): the mean over runs, shaded ± one std over runs.

    With a single run, the band is the std over its evaluation episodes.
    """
    plt = _plt()
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(6, 4))
    frames, mean, std = _curve_stats(runs, key)
    if len(runs) == 1 and key == "return_mean":
        std = torch.tensor([r.get("return_std", 0.0) for r in runs[0] if r["frames"] in frames], dtype=torch.float64)
    ax.plot(frames, mean, marker="o", ms=3, label=f"{label} (n={len(runs)})" if label else None)
    ax.fill_between(frames, mean - std, mean + std, alpha=0.25)
    if behaviour is not None:
        ax.axhline(behaviour, color="gray", ls="--", label="behaviour (dataset)")
    ax.set_xlabel("model-env frames")
    ax.set_ylabel("real-env return" if key == "return_mean" else key)
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    if own:
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
    return path


def plot_option_usage(usage: torch.Tensor, path, title: str = "option usage"):
    """``usage [T, n]``: fraction of running episodes in which each option is active at each step."""
    plt = _plt()
    t, n = usage.shape
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.stackplot(range(t), usage.T.numpy(), labels=[f"option {i}" for i in range(n)], alpha=0.85)
    ax.set_xlim(0, max(t - 1, 1))
    ax.set_ylim(0, 1)
    ax.set_xlabel("time step in episode")
    ax.set_ylabel("fraction of episodes")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8, ncol=min(n, 4))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


#: D4RL normalised scores drawn on behaviour curves: the medium band and the expert target.
BEHAVIOUR_LEVELS = {"medium band (30-50)": (30.0, 50.0), "expert target (85)": (85.0,)}


def plot_behaviour_run(run_dir, path=None):
    """Learning curve of a behaviour run (``scripts/train_behaviour.py --out run_dir``).

    Stochastic return (mean, shaded ± std over the evaluation episodes) and
    deterministic return against env steps, read from ``run_dir/evals.json``.
    For an env with D4RL reference returns, a right axis gives the
    normalised score and dotted lines mark the medium band (30-50) and the
    expert target (85), so the checkpoints that qualify for a level are read
    off the figure. Written atomically to ``path`` (default
    ``run_dir/curve.png``); returns the path.
    """
    from ..utils import atomic_write

    d = Path(run_dir)
    evals_path = d / "evals.json"
    if not evals_path.is_file():
        raise FileNotFoundError(f"{d} has no evals.json: not an --out folder of scripts/train_behaviour.py")
    run = json.loads(evals_path.read_text())
    if not run.get("evals"):
        raise ValueError(f"{evals_path}: no evaluation records yet (the first comes after --eval-every steps)")
    fig = behaviour_figure(run)
    path = d / "curve.png" if path is None else Path(path)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def behaviour_figure(run: dict):
    """The matplotlib figure of :func:`plot_behaviour_run` for the contents of an ``evals.json``.

    A plain :class:`~matplotlib.figure.Figure` (not pyplot's): drawing it
    leaves the caller's matplotlib backend and open figures alone.
    """
    from matplotlib.figure import Figure

    from ..scores import d4rl_reference, normalized_score, return_for_score

    records = run["evals"]
    steps = [r["steps"] for r in records]
    mean = torch.tensor([r["stochastic"]["mean"] for r in records])
    std = torch.tensor([r["stochastic"]["std"] for r in records])
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    ax.plot(steps, mean, marker="o", ms=2.5, label="stochastic (as collected)")
    ax.fill_between(steps, mean - std, mean + std, alpha=0.25)
    ax.plot(steps, [r["deterministic"]["mean"] for r in records], lw=1, alpha=0.8, label="deterministic")
    env_id = run.get("env_id", "")
    if d4rl_reference(env_id) is not None:
        for (name, scores), color in zip(BEHAVIOUR_LEVELS.items(), ("tab:green", "tab:red")):
            for i, sc in enumerate(scores):
                ax.axhline(return_for_score(env_id, sc), color=color, ls=":", lw=1, label=name if i == 0 else None)
        ax.secondary_yaxis("right", functions=(lambda r: normalized_score(env_id, r), lambda s: return_for_score(env_id, s))).set_ylabel("D4RL score")
    ax.set_xlabel("env steps")
    ax.set_ylabel(f"return ({len(records)} evaluations)")
    ax.set_title(f"{run.get('algorithm', 'sac')} {run.get('env_id', '?')} seed {run.get('seed', '?')}")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return fig


def load_run(run_dir) -> dict:
    """``{"dir", "config", "evals", "summary"}`` of a run directory (summary may be missing for unfinished runs)."""
    d = Path(run_dir)
    evals_path = d / "evals.json"
    if not evals_path.is_file():
        raise FileNotFoundError(f"{d} has no evals.json: not a run directory written by offline_train")
    cfg = json.loads((d / "config.json").read_text()) if (d / "config.json").is_file() else {}
    summary = json.loads((d / "summary.json").read_text()) if (d / "summary.json").is_file() else None
    return {"dir": str(d), "config": cfg, "evals": json.loads(evals_path.read_text()), "summary": summary}


def _group_key(run: dict) -> tuple:
    cfg = run["config"]
    abl = ",".join(k for k, v in sorted((cfg.get("ablation") or {}).items()) if v) or "-"
    return (cfg.get("algo", {}).get("name", "?"), cfg.get("env", {}).get("env_id", "?"), str(cfg.get("dataset", "?")), abl)


def aggregate(run_dirs: Sequence, out_dir) -> str:
    """Aggregate seeds: writes ``out_dir/results.md``, ``results.csv`` and ``curves.png``; returns the Markdown table."""
    runs = [load_run(d) for d in run_dirs]
    if not runs:
        raise ValueError("aggregate: no run directories given")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in runs:
        groups[_group_key(r)].append(r)
    rows = []
    for key, rs in sorted(groups.items()):
        finals = torch.tensor([r["evals"][-1]["return_mean"] for r in rs], dtype=torch.float64)
        scores = [r["evals"][-1].get("normalized_d4rl") for r in rs]
        sc = torch.tensor([s for s in scores if s is not None], dtype=torch.float64)
        frames = min(r["evals"][-1]["frames"] for r in rs)
        beh = [r["summary"]["behaviour_normalized_d4rl"] for r in rs if r["summary"] and r["summary"].get("behaviour_normalized_d4rl") is not None]
        rows.append(
            {
                "algo": key[0], "env": key[1], "dataset": key[2], "ablation": key[3], "seeds": len(rs), "frames": frames,
                "return_mean": float(finals.mean()), "return_std": float(finals.std()) if len(rs) > 1 else 0.0,
                "score_mean": float(sc.mean()) if sc.numel() else None,
                "score_std": float(sc.std()) if sc.numel() > 1 else 0.0,
                "behaviour_score": float(sum(beh) / len(beh)) if beh else None,
            }
        )
    header = "| algo | env | dataset | ablation | seeds | frames | return (mean ± std) | D4RL score (mean ± std) | behaviour score |"
    lines = [header, "|" + "---|" * 9]
    for r in rows:
        score = "n/a" if r["score_mean"] is None else f"{r['score_mean']:.1f} ± {r['score_std']:.1f}"
        beh = "n/a" if r["behaviour_score"] is None else f"{r['behaviour_score']:.1f}"
        lines.append(
            f"| {r['algo']} | {r['env']} | {r['dataset']} | {r['ablation']} | {r['seeds']} | {r['frames']} | "
            f"{r['return_mean']:.1f} ± {r['return_std']:.1f} | {score} | {beh} |"
        )
    table = "\n".join(lines)
    (out / "results.md").write_text(table + "\n")
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    plt = _plt()
    envs = sorted({k[1] for k in groups})
    fig, axes = plt.subplots(1, len(envs), figsize=(6 * len(envs), 4), squeeze=False)
    for ax, env_id in zip(axes[0], envs):
        for key, rs in sorted(groups.items()):
            if key[1] == env_id:
                label = f"{key[0]} {key[2]}" + ("" if key[3] == "-" else f" [{key[3]}]")
                plot_curve([r["evals"] for r in rs], None, label=label, title=env_id, ax=ax)
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=110)
    plt.close(fig)
    return table
