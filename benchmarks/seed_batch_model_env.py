"""Seeds as a batch dimension on the model env: N seeds of MOC (or PPO, SAC, MOPO) collecting and updating as one, against N separate runs.

    .venv/bin/python benchmarks/seed_batch_model_env.py [--algo moc|ppo|sac|mopo] [--seeds 1 5] [--iterations 3] [--threads 1] [--device cpu]

The demo's setting (``configs/demo.yaml``: 64 model envs per seed, batches
of 2,048 frames, minibatches of 256, ensemble and CVAE of MLP(256, 256);
weights barely fitted, which does not change the cost) on Hopper-v5's
dimensions. For each N, in one run: N agents each with its own env of 64
envs and its own collector, one after the other (what N separate runs cost
on one core), and the same N agents as one
:class:`~torchrl_offhrl.agents.seeds.OnPolicySeedBatch` on one env of
N x 64 envs (one collector, one vmapped policy, one vmapped update). Each
timed iteration is one batch per seed: collection and update, no evaluation
(an untimed warm-up iteration first). Prints frames/s per seed, the batched
time over one seed's, and the speed-up over separate runs.

SAC and MOPO (:class:`~torchrl_offhrl.agents.seeds.OffPolicySeedBatch`):
their configs' batches of 64 frames per seed (one step of the 64 envs),
each followed by 64 gradient steps on minibatches of 256 (``utd_ratio``
1) from each seed's own replay buffer, with no random-action phase
(``init_random_frames=0``); MOPO in real actions (no CVAE), 5% of each
minibatch from the dataset. Give them more iterations (``--iterations 20``):
one is ~64 gradient steps.
"""
from __future__ import annotations

import argparse
import time

import torch


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--algo", default="moc", choices=["moc", "ppo", "sac", "mopo"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1, 5])
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)

    from omegaconf import OmegaConf
    from torchrl.collectors import Collector

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.agents.seeds import OffPolicySeedBatch, OnPolicySeedBatch
    from torchrl_offhrl.data import collect_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.pipeline import make_model_env

    dev = torch.device(a.device)
    cfg = OmegaConf.to_container(compose("demo", [f"algo={a.algo}"]), resolve=True)
    acfg, per_seed = dict(cfg["algo"]), int(cfg["collector"]["num_envs"])
    off_policy, latent = a.algo in ("sac", "mopo"), a.algo != "mopo"
    if off_policy:
        acfg.pop("minibatch_size", None)  # the demo's setting for the on-policy agents
        acfg["init_random_frames"] = 0  # every timed batch takes its gradient steps
    torch.manual_seed(0)
    data = collect_dataset("Hopper-v5", 5000, num_envs=8, seed=0, progress=False)
    ens = DynamicsEnsemble.for_dataset(data, num_models=5, hidden_sizes=tuple(cfg["ensemble"]["hidden_sizes"])).fit(data, max_steps=20, progress=False)
    cvae = ConditionalVAE.for_dataset(data, hidden_sizes=tuple(cfg["cvae"]["hidden_sizes"])).fit(data, max_steps=20, progress=False)
    ens, cvae = ens.to(dev), cvae.to(dev)
    stats = data.stats()
    pcfg = {"seed": 0, "device": str(dev), "env": {"quantile": 0.99, "penalty": 20.0, "threshold": None}}
    pcfg["env"]["threshold"] = make_model_env(pcfg, ens, cvae, data, batch_size=1).base_env.threshold

    def agents_and_env(n: int, envs: int):
        env = make_model_env(pcfg, ens, cvae if latent else None, data, batch_size=envs, latent=latent)
        agents = []
        for s in range(n):
            torch.manual_seed(s)
            agents.append(make_agent(a.algo, env, acfg, obs_loc=stats.obs_mean.to(dev), obs_scale=stats.obs_std.to(dev), device=dev,
                                     action_key="latent_action" if latent else "action"))
            agents[-1].use_dataset(data)  # MOPO's share of the dataset's transitions (nothing for the others)
        agents[0].attach(env)
        return agents, env

    def run(policy, update, env, frames_per_batch: int) -> float:
        collector = Collector(env, policy, frames_per_batch=frames_per_batch, total_frames=frames_per_batch * (a.iterations + 1), device=dev,
                              auto_register_policy_transforms=False)
        it = iter(collector)
        update(next(it))  # warm-up
        t = time.perf_counter()
        for batch in it:
            update(batch)
        if dev.type == "cuda":
            torch.cuda.synchronize()
        out = time.perf_counter() - t
        collector.shutdown()
        return out

    fpb = int(acfg["frames_per_batch"])
    print(f"torch {torch.__version__}, device {dev}, {torch.get_num_threads()} thread(s); {a.algo}, {per_seed} model envs and {fpb} frames "
          f"per batch per seed, {a.iterations} timed iterations (collection + update)\n")
    print(f"{'seeds':>5s} {'separate s':>11s} {'batched s':>10s} {'frames/s/seed sep':>18s} {'frames/s/seed bat':>18s} "
          f"{'batched / 1 seed':>17s} {'speed-up':>9s}")
    one = None
    for n in a.seeds:
        t_sep = 0.0
        for s in range(n):  # each seed alone: its agent, its env of per_seed envs
            agents, env = agents_and_env(1, per_seed)
            torch.manual_seed(s)
            t_sep += run(agents[0].policy, agents[0].update, env, fpb)
        if n == 1:
            one = t_sep
        agents, env = agents_and_env(n, n * per_seed)
        sb = (OffPolicySeedBatch if off_policy else OnPolicySeedBatch)(agents)
        t_bat = run(sb.policy, sb.update, env, n * fpb)
        one = one or t_sep / n
        frames = a.iterations * fpb
        print(f"{n:5d} {t_sep:11.2f} {t_bat:10.2f} {n * frames / t_sep:18,.0f} {n * frames / t_bat:18,.0f} {t_bat / one:16.2f}x "
              f"{t_sep / t_bat:8.2f}x", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
