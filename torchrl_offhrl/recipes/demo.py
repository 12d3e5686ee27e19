"""The embedded demo: the whole pipeline on Hopper-v5, offline, in minutes on a CPU.

1. collect a small dataset with the shipped ``hopper-medium`` behaviour policy
   (cached: a second run reuses it);
2. fit the dynamics ensemble and the CVAE (cached);
3. train MOC on ``TransformedEnv(PessimisticModelEnv, LatentActionTransform)``
   for a short budget, evaluating in the real env through the decoder;
4. print a summary table and where the plots are.

Hyper-parameters: ``configs/demo.yaml`` (the offline-training config with
smaller budgets).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

__all__ = ["run_demo"]


def run_demo(overrides: list[str] | None = None, progress: bool = True) -> dict:
    """Run the demo with optional hydra ``overrides``; returns the training summary plus timings."""
    from ..cli import compose
    from ..scores import normalized_score
    from .pipeline import _plain
    from .train import resolve_dataset, train

    cfg = _plain(compose("demo", list(overrides or [])))
    t0 = time.time()
    data = resolve_dataset(cfg["dataset"], cfg["env"]["name"], cfg["env"]["env_id"], cfg.get("num_transitions"), cfg["seed"])
    t_data = time.time() - t0
    summary = train(cfg, progress=progress)
    total = time.time() - t0
    env_id = summary["env_id"]
    beh = data.episode_returns()
    final = summary["final"]
    policy_name = str(data.metadata.get("policy", "?"))
    ref = (data.metadata.get("ref_min_return"), data.metadata.get("ref_max_return"))
    rows = [
        ("behaviour data (" + policy_name + ")", float(beh.mean()), float(beh.std()), int(beh.numel())),
        (f"MOC agent, real {env_id}", final["return_mean"], final["return_std"], int(cfg["eval"]["episodes"])),
    ]
    lines = [
        "",
        "=" * 78,
        f"torchrl_offhrl demo: offline MOC on {env_id} from {len(data):,} transitions of medium data",
        "=" * 78,
        f"{'':34s} {'return':>9s} {'± std':>8s} {'episodes':>9s} {'D4RL score':>11s} {'data score':>11s}",
    ]
    for name, m, s, n in rows:
        d4rl = normalized_score(env_id, m)
        own = normalized_score(env_id, m, ref=ref) if None not in ref else None
        lines.append(f"{name:34s} {m:9.1f} {s:8.1f} {n:9d} {d4rl:11.1f} {('n/a' if own is None else f'{own:.1f}'):>11s}")
    model_s = summary["total_s"] - summary["update_time_s"]
    lines += [
        "",
        f"time: {total / 60:.1f} min in total (data {t_data:.0f} s; models, env calibration, collection and evaluation "
        f"{model_s:.0f} s; MOC updates {summary['update_time_s']:.0f} s for {summary['frames']:,} model frames)",
        f"plots: {summary['run_dir']}/learning_curve.png, {summary['run_dir']}/option_usage.png; logs: {summary['run_dir']}/logs",
        "",
        "This is a short-budget run (100k transitions, small models, 160k MOC frames) to show the pipeline end to end;",
        "its score is not the paper's. The full-budget command (1M transitions, paper-size models, 1M frames):",
        "    offhrl train algo=moc env=hopper dataset=medium",
    ]
    print("\n".join(lines))
    out = {**summary, "demo_total_s": total, "data_s": t_data}
    (Path(summary["run_dir"]) / "demo_summary.json").write_text(json.dumps(out, indent=2, default=str))
    return out
