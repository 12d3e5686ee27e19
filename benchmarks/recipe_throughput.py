"""Throughput of the three offline recipes on the composed env, side by side in one run.

    python benchmarks/recipe_throughput.py [--device cuda] [--frames 16384] [--threads 1] [--recipes sac ppo moc]

For SAC, PPO and MOC with their config values (configs/algo/*.yaml) this
measures, on the same TransformedEnv(PessimisticModelEnv, LatentActionTransform)
(Hopper-v5 dimensions, ensemble 5 x MLP(512, 512), CVAE MLP(720, 720);
weights barely trained, which does not change the cost): collection frames/s
(model env + policy), gradient updates/s, and end-to-end frames/s of the
training loop (collection + updates, no evaluation).

Each recipe runs twice in the same process, "before" with torch's per-tensor
Adam (``fused_adam=false``) and, for PPO, TorchRL's functionalised loss
(``functional=true``), as the agents ran before the speed work, and "after"
with the config's defaults, and for PPO and MOC "compiled" (``compile=true``:
``torch.compile`` of the minibatch loss, built during the untimed warm-up
batch); the speed-up column is relative to "before".
"""
from __future__ import annotations

import argparse
import time

import torch


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--frames", type=int, default=16384, help="frames per on-policy recipe (after one warm-up batch)")
    p.add_argument("--sac-frames", type=int, default=2048, help="frames for SAC (one update per frame: slow)")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument("--recipes", nargs="+", default=["sac", "ppo", "moc"], choices=["sac", "ppo", "moc"])
    a = p.parse_args()
    if a.threads:
        torch.set_num_threads(a.threads)

    from omegaconf import OmegaConf
    from torchrl.collectors import Collector

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import collect_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.pipeline import make_model_env

    dev = torch.device(a.device)
    torch.manual_seed(0)
    data = collect_dataset("Hopper-v5", 5000, num_envs=8, seed=0, progress=False)
    ens = DynamicsEnsemble.for_dataset(data, num_models=5, hidden_sizes=(512, 512)).fit(data, max_steps=20, progress=False)
    cvae = ConditionalVAE.for_dataset(data, hidden_sizes=(720, 720)).fit(data, max_steps=20, progress=False)
    ens, cvae = ens.to(dev), cvae.to(dev)
    stats = data.stats()
    before = {}
    threshold = None
    print(f"\ndevice: {dev}, {a.num_envs} model envs, {torch.get_num_threads()} torch threads", flush=True)
    print("| recipe | variant | frames/batch | frames | collection frames/s | updates/s | end-to-end frames/s | updates per frame | end-to-end speed-up |")
    print("|---|---|---|---|---|---|---|---|---|", flush=True)
    variants = [(algo, when) for algo in a.recipes for when in ("before", "after", "compiled") if not (algo == "sac" and when == "compiled")]
    for algo, when in variants:
        torch.manual_seed(0)
        cfg = OmegaConf.to_container(compose("offline_train", [f"algo={algo}"]), resolve=True)
        pcfg = {"seed": 0, "device": str(dev), "env": {"quantile": 0.99, "penalty": 20.0, "threshold": threshold}}
        env = make_model_env(pcfg, ens, cvae, data, batch_size=a.num_envs)
        threshold = env.base_env.threshold
        acfg = dict(cfg["algo"])
        if "buffer_size" in acfg:  # off-policy: a smaller buffer, and learning from the first batch on
            acfg.update(buffer_size=100_000, init_random_frames=0)
        if when == "compiled":  # the warm-up batch below builds the compiled loss (not timed)
            acfg["compile"] = True
        if when == "before":
            acfg["fused_adam"] = False
            if "functional" in acfg:
                acfg["functional"] = True
        agent = make_agent(algo, env, acfg, obs_loc=stats.obs_mean.to(dev), obs_scale=stats.obs_std.to(dev), device=dev)
        agent.attach(env)
        fpb = max(a.num_envs, agent.frames_per_batch // a.num_envs * a.num_envs)
        collector = Collector(env, agent.policy, frames_per_batch=fpb, total_frames=fpb + (a.sac_frames if algo == "sac" else a.frames), device=dev, auto_register_policy_transforms=False)
        t_collect = t_update = 0.0
        updates = frames = 0
        it = iter(collector)
        batch = next(it)  # warm-up
        agent.update(batch)
        t0 = time.perf_counter()
        t_last = t0
        for batch in it:
            t1 = time.perf_counter()
            t_collect += t1 - t_last
            m = agent.update(batch)
            if dev.type == "cuda":
                torch.cuda.synchronize()
            t_last = time.perf_counter()
            t_update += t_last - t1
            updates += m["updates"]
            frames += batch.numel()
        total = time.perf_counter() - t0
        collector.shutdown()
        cf, us, ef, upf = frames / t_collect, updates / t_update, frames / total, updates / frames
        before.setdefault(algo, ef)  # "before" is measured first
        # each row as soon as it is measured: a run stopped by a time limit keeps the rows it finished
        print(f"| {algo} | {when} | {fpb} | {frames} | {cf:,.0f} | {us:,.1f} | {ef:,.0f} | {upf:.3f} | {ef / before[algo]:.2f}x |", flush=True)


if __name__ == "__main__":
    main()
