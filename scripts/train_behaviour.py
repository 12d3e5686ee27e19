"""Train a D4RL-style behaviour policy run (SAC or CrossQ) in a real Gymnasium env.

    python scripts/train_behaviour.py Hopper-v5 --steps 300000 --out outputs/behaviour/hopper
    python scripts/train_behaviour.py HalfCheetah-v5 --algorithm crossq --steps 1000000 --out outputs/behaviour/halfcheetah
    python scripts/train_behaviour.py HalfCheetah-v5 --steps 1000000 --device cuda --out outputs/behaviour/halfcheetah_gpu

Saves an actor snapshot and its evaluation at every ``--eval-every`` steps,
plus the state needed to continue: rerunning the same command after an
interruption (or with a larger ``--steps``) resumes the run.
``python -m torchrl_offhrl.data.policies ship`` ships the chosen snapshots.
"""
import argparse

import torch

from torchrl_offhrl.data.policies.actors import ALGORITHMS
from torchrl_offhrl.recipes.behaviour import train_behaviour

if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("env_id")
    p.add_argument("--algorithm", choices=sorted(ALGORITHMS), default="sac")
    p.add_argument("--steps", type=int, default=200_000)
    p.add_argument("--eval-every", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--critic-hidden", type=int, nargs="+", default=None, help="critic widths (default: the actor's 256 256; CrossQ's paper uses 2048 2048)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (2 gives about 1.3x the updates/s of 1 on a 2-core machine)")
    p.add_argument("--device", default=None, help="where the networks and the replay buffer live, e.g. cuda (default: cpu; the env steps on the CPU)")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    train_behaviour(a.env_id, a.out, algorithm=a.algorithm, total_steps=a.steps, eval_every=a.eval_every, seed=a.seed, critic_hidden=a.critic_hidden, device=a.device)
