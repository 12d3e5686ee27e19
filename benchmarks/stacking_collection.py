"""Block-stacking data collection: transitions/s of the scripted stacker, side by side.

    python benchmarks/stacking_collection.py [--transitions 4000] [--num-envs 8] [--env BlockStack2-v0]

Three ways of stepping the same envs with the same controller (``ScriptedStacker``, medium noise), one torch thread:

* ``mujoco only``: the physics alone (``mj_step`` of the 20 sub-steps of one env step, no observation): the bound;
* ``gymnasium vector env``: ``collect_stacking`` as shipped (Gymnasium's synchronous vector env, every
  episode of a round reset together, the goal fields recorded);
* ``torchrl SerialEnv``: the same loop through TorchRL's batched ``GymEnv`` (``make_blockstack_env``,
  what training and evaluation use) with a TensorDict per step.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--transitions", type=int, default=4000)
    p.add_argument("--num-envs", type=int, default=8)
    p.add_argument("--env", default="BlockStack2-v0")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    import gymnasium as gym

    from torchrl_offhrl.blockstack import goals as G, make_blockstack_env
    from torchrl_offhrl.registry import task_of
    from torchrl_offhrl.data.stacking import SCRIPT_LEVELS, ScriptedStacker, collect_stacking

    n_blocks = task_of(a.env).n_blocks
    rows = []

    env = gym.make(a.env).unwrapped
    env.reset(seed=0)
    steps = a.transitions // 4
    t = time.perf_counter()
    for _ in range(steps):
        env._mujoco_step(np.zeros(4))
    rows.append(("mujoco only (one env)", steps / (time.perf_counter() - t)))

    t = time.perf_counter()
    ds = collect_stacking(a.env, a.transitions, *SCRIPT_LEVELS["medium"], num_envs=a.num_envs, seed=0, progress=False)
    rows.append((f"gymnasium vector env ({a.num_envs} envs, as shipped)", len(ds) / (time.perf_counter() - t)))

    benv = make_blockstack_env(a.env, num_envs=a.num_envs)
    ctrl = ScriptedStacker(n_blocks, *SCRIPT_LEVELS["medium"], generator=torch.Generator().manual_seed(0))
    t = time.perf_counter()
    done = 0
    td = benv.reset()
    option = G.first_option(td["desired_goal"].argmax(-1))
    while done < a.transitions:
        td["action"] = ctrl(td["observation"], option)
        td, nxt = benv.step_and_maybe_reset(td)
        option = torch.where(td["next", "done"].squeeze(-1), G.first_option(nxt["desired_goal"].argmax(-1)),
                             G.next_option(option, td["desired_goal"].argmax(-1), td["next", "achieved_goal"]))
        td = nxt
        done += a.num_envs
    rows.append((f"torchrl SerialEnv ({a.num_envs} envs)", done / (time.perf_counter() - t)))

    base = rows[1][1]
    print(f"{a.env}, {a.transitions} transitions, 1 torch thread")
    print("| path | transitions/s | 1M transitions take | vs shipped |")
    print("|---|---|---|---|")
    for name, rate in rows:
        print(f"| {name} | {rate:,.0f} | {1e6 / rate / 60:.0f} min | {rate / base:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
