"""Train a D4RL-style behaviour policy run (SAC) in a real Gymnasium env.

    python scripts/train_behaviour.py Hopper-v5 --steps 200000 --out outputs/behaviour/hopper

Saves an actor snapshot and its evaluation at every ``--eval-every`` steps;
``offhrl`` / ``torchrl_offhrl.data.policies`` ship the chosen snapshots.
"""
import argparse

import torch

from torchrl_offhrl.recipes.behaviour import train_behaviour_sac

if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("env_id")
    p.add_argument("--steps", type=int, default=200_000)
    p.add_argument("--eval-every", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", required=True)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    train_behaviour_sac(a.env_id, a.out, total_steps=a.steps, eval_every=a.eval_every, seed=a.seed)
