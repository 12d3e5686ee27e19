"""Can an on-policy critic fit the model env's value targets? (why PPO and MOC did not improve)

    python experiments/diagnostics/critic_probe.py [hydra overrides of configs/demo.yaml ...]
    python experiments/diagnostics/critic_probe.py cvae.kl_weight=0.05 ensemble.fit.max_steps=20000 cvae.fit.max_steps=20000

Rolls the untrained PPO policy (stochastic) out for 64 x 1000 steps in the
model env built exactly as `offhrl train` builds it (cached dataset and
models), computes the discounted Monte-Carlo returns (gamma 0.99), and fits
a fresh 64x64 tanh critic (the PPO/MOC critic's architecture, normalised
inputs) to them with Adam at two learning rates, on the raw returns and on
the returns divided by their std (what ``model_env.reward_scale=auto`` does),
printing the explained variance on held-out envs. A critic that explains
~0% of its targets gives advantages that are noise.
"""
from __future__ import annotations

import sys

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_offhrl.agents import make_agent
from torchrl_offhrl.nets import NormalizedMLP
from torchrl_offhrl.recipes.config import compose, model_config, model_env_config, resolve_dataset
from torchrl_offhrl.recipes.pipeline import fit_or_load_models, make_model_env
from torchrl_offhrl.utils import to_plain

ENVS, STEPS, GAMMA, CUT = 64, 1000, 0.99, 300


def main(overrides: list[str]) -> None:
    torch.set_num_threads(1)
    cfg = to_plain(compose("demo", [*overrides, "model_env.reward_scale=1.0"]))
    data = resolve_dataset(cfg)
    mcfg = model_config(cfg)
    ensemble, cvae, _ = fit_or_load_models(mcfg, data, progress=False)
    mcfg["env"], _ = model_env_config(cfg, data.metadata.get("level"), data)
    torch.manual_seed(0)
    env = make_model_env(mcfg, ensemble, cvae, data, batch_size=ENVS)
    stats = data.stats()
    agent = make_agent("ppo", env, {}, obs_loc=stats.obs_mean, obs_scale=stats.obs_std)
    agent.attach(env)
    env.set_seed(1)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = env.rollout(STEPS, agent.policy, break_when_any_done=False)
    obs, r, d = td["observation"], td["next", "reward"].squeeze(-1), td["next", "done"].squeeze(-1)
    print(f"model env, untrained PPO policy: reward {r.mean():.2f} +- {r.std():.2f} per step, episode ends {d.float().mean():.4f} per step")
    ret, acc = torch.zeros_like(r), torch.zeros(ENVS)
    for t in reversed(range(STEPS)):  # offline analysis, not a hot path
        acc = r[:, t] + GAMMA * acc * (~d[:, t]).float()
        ret[:, t] = acc
    # the last CUT steps' returns are cut by the rollout's end: left out
    x, y = obs[:, : STEPS - CUT].reshape(-1, obs.shape[-1]), ret[:, : STEPS - CUT].reshape(-1)
    ntr = (ENVS * 3 // 4) * (STEPS - CUT)
    print(f"discounted returns {y.mean():.1f} +- {y.std():.1f}; dataset returns-to-go std {data.returns_to_go(GAMMA).std():.1f}")
    print("| lr | targets | EV after 300 | 1000 | 3000 steps |\n|---|---|---|---|---|")
    for lr in (1e-4, 1e-3):
        for name, scale in (("raw", 1.0), ("/ std", 1.0 / float(y.std()))):
            torch.manual_seed(0)
            net = NormalizedMLP(obs.shape[-1], 0, 1, [64, 64], "tanh", stats.obs_mean, stats.obs_std)
            opt = torch.optim.Adam(net.parameters(), lr=lr)
            evs = []
            for step in range(3000):
                i = torch.randint(0, ntr, (64,))
                loss = ((net(x[i]).squeeze(-1) - y[i] * scale) ** 2).mean()
                opt.zero_grad()
                loss.backward()
                opt.step()
                if step + 1 in (300, 1000, 3000):
                    with torch.no_grad():
                        pred = net(x[ntr:]).squeeze(-1) / scale
                    evs.append(float(1 - (y[ntr:] - pred).var() / y[ntr:].var()))
            print(f"| {lr:g} | {name} | " + " | ".join(f"{e:.3f}" for e in evs) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
