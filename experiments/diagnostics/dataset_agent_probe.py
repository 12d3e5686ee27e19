"""Where does a dataset agent's final policy take the real env, and what does its critic think of it?

    python experiments/diagnostics/dataset_agent_probe.py RUN_DIR [--episodes 5] [--seed 12345] [--data-states 5000]
    python experiments/diagnostics/dataset_agent_probe.py outputs/results/full/td3bc-halfcheetah-medium-expert-seed4

For a run of IQL, CQL, TD3+BC or BC (`offhrl train algo=iql|cql|td3bc|bc`):
rolls its checkpointed policy out deterministically (as the evaluations do)
and prints, per episode, the return, the first critic's Q(s, pi(s)) over
the first 5 steps and over the last half of the episode, and the fraction of
visited states with a coordinate outside the data's 0.5-99.5% range (the
data's own states: printed beside, for reference). Then the same Q on
``--data-states`` states drawn from each part of the run's dataset
(medium-expert: the medium and the expert part). A critic that ranks the
states a failing episode ends in above the data's has been exploited; one
that ranks them below has not, and the actor went there anyway. BC has no
critic: only returns and the out-of-data fractions.

Written for the medium-expert runs of issue 15 (2026-11-27): TD3+BC on
halfcheetah-medium-expert, seed 4, stands still nose-up from 4 of 5 start
states (returns -91, 8,540, -41, -31, 74), where its critic gives 346
against 526 on medium and 958 on expert data states.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from torchrl_offhrl.recipes.config import resolve_dataset
from torchrl_offhrl.recipes.evaluation import load_run_agent
from torchrl_offhrl.rollouts import evaluate_policy, first_episode_mask


def first_critic(agent):
    """``obs -> Q(obs, pi(obs))`` with the loss's first Q network, or None for an agent without one (BC)."""
    loss = getattr(agent, "loss", None)
    if loss is None or not hasattr(loss, "qvalue_network"):
        return None
    params = loss.qvalue_network_params[0]

    @torch.no_grad()
    def q(obs: torch.Tensor) -> torch.Tensor:
        td = agent.policy(TensorDict({"observation": obs}, batch_size=obs.shape[:1]))
        with params.to_module(loss.qvalue_network):
            return loss.qvalue_network(td)["state_action_value"].squeeze(-1)

    return q


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run_dir")
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--seed", type=int, default=12345, help="seed of the episodes' start states (default: not the training evaluation's)")
    p.add_argument("--data-states", type=int, default=5000)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    run = Path(args.run_dir)
    cfg, env, agent, state, _ = load_run_agent(run, num_envs=args.episodes)
    if "observation" not in env.observation_spec.keys():
        raise SystemExit(f"{run}: the probe reads the 'observation' key; this run's env has {list(env.observation_spec.keys())}")
    rets, td = evaluate_policy(env, agent.policy, args.episodes, max_steps=int(cfg["eval"]["max_steps"]), deterministic=True,
                               seed=args.seed, return_rollout=True)
    env.close()
    data = resolve_dataset(cfg)
    obs_data = data.data["observation"]
    sample = obs_data[torch.randperm(len(obs_data), generator=torch.Generator().manual_seed(0))[:100_000]]
    low, high = (torch.quantile(sample, q, dim=0) for q in (0.005, 0.995))
    base = ((sample < low) | (sample > high)).any(-1).float().mean()
    q = first_critic(agent)
    print(f"{run.name}: {state.get('updates', state.get('frames'))} updates, {args.episodes} deterministic episodes, seed {args.seed}; "
          f"{base:.0%} of the data's own states lie outside its 0.5-99.5% box")
    alive = first_episode_mask(td["next", "done"].squeeze(-1))
    for i in range(args.episodes):
        o = td["observation"][i][alive[i]]
        outside = ((o < low) | (o > high)).any(-1).float().mean()
        line = f"  episode {i}: return {float(rets[i]):9.1f}, {len(o)} steps, outside the box {outside:.0%}"
        if q is not None:
            line += f", Q(s, pi(s)) first 5 steps {q(o[:5]).mean():.1f}, last half {q(o[len(o) // 2:]).mean():.1f}"
        print(line)
    if q is None:
        print("  (no critic: BC)")
        return
    parts = data.metadata.get("parts") or {data.metadata.get("level", "data"): {"transitions": len(data)}}
    rng, start = np.random.default_rng(0), 0
    for name, part in parts.items():
        n = int(part["transitions"])
        idx = torch.as_tensor(np.sort(rng.choice(n, min(n, args.data_states), replace=False)) + start)
        print(f"  Q(s, pi(s)) on {len(idx)} {name} data states: {q(obs_data[idx]).mean():.1f}")
        start += n
    print(json.dumps({"returns": [round(float(r), 1) for r in rets]}))


if __name__ == "__main__":
    main()
