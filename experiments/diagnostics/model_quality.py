"""Held-out one-step quality of fitted ensembles: are the members wrong together (bias) or apart (disagreement)?

    python experiments/diagnostics/model_quality.py MODEL_DIR [MODEL_DIR ...] [--env hopper] [--transitions 20000] [--seed 99]

Generates fresh ``medium`` transitions in the real env with a seed no dataset used (held out from every fit; a
simulator is fine here, this is a question asked while building the library), then prints for each ensemble
:func:`torchrl_offhrl.models.ensemble_quality`: the error of the members' mean next-state prediction in units of the
data's state-change std, the members' spread in the same units, and the reward's. A run's calibration report prints
the same numbers on the held-out episodes of its own data. Issue 13 used it to compare the demo-size models (100k
transitions, 256x256, lr 1e-3) with the paper-size ones (1M, 512x512, lr 1e-4).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model_dirs", nargs="+")
    p.add_argument("--env", default="hopper")
    p.add_argument("--transitions", type=int, default=20000)
    p.add_argument("--seed", type=int, default=99)
    a = p.parse_args(argv)
    from torchrl_offhrl.data import generate_dataset
    from torchrl_offhrl.models import DynamicsEnsemble, ensemble_quality

    data = generate_dataset(a.env, "medium", num_transitions=a.transitions, seed=a.seed, progress=False)
    print("| models | state error (data-std units) | members' spread | error / spread | reward error (abs) | reward spread |")
    print("|---|---|---|---|---|---|")
    for d in a.model_dirs:
        q = ensemble_quality(DynamicsEnsemble.load(Path(d) / "ensemble.pt"), data)
        reward = "| n/a | n/a |" if q["reward_error"] is None else f"| {q['reward_error']:.4f} | {q['reward_spread']:.4f} |"
        print(f"| {d} | {q['state_error']:.4f} | {q['state_spread']:.4f} | {q['error_over_spread']:.1f} {reward}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
