"""How long do episodes last in the pessimistic model, and what ends them, next to the real env?

    python experiments/diagnostics/model_episode_ends.py [hydra overrides of configs/demo.yaml ...]
    python experiments/diagnostics/model_episode_ends.py model_env.member_mode=mean ensemble.fit.max_steps=20000
    python experiments/diagnostics/model_episode_ends.py --config=offline_train ensemble.fit.lr=1e-3   # full scale (first argument)
    python experiments/diagnostics/model_episode_ends.py --run=outputs/results/full/ppo-halfcheetah-medium-expert-seed6

Rolls the untrained MOC agent's deterministic policy (the CVAE decoder's mean
action) out for 50 episodes in the model env built exactly as `offhrl train`
builds it (cached dataset and models) and in the real env, and prints the
return, the episode length, what ended each model episode (pessimism penalty,
task termination, horizon) and, for terminations, which Hopper health
condition fired. A model whose episodes end much earlier than the real ones
trains the agent on a different problem than the one it is evaluated on.

With ``--run=RUN_DIR`` it rolls out that run's trained policy instead (its
last checkpoint; the run's own config, models and P-MDP): where a policy's
model return rises while its real one falls, whether the pairs it visits lie
beyond the threshold (the pessimism could catch them) or below it (the
members agree, and are wrong, where the policy goes).
"""
from __future__ import annotations

import sys

import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_offhrl.agents import make_agent
from torchrl_offhrl.recipes.config import acts_in_latent_space, compose, latent_bound, model_config, model_env_config, resolve_dataset
from torchrl_offhrl.recipes.pipeline import fit_or_load_models, make_model_env, make_real_env
from torchrl_offhrl.rollouts import first_episode_mask
from torchrl_offhrl.utils import to_plain

EPISODES = 50


def rollout(env, policy, seed: int):
    env.set_seed(seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(1000, policy, break_when_any_done=False)
    done = td["next", "done"].reshape(EPISODES, -1)
    alive = first_episode_mask(done)
    ret = (td["next", "reward"].reshape(EPISODES, -1) * alive).sum(1)
    return td, alive, alive & done, ret, alive.sum(1).float()


def main(overrides: list[str]) -> None:
    torch.set_num_threads(1)
    name, run = "demo", None
    if overrides and overrides[0].startswith("--config="):  # e.g. --config=offline_train: the full-scale settings
        name, overrides = overrides[0].split("=", 1)[1], overrides[1:]
    if overrides and overrides[0].startswith("--run="):  # a trained run's policy, in its own P-MDP
        run, overrides = overrides[0].split("=", 1)[1], overrides[1:]
        if overrides:
            raise SystemExit(f"--run takes the run's own config; drop the overrides {overrides}")
    if run is not None:
        from torchrl_offhrl.recipes.evaluation import load_run_agent

        cfg, _, trained, state, _ = load_run_agent(run)
        print(f"{run}: its policy after {state.get('frames')} frames")
    else:
        cfg = to_plain(compose(name, overrides))
    data = resolve_dataset(cfg)
    mcfg = model_config(cfg)
    ensemble, cvae, _ = fit_or_load_models(mcfg, data, progress=False)
    mcfg["env"], pessimism = model_env_config(cfg, data.metadata.get("level"), data)
    torch.manual_seed(0)
    latent = acts_in_latent_space(cfg)  # a run with ablation.no_cvae (e.g. MOPO) acts in real actions
    env = make_model_env(mcfg, ensemble, cvae, data, batch_size=EPISODES, latent=latent)
    stats = data.stats()
    agent = trained if run is not None else make_agent("moc", env, cfg["algo"], obs_loc=stats.obs_mean, obs_scale=stats.obs_std)
    real = make_real_env(cfg["env"]["env_id"], cvae if latent else None, num_envs=EPISODES, latent_bound=latent_bound(cfg))
    for e in (env, real):
        agent.attach(e)
    print(f"pessimism {pessimism}, threshold {env.base_env.threshold:.3g}, member_mode {mcfg['env'].get('member_mode')}")
    print(env.base_env.calibration_report())
    data_sorted = env.base_env.calibration.discrepancies.double().sort().values
    for name, e in (("model", env), ("real", real)):
        td, alive, end, ret, length = rollout(e, agent.policy, seed=1)
        nobs = td["next", "observation"].reshape(EPISODES, alive.shape[1], -1)[end]
        line = f"{name}: return {ret.mean():.0f} ± {ret.std():.0f}, length {length.mean():.0f}, reward/step {(ret / length).mean():.2f}"
        if name == "model":
            pen = int((td["next", "penalized"].reshape(EPISODES, -1) & end).sum())
            term = int((td["next", "terminated"].reshape(EPISODES, -1) & end).sum()) - pen
            line += f"; ended by penalty {pen}, task termination {term}, horizon {EPISODES - pen - term}"
        terminated = td["next", "terminated"].reshape(EPISODES, -1)[end] if name == "real" else None
        z, angle = nobs[:, 0], nobs[:, 1]
        mask = torch.ones_like(z, dtype=torch.bool) if terminated is None else terminated
        line += f"; at terminal steps: z <= 0.7 in {int(((z <= 0.7) & mask).sum())}, |angle| >= 0.2 in {int(((angle.abs() >= 0.2) & mask).sum())}"
        print(line)
        # The same discrepancy the P-MDP thresholds, on the pairs this policy visits (real actions, decoded):
        # in the real env, where the policy is in the data's support; in the model, where it is ended.
        with torch.no_grad():
            obs, act = td["observation"][alive], td["action"][alive]
            disc = ensemble.discrepancy(obs.float(), act.float(), env.base_env.discrepancy_kind)
        q = torch.quantile(disc.double(), torch.tensor([0.5, 0.9, 0.99], dtype=torch.float64))
        rank = torch.searchsorted(data_sorted, q, right=True).double() / data_sorted.numel()
        ranks = " (the data's quantiles " + " / ".join(f"{r:.3f}" for r in rank) + ")"
        print(f"  discrepancy on its {disc.numel()} visited pairs: median / 90% / 99% "
              f"{q[0]:.3g} / {q[1]:.3g} / {q[2]:.3g}{ranks}; above the threshold: "
              f"{100 * float((disc > env.base_env.threshold).double().mean()):.1f}%")
    real.close()


if __name__ == "__main__":
    main(sys.argv[1:])
