"""Command line of the shipped behaviour policies.

    python -m torchrl_offhrl.data.policies list
    python -m torchrl_offhrl.data.policies plot outputs/behaviour/hopper
    python -m torchrl_offhrl.data.policies ship outputs/behaviour/hopper hopper-expert --level expert
    python -m torchrl_offhrl.data.policies ship outputs/behaviour/hopper hopper-medium --level medium --fraction 0.33
"""
from __future__ import annotations

import argparse
import json
import sys


def main(argv: list[str] | None = None) -> int:
    """Run the ``list`` or ``ship`` sub-command; returns the exit status."""
    from . import POLICY_DIR, SHIP_EVAL_SEED, list_policies, ship_policy

    p = argparse.ArgumentParser(prog="python -m torchrl_offhrl.data.policies", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="the shipped policies and their evaluated returns")
    c = sub.add_parser("plot", help="draw a behaviour run's learning curve (run_dir/curve.png), with the D4RL level lines")
    c.add_argument("run_dir", help="--out folder of scripts/train_behaviour.py")
    c.add_argument("--path", default=None, help="where to write the PNG (default run_dir/curve.png)")
    s = sub.add_parser("ship", help="re-evaluate a checkpoint of a behaviour run and ship it")
    s.add_argument("run_dir", help="--out folder of scripts/train_behaviour.py")
    s.add_argument("name", help="policy name, e.g. hopper-medium")
    s.add_argument("--level", required=True, choices=["medium", "expert"])
    pick = s.add_mutually_exclusive_group()
    pick.add_argument("--steps", type=int, help="the checkpoint of exactly this many env steps")
    pick.add_argument("--target", type=float, help="the checkpoint whose return is closest to this")
    pick.add_argument("--fraction", type=float,
                      help="the checkpoint closest to this fraction of the best return (medium: 0.33)")
    s.add_argument("--episodes", type=int, default=10)
    s.add_argument("--seed", type=int, default=SHIP_EVAL_SEED)
    s.add_argument("--dest", default=None, help=f"output folder (default {POLICY_DIR})")
    s.add_argument("--max-steps", type=int, default=1000,
                   help="step limit of the evaluation episodes (1000; smaller only for quick checks)")
    s.add_argument("--note", help="free text stored in the card (e.g. how the run was resumed)")
    a = p.parse_args(argv)

    if a.cmd == "list":
        for name in list_policies():
            card = json.loads((POLICY_DIR / f"{name}.json").read_text())
            ev = card.get("eval", {})
            print(f"{name:24s} {card.get('env_id', '?'):16s} steps={card.get('train_steps')} "
                  f"stochastic={ev.get('stochastic', {}).get('mean', float('nan')):.1f} "
                  f"normalized={ev.get('normalized_d4rl')}")
        return 0
    if a.cmd == "plot":
        from .plots import plot_behaviour_run

        try:
            print(plot_behaviour_run(a.run_dir, a.path))
        except (FileNotFoundError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
        return 0
    target = a.target
    if a.fraction is not None:
        from pathlib import Path

        records = json.loads((Path(a.run_dir) / "evals.json").read_text())["evals"]
        target = a.fraction * max(r["stochastic"]["mean"] for r in records)
    ship_policy(a.run_dir, a.name, a.level, steps=a.steps, target=target, episodes=a.episodes,
                seed=a.seed, dest=a.dest, progress=True, max_steps=a.max_steps, note=a.note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
