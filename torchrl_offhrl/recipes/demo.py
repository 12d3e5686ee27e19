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
from pathlib import Path

from ..utils import to_plain
from .config import compose
from .report import fmt_number
from .train import train

__all__ = ["run_demo"]


def run_demo(overrides: list[str] | None = None, progress: bool = True) -> dict:
    """Run the demo with optional hydra ``overrides``; returns the training summary plus the printed table."""
    cfg = to_plain(compose("demo", list(overrides or []), "demo"))
    s = train(cfg, progress=progress)
    final, algo = s["final"], s["algo"].upper()
    rows = [
        (f"behaviour data ({s['dataset_policy']})", s["behaviour_return_mean"], s["behaviour_return_std"], s["behaviour_episodes"],
         s["behaviour_normalized_d4rl"], s["behaviour_normalized_dataset"]),
        (f"{algo} agent, real {s['env_id']}", final["return_mean"], final["return_std"], int(cfg["eval"]["episodes"]),
         final["normalized_d4rl"], final["normalized_dataset"]),
    ]
    first = s.get("initial")
    if first is not None:  # the untrained agent: with the CVAE, about the decoder's mean action
        rows.insert(1, (f"{algo} agent before training", first["return_mean"], first["return_std"], int(cfg["eval"]["episodes"]),
                        first["normalized_d4rl"], first["normalized_dataset"]))
    lines = [
        "",
        "=" * 80,
        f"torchrl_offhrl demo: offline {algo} on {s['env_id']} from {s['dataset_transitions']:,} transitions of "
        f"{s['dataset_level'] or s['dataset']} data",
        "=" * 80,
        f"{'':36s} {'return':>9s} {'± std':>8s} {'episodes':>9s} {'D4RL score':>11s} {'data score':>11s}",
    ]
    for name, m, sd, n, d4rl, own in rows:
        lines.append(f"{name:36s} {m:9.1f} {sd:8.1f} {n:9d} {fmt_number(d4rl):>11s} {fmt_number(own):>11s}")
    other = s["total_s"] - s["data_s"] - s["models_s"] - s["update_time_s"]
    lines += [
        "(data score: normalised with the dataset's own random/expert reference returns; n/a without an expert policy;",
        " before training, the agent's mean latent action is about the CVAE decoder's mean action: behaviour cloning)",
        "",
        f"time: {s['total_s'] / 60:.1f} min in total: data {s['data_s']:.0f} s, ensemble + CVAE {s['models_s']:.0f} s, "
        f"{algo} updates {s['update_time_s']:.0f} s for {s['frames']:,} model frames, env calibration + collection + "
        f"real-env evaluation {other:.0f} s",
        f"plots: {', '.join(s['plots'])}; logs: {s['run_dir']}/logs",
        "",
        f"This is a short-budget run ({s['dataset_transitions']:,} transitions, small models fitted for "
        f"{cfg['ensemble']['fit']['max_steps']} steps, {s['frames']:,} {algo} frames) that shows the pipeline end to end;",
        "its score is not a full-scale result. The full-scale command (1M transitions, paper-size models; the results in",
        "docs/results/full/ ran 205k frames with minibatches of 256, the default is 1M frames):",
        f"    offhrl train algo={s['algo']} env={cfg['env']['name']} dataset={cfg['dataset']} train.total_frames=204800 algo.minibatch_size=256",
    ]
    text = "\n".join(lines)
    print(text)
    out = {**s, "table": text}
    (Path(s["run_dir"]) / "demo_summary.json").write_text(json.dumps(out, indent=2, default=str))
    return out
