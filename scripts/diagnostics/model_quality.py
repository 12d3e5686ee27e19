"""Held-out one-step quality of fitted ensembles: are the members wrong together (bias) or apart (disagreement)?

    python scripts/diagnostics/model_quality.py MODEL_DIR [MODEL_DIR ...] [--env hopper] [--transitions 20000] [--seed 99]

Generates fresh ``medium`` transitions with a seed no dataset used (held out from every fit), then per
ensemble: the error of the members' mean next-state prediction and of their reward prediction, in units
of the data's std (normalised residuals), and the members' disagreement (the std across members), so a
reader sees whether the ensemble's uncertainty covers its error. Issue 13 uses it to compare the
demo-size models (100k transitions, 256x256, lr 1e-3) with the paper-size ones (1M, 512x512, lr 1e-4).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model_dirs", nargs="+")
    p.add_argument("--env", default="hopper")
    p.add_argument("--transitions", type=int, default=20000)
    p.add_argument("--seed", type=int, default=99)
    a = p.parse_args(argv)
    from torchrl_offhrl.data import generate_dataset
    from torchrl_offhrl.models import DynamicsEnsemble

    data = generate_dataset(a.env, "medium", num_transitions=a.transitions, seed=a.seed, progress=False)
    td = data.data
    obs, act = td["observation"], td["action"]
    nxt, rew = td["next", "observation"], td["next", "reward"].reshape(-1)
    print("| models | obs error (mean abs, data-std units) | obs disagreement (member std) | error / disagreement | reward error (abs) | reward member std |")
    print("|---|---|---|---|---|---|")
    for d in a.model_dirs:
        ens = DynamicsEnsemble.load(Path(d) / "ensemble.pt")
        with torch.no_grad():
            out = ens.predict(obs, act)
        scale = ens.delta_std.reshape(-1)
        err = ((out["next_observation"].mean(0) - nxt) / scale).abs().mean()
        dis = (out["next_observation"] / scale).std(0).mean()
        r = out["reward"]
        rerr = (r.mean(0) - rew).abs().mean() if r is not None else float("nan")
        rstd = r.std(0).mean() if r is not None else float("nan")
        print(f"| {d} | {err:.4f} | {dis:.4f} | {err / dis:.1f} | {float(rerr):.4f} | {float(rstd):.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
