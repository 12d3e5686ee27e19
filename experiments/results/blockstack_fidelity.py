"""Block stacking: the datasets' per-goal success rates and how faithful the learned model env is to the real one.

    offhrl results blockstack-fidelity [--envs blockstack2 blockstack3] [--transitions 100000] [--episodes 240]
        [--config offline_train] [OVERRIDE ...]          # e.g. ensemble.fit.max_steps=10000

For each task it generates (or loads from the cache) the scripted ``medium`` and ``expert`` datasets of
``--transitions`` transitions and their concatenation ``medium-expert``, fits (or loads) the dynamics
ensemble of ``--config`` on ``medium-expert`` (transitions only, as the goal-conditioned P-MDP uses it),
then replays fresh episodes (a collection seed no dataset used, half medium and half expert, so the model
never saw them) open loop through every member: the recorded actions on the member's own predicted
states, as in the P-MDP. Writes ``docs/results/blockstack/fidelity.md`` (dataset table, per-goal success
agreement, error growth) and ``fidelity.png`` (position error per step).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

from .paths import ROOT  # noqa: E402  (the checkout the pages and runs live in)
OUT = ROOT / "docs" / "results" / "blockstack"
HOLDOUT_SEED = 7777  # no dataset is collected with it


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="offhrl results blockstack-fidelity", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", nargs="+", default=["blockstack2", "blockstack3"])
    p.add_argument("--transitions", type=int, default=100_000, help="per dataset part (medium-expert holds twice as many)")
    p.add_argument("--episodes", type=int, default=240, help="held-out episodes replayed per task")
    p.add_argument("--script-episodes", type=int, default=20, help="episodes per goal of the noiseless script at horizons 25 and 50")
    p.add_argument("--config", default="offline_train")
    p.add_argument("--out", default=str(OUT))
    p.add_argument("overrides", nargs="*")
    a = p.parse_args(argv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchrl_offhrl.data.stacking import SCRIPT_LEVELS, generate_stacking_dataset, scripted_success
    from torchrl_offhrl.registry import ENV_IDS
    from torchrl_offhrl.blockstack import goals as G
    from torchrl_offhrl.envs import calibrate_threshold
    from torchrl_offhrl.envs.goal_model import replay_open_loop
    from torchrl_offhrl.recipes.config import compose, model_config, resolve_dataset
    from torchrl_offhrl.recipes.pipeline import fit_or_load_models
    from torchrl_offhrl.utils import to_plain

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    data_rows, goal_rows, err_rows, curves, notes, script_rows = [], [], [], {}, [], []
    for env in a.envs:
        for horizon in (25, 50):  # the script without noise, each goal set at reset (UOF's test: success at any step)
            rates = scripted_success(ENV_IDS[env], episodes=a.script_episodes, horizon=horizon, seed=1)
            script_rows.append(f"| {env} | {horizon} | " + " / ".join(f"{v:.2f}" for v in rates.values()) + " |")
        datasets = {}
        for level in ("medium", "expert", "medium-expert"):
            cfg = to_plain(compose(a.config, [f"env={env}", f"dataset={level}", f"num_transitions={a.transitions}", *a.overrides]))
            datasets[level] = resolve_dataset(cfg)
        for level, ds in datasets.items():
            m = ds.metadata
            secs = m.get("collection_seconds")
            rate = len(ds) / secs if secs else None
            data_rows.append(f"| {env} | {level} | {len(ds):,} | " + " / ".join(f"{v:.2f}" for v in m["goal_success"].values())
                             + f" | {m['success_rate']:.2f} | " + (f"{secs / 60:.1f} min ({rate:.0f} transitions/s; 1M: {1e6 / rate / 60:.0f} min)" if rate else "-")
                             + " |")
        data = datasets["medium-expert"]
        t0 = time.time()
        ens, _, info = fit_or_load_models(model_config(cfg), data, with_cvae=False)
        hist = info.get("ensemble_history")
        fit_note = f"fitted in {time.time() - t0:.0f} s" if info["ensemble"] == "fitted" else f"loaded from {info['model_dir']}"
        notes.append(f"- {env}: ensemble {cfg['ensemble']['num_models']} x MLP{tuple(cfg['ensemble']['hidden_sizes'])}, fit "
                     f"{json.dumps(cfg['ensemble']['fit'])}, {fit_note}"
                     + (f", final validation loss (mean over members) {sum(hist[-1]['val_loss']) / len(hist[-1]['val_loss']):.4f} after {len(hist)} epochs"
                        if hist and hist[-1].get("val_loss") is not None else ""))
        threshold = calibrate_threshold(ens, data, "variance", quantile=0.99).threshold
        env_id = data.metadata["env_id"]
        per_part = a.episodes // 2 * 25
        held = [generate_stacking_dataset(env_id, lv, per_part, seed=HOLDOUT_SEED, progress=False) for lv in SCRIPT_LEVELS]
        episodes = torch.cat([h.data.reshape(-1, 25) for h in held], 0)
        n_blocks = int(data.metadata["n_blocks"])
        r = replay_open_loop(ens, episodes, n_blocks, threshold=threshold)
        K, E = r["model_success"].shape
        for k in range(G.n_goals(n_blocks)):
            sel = r["goal"] == k
            if not sel.any():
                continue
            real, model = r["real_success"][sel].float(), r["model_success"][:, sel].float()
            agree = (r["model_success"][:, sel] == r["real_success"][sel]).float().mean()
            cut = (r["cut_step"][:, sel] <= 25).float().mean()
            goal_rows.append(f"| {env} | {k} | {int(sel.sum())} | {real.mean():.2f} | {model.mean():.2f} | {agree:.2f} | {cut:.2f} |")
        steps = [1, 5, 10, 15, 20, 25]
        err_rows.append(f"| {env} | gripper | " + " | ".join(f"{100 * r['gripper_error'][s - 1]:.1f}" for s in steps) + " |")
        err_rows.append(f"| {env} | blocks | " + " | ".join(f"{100 * r['block_error'][s - 1]:.1f}" for s in steps) + " |")
        curves[env] = (r["gripper_error"], r["block_error"])
        cut_all = r["cut_step"] <= 25
        notes.append(f"- {env}: threshold {threshold:.4g} (0.99 quantile of the data's variance discrepancy); {E} held-out episodes x {K} members; "
                     f"{cut_all.float().mean():.0%} of the replayed paths would be cut by the pessimism within 25 steps"
                     + (f" (median step {r['cut_step'][cut_all].float().median():.0f})" if cut_all.any() else ""))
        print(f"{env}: done", flush=True)

    fig, axes = plt.subplots(1, len(curves), figsize=(5 * len(curves), 3.6), squeeze=False)
    for ax, (env, (ge, be)) in zip(axes[0], curves.items()):
        t = range(1, len(ge) + 1)
        ax.plot(t, 100 * ge, label="gripper")
        ax.plot(t, 100 * be, label="blocks (mean)")
        ax.set_title(f"{env}: open-loop replay")
        ax.set_xlabel("step")
        ax.set_ylabel("position error (cm)")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fidelity.png", dpi=110)
    md = ["# Block stacking: datasets and model-env fidelity", "",
          f"Made by `offhrl results blockstack-fidelity {' '.join(argv if argv is not None else sys.argv[1:])}`.", "",
          "## The scripted controller without noise", "",
          f"Fraction of {a.script_episodes} episodes per goal (goal set at reset, reset seeds 1000 onwards) reaching the goal at some step:", "",
          "| task | horizon | success per goal |", "|---|---|---|", *script_rows, "",
          "## Datasets (scripted controller, horizon 25)", "",
          "Per-goal success: the fraction of episodes with that goal whose high-level reward was 0 at some step. "
          "Levels: `expert` = the script with Gaussian noise 0.05 on its displacement; `medium` = 10% uniformly random actions "
          "and noise 0.1; `medium-expert` = both concatenated. Times on the 2-core machine with two training runs beside it.", "",
          "| task | level | transitions | success per goal | all | collection |", "|---|---|---|---|---|---|", *data_rows, "",
          "## Model fidelity: held-out episodes replayed open loop", "",
          "Each member starts at the episode's first state and gets the recorded actions on its own predictions. "
          "Success agreement: the member's path reaches the goal (by the task's functions on the predicted states) exactly when the "
          "real episode did. Cut: the members' disagreement on the path passes the P-MDP threshold within the 25 steps.", "",
          "| task | goal | episodes | real success | model success | agreement | cut by pessimism |", "|---|---|---|---|---|---|---|", *goal_rows, "",
          "Position error (cm) after a number of steps, mean over members and episodes:", "",
          "| task | object | 1 | 5 | 10 | 15 | 20 | 25 |", "|---|---|---|---|---|---|---|---|", *err_rows, "",
          "![error growth](fidelity.png)", "", *notes, ""]
    (out / "fidelity.md").write_text("\n".join(md))
    print("\n".join(md))
    return 0

