"""Learning-curve plots of runs: mean ± std bands over seeds, per-goal success, the transfer setting's two phases, training metrics."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from .runs import read_scalar_logs, record_step

__all__ = ["UNIT_LABELS", "plot_curve", "plot_goal_success", "plot_training_metrics", "plot_transfer", "pyplot"]


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: how the x-axis of a run's curves is labelled, by the unit of its budget (``summary["unit"]``)
UNIT_LABELS = {"frames": "model-env frames", "updates": "gradient steps on the dataset",
               "transfer": "frames (model env offline, then real env online)"}


def _curve_stats(runs: Sequence[Sequence[dict]], key: str):
    """Mean and std over runs at the evaluation points every run has."""
    common = sorted(set.intersection(*[{record_step(r) for r in recs} for recs in runs])) if runs else []
    if not common:
        return [], torch.zeros(0), torch.zeros(0)
    vals = torch.tensor([[next(r[key] for r in recs if record_step(r) == f) for f in common] for recs in runs], dtype=torch.float64)
    std = vals.std(0) if vals.shape[0] > 1 else torch.zeros(vals.shape[1], dtype=torch.float64)
    return common, vals.mean(0), std


def _band(ax, runs: Sequence[Sequence[dict]], key: str, label: str | None, x_offset: int = 0, color=None):
    """Plot the mean over runs, shaded ± one std (one run: ± the std over its evaluation episodes); returns ``(steps, colour)``."""
    steps, mean, std = _curve_stats(runs, key)
    if len(runs) == 1 and key == "return_mean":
        std = torch.tensor([r.get("return_std", 0.0) for r in runs[0] if record_step(r) in steps], dtype=torch.float64)
    x = [f + x_offset for f in steps]
    line, = ax.plot(x, mean, marker="o", ms=3, color=color, label=label)
    ax.fill_between(x, mean - std, mean + std, alpha=0.25, color=line.get_color())
    return steps, line.get_color()


def _finish(ax, path, own: bool, xlabel: str, ylabel: str, title: str):
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    if own:
        plt = pyplot()
        ax.figure.tight_layout()
        ax.figure.savefig(path, dpi=110)
        plt.close(ax.figure)
    return path


def plot_curve(runs: Sequence[Sequence[dict]], path, label: str = "", title: str = "", behaviour: float | None = None, key: str = "return_mean", ax=None,
               xlabel: str = UNIT_LABELS["frames"]):
    """Learning curve(s): the mean over runs, shaded ± one std over runs.

    With a single run, the band is the std over its evaluation episodes.
    """
    own = ax is None
    if own:
        _, ax = pyplot().subplots(figsize=(6, 4))
    _band(ax, runs, key, f"{label} (n={len(runs)})" if label else None)
    if behaviour is not None:
        ax.axhline(behaviour, color="gray", ls="--", label="behaviour (dataset)")
    return _finish(ax, path, own, xlabel, "real-env return" if key == "return_mean" else key, title)


def plot_goal_success(runs: Sequence[Sequence[dict]], path, label: str = "", title: str = "", xlabel: str = UNIT_LABELS["frames"], axes=None,
                      key: str = "success_per_goal"):
    """Per-goal success curves of goal-conditioned runs (the paper's Fig. 4): one panel per goal, mean over runs, shaded ± one std.

    ``key`` is the records' per-goal list (``success_per_goal``: horizon 25;
    ``success_per_goal_h50``: horizon 50). Pass ``axes`` (one per goal) to
    draw several algorithms on the same panels; the figure is then saved by
    the caller (``path`` is ignored).
    """
    runs = [[r for r in recs if key in r] for recs in runs]
    if not runs or not all(runs):
        return None
    n = len(runs[0][0][key])
    own = axes is None
    if own:
        fig, axes = pyplot().subplots(1, n, figsize=(3.2 * n, 3.2), sharey=True, squeeze=False)
        axes = axes[0]
    for k, ax in enumerate(axes):
        per_goal = [[{**r, "_success": r[key][k]} for r in recs] for recs in runs]
        _band(ax, per_goal, "_success", f"{label} (n={len(runs)})" if label and k == 0 else None)
        ax.set_title(f"goal {k}", fontsize=9)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel(xlabel, fontsize=8)
    axes[0].set_ylabel("success rate")
    if own:
        axes[0].legend(loc="best", fontsize=8)
        fig = axes[0].figure
        fig.suptitle(title, fontsize=9)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        pyplot().close(fig)
    return path


def plot_transfer(runs: Sequence[Sequence[dict]], path, label: str = "", title: str = "", key: str = "return_mean", ax=None, x_offset: int = 0,
                  xlabel: str = UNIT_LABELS["transfer"]):
    """Learning curves of transfer runs: the offline phase (old task) then the online phase (new task), one x-axis of frames.

    Each phase is drawn as its own segment (mean over runs, shaded ± one std;
    one run: ± the std over its evaluation episodes), in one colour, so the
    drop at the switch shows: both tasks are evaluated there. A dotted line
    marks the switch. ``x_offset`` shifts runs without an offline phase
    (trained from scratch) to start at another run's switch.
    """
    own = ax is None
    if own:
        _, ax = pyplot().subplots(figsize=(6, 4))
    color, switch = None, None
    for phase in ("offline", "online"):
        recs = [[r for r in rs if r.get("phase") == phase] for rs in runs]
        if not recs or not all(recs):
            continue
        first = color is None
        steps, color = _band(ax, recs, key, (f"{label} (n={len(runs)})" if label else None) if first else None, x_offset, color)
        if phase == "online" and steps and x_offset == 0:
            switch = steps[0]
    if switch:
        ax.axvline(switch, color="k", ls=":", lw=1)
    return _finish(ax, path, own, xlabel, "real-env return on the current task" if key == "return_mean" else key, title)


def plot_training_metrics(log_dir, path, keys: Sequence[str] | None = None, xlabel: str = "frames"):
    """One panel per logged scalar of a run's CSV logs (``logs/scalars/{train,eval}/*.csv``), against the run's steps (``xlabel``).

    Shows whether options are alive (termination rate, option duration, pi_O
    and usage entropies, the termination advantage), whether the model is
    exploited (``penalized_rate``, the model return next to the real one) and
    the losses. ``keys`` picks panels by name (default: every file). Returns
    the path, or None when there are no CSV logs (another logger backend).
    A figure is a convenience: a failure to draw it warns and returns None.
    """
    import warnings

    series = read_scalar_logs(log_dir, keys)
    if not series:
        return None
    try:
        plt = pyplot()
        evals = {k: v for k, v in series.items() if k.startswith("eval/") and "return_mean" in k}
        panels = ([("eval/returns", evals)] if evals else []) + [(k, {k: v}) for k, v in series.items() if k not in evals]
        cols = 4
        rows_n = -(-len(panels) // cols)
        fig, axes = plt.subplots(rows_n, cols, figsize=(4 * cols, 2.6 * rows_n), squeeze=False)
        for ax, (title, group) in zip(axes.flat, panels):
            for name, (x, y) in group.items():
                ax.plot(x, y, lw=1, label=name.split("/", 1)[1])
            ax.set_title(title, fontsize=9)
            ax.tick_params(labelsize=7)
            if len(group) > 1:
                ax.legend(fontsize=7)
        for ax in list(axes.flat)[len(panels):]:
            ax.axis("off")
        fig.supxlabel(xlabel, fontsize=9)
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
    except Exception as err:  # noqa: BLE001
        warnings.warn(f"could not draw {path}: {err!r}", stacklevel=2)
        return None
    return Path(path)
