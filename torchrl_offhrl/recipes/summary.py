"""One run's result: its ``summary.json`` (:func:`run_summary`) and the paragraph ``offhrl train`` prints (:func:`format_summary`).

Multi-seed tables of many runs are :mod:`~torchrl_offhrl.recipes.report`'s.
"""
from __future__ import annotations

from pathlib import Path

from ..scores import normalized_score
from .config import data_label  # noqa: F401  (re-exported: the summary's name for the data)
from .runs import record_step

__all__ = ["data_label", "fmt_number", "format_summary", "run_summary"]


def fmt_number(x, spec: str = ".1f") -> str:
    """``x`` formatted with ``spec``, or ``"n/a"`` for None."""
    return "n/a" if x is None else format(x, spec)


def format_summary(summary) -> str:
    """The one-paragraph result of a run, as printed by ``offhrl train`` and ``examples/offline_train.py``."""
    f = summary["final"]
    t = summary.get("transfer")
    if t:
        off = summary.get("offline_final")
        before = "" if off is None else (f"offline on the forward task: return {off['return_mean']:.1f} "
                                         f"(D4RL-normalised {fmt_number(off['normalized_d4rl'])}); ")
        return (f"{summary['algo']} on {summary['env_id']} ({summary['dataset']}), transfer to the {t['task']} task "
                f"({'from scratch' if t['from_scratch'] else 'decoder ' + ('kept' if t['decoder'] == 'keep' else 'discarded')}): {before}"
                f"after {summary['frames'] - t['switch_frame']} online frames on the {t['task']} task: return {f['return_mean']:.1f} ± "
                f"{f['return_std']:.1f}; outputs in {summary['run_dir']}")
    text = (
        f"{summary['algo']} on {summary['env_id']} ({data_label(summary)}), {summary.get('step', summary['frames'])} {summary.get('unit', 'frames')}: "
        f"real return {f['return_mean']:.1f} ± {f['return_std']:.1f}, D4RL-normalised {fmt_number(f['normalized_d4rl'])} "
        f"(behaviour data: {fmt_number(summary['behaviour_normalized_d4rl'])}); outputs in {summary['run_dir']}"
    )
    sel, guard = summary.get("selected"), summary.get("guard")
    if guard is not None and guard.get("fired") is None:
        text += f"\nguard: off ({guard['reason']})"
    elif guard is not None:
        fired = {"bc": "FIRED, the percentile BC is returned"}.get(guard.get("returned"), "FIRED, the start policy is returned")
        text += f"\nguard: {fired if guard['fired'] else 'passed, the trained policy is returned'} ({guard['reason']})"
    fb = summary.get("fallback")
    if fb is not None:
        text += (f"\npercentile BC of the data's best episodes (the guard's other fallback): real return {fb['return_mean']:.1f}, "
                 f"D4RL-normalised {fmt_number(fb.get('normalized_d4rl'))}")
    if sel is not None and (sel.get("step", sel.get("frames")) != summary.get("step", summary["frames"]) or guard is not None):
        what = "the percentile BC" if sel.get("policy") == "percentile_bc" else f"{sel.get('frames', sel.get('step'))} {summary.get('unit', 'frames')}"
        text += (f"\nreturned policy: {what} (selection.criterion={sel['criterion']}), "
                 f"real return {sel['return_mean']:.1f}, D4RL-normalised {fmt_number(sel.get('normalized_d4rl'))} "
                 "(the real-env score is reported, never used to choose)")
    return text


def run_summary(cfg, data, behaviour: dict, records: list[dict], *, ref, pessimism, threshold, frames: int, updates: int,
                frames_per_s, updates_per_s, timing: dict, models, run_dir, evaluation_files=(), unit: str = "frames") -> dict:
    """The ``summary.json`` of a training run: the final (and initial) evaluation, the behaviour data's score, sizes and timings."""
    env_id, level = cfg["env"]["env_id"], data.metadata.get("level")
    return {
        "algo": cfg["algo"]["name"],
        "env_id": env_id,
        "dataset": str(cfg["dataset"]),
        "level": level,
        "seed": cfg["seed"],
        "ablation": cfg.get("ablation", {}),
        "pessimism": pessimism,
        "threshold": threshold,
        "frames": frames,
        "updates": updates,
        "unit": unit,
        "step": updates if unit == "updates" else frames,
        "final": records[-1],
        "initial": records[0] if record_step(records[0]) == 0 else None,
        "behaviour_return_mean": behaviour["mean"],
        "behaviour_return_std": behaviour["std"],
        "behaviour_episodes": behaviour["episodes"],
        "behaviour_normalized_d4rl": normalized_score(env_id, behaviour["mean"]),
        "behaviour_normalized_dataset": normalized_score(env_id, behaviour["mean"], ref=ref) if ref else None,
        "dataset_transitions": len(data),
        "dataset_policy": str(data.metadata.get("policy", "?")),
        "dataset_level": level,
        "frames_per_s": frames_per_s,
        "updates_per_s": updates_per_s,
        **{k: round(v, 1) for k, v in timing.items()},
        "models": models,
        "run_dir": str(run_dir),
        "plots": [str(Path(run_dir) / "learning_curve.png")] + [str(Path(run_dir) / f) for f in evaluation_files if f.endswith(".png")],
    }
