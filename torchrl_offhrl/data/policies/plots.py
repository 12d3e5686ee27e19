"""The learning curve of a behaviour-policy run (``scripts/train_behaviour.py --out RUN``): ``curve.png``.

``python -m torchrl_offhrl.data.policies plot RUN`` redraws it.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from ...scores import d4rl_reference, normalized_score, return_for_score
from ...utils import atomic_write

__all__ = ["BEHAVIOUR_LEVELS", "behaviour_figure", "plot_behaviour_run"]

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
