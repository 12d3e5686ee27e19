"""Where do a policy's real and model episodes part? Each kept policy rolled out in the real env and in each member alone.

    python experiments/diagnostics/paired_rollouts.py RUN_DIR [--steps 1000] [--episodes 5]

For every ``snapshot-<frames>.pt`` of a run, ``--episodes`` real ``Hopper-v5``
episodes (start-state seeds 100, 101, ...) are run with the deterministic
policy (a fresh option pick at each state, as ``fqe_probe.policy_actions``
decodes), and from each episode's real start state every ensemble member
rolls the same policy out alone, for ``--steps`` steps, with the env's own
termination (no pessimism). Printed per policy: the run's recorded real
score, then the real and the model's return, episode length and mean forward
velocity (observation 5). Used for row 21 of
``docs/results/demo_robustness_notes.md``.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from torchrl_offhrl.envs.tasks import hopper_termination
from torchrl_offhrl.recipes.config import model_config, resolve_dataset
from torchrl_offhrl.recipes.evaluation import load_run_agent
from torchrl_offhrl.recipes.pipeline import fit_or_load_models
from torchrl_offhrl.utils import load_torch_file

from fqe_probe import policy_actions


def paired(run: Path, steps: int, episodes: int) -> list[dict]:
    cfg, env, agent, _, cvae = load_run_agent(run, num_envs=1)
    env.close()
    data = resolve_dataset(cfg)
    ens, _, _ = fit_or_load_models(model_config(cfg), data, progress=False)
    bound = cfg.get("model_env", {}).get("latent_bound", 2.0)
    recs = {int(r["frames"]): r for r in json.loads((run / "evals.json").read_text())}
    k = ens.num_members
    own = torch.arange(k)
    rows = []
    for p in sorted(run.glob("snapshot-*.pt"), key=lambda p: int(re.findall(r"\d+", p.name)[-1])):
        frames = int(re.findall(r"\d+", p.name)[-1])
        agent.load_state_dict(load_torch_file(p, "snapshot", "")["agent"])
        real_env = gym.make(cfg["env"]["env_id"])
        per_episode = []
        for ep in range(episodes):
            o, _ = real_env.reset(seed=100 + ep)
            start = torch.as_tensor(o, dtype=torch.float32)
            ret, length, vel = 0.0, steps, []
            for t in range(steps):
                a = policy_actions(agent, cvae, bound, torch.as_tensor(o, dtype=torch.float32)[None])[0].numpy()
                o, r, term, _, _ = real_env.step(a)
                ret += r
                vel.append(o[5])
                if term:
                    length = t + 1
                    break
            s = start[None].repeat(k, 1)
            alive = torch.ones(k, dtype=torch.bool)
            m_ret, m_len, m_vel = torch.zeros(k), torch.full((k,), steps), torch.zeros(k)
            for t in range(steps):
                with torch.no_grad():
                    pred = ens.predict(s, policy_actions(agent, cvae, bound, s))
                s = s + pred["delta"][own, own] * ens.delta_std + ens.delta_mean  # member i's own prediction for rollout i
                m_ret += pred["reward"][own, own].reshape(-1) * alive
                m_vel += s[:, 5] * alive
                dead = hopper_termination(s).reshape(-1) & alive
                m_len[dead] = t + 1
                alive &= ~dead
            per_episode.append((ret, length, float(np.mean(vel)), float(m_ret.mean()), float(m_len.float().mean()),
                                float((m_vel / m_len).mean())))
        real_env.close()
        m = np.mean(per_episode, axis=0)
        rows.append({"frames": frames, "recorded": recs[frames]["normalized_d4rl"], "real_return": m[0], "real_len": m[1], "real_vel": m[2],
                     "model_return": m[3], "model_len": m[4], "model_vel": m[5]})
        r = rows[-1]
        print(f"{run.name} {frames:6d} recorded {r['recorded']:5.1f} | real: return {r['real_return']:7.1f} length {r['real_len']:6.1f} "
              f"velocity {r['real_vel']:.2f} | members alone: return {r['model_return']:7.1f} length {r['model_len']:6.1f} "
              f"velocity {r['model_vel']:.2f}", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--episodes", type=int, default=5)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    paired(a.run, a.steps, a.episodes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
