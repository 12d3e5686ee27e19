"""Where one update's time goes, for every agent the recipes train (issue 75, item 1).

    python benchmarks/update_profile.py [--threads 1] [--algos iql td3bc cql sac moc ppo] [--repeats N]

Each agent as the shipped configs build it (``make_agent`` on ``configs/algo/<algo>.yaml``; MLP(256, 256), Hopper-v5's
sizes):

* the dataset agents (IQL, TD3+BC, CQL): ``agent.update`` on a batch of 256 random transitions (the cost does not depend
  on the values), one gradient step per call;
* the model-env agents (SAC, MOC, PPO) on the demo's model env (``configs/demo.yaml``: 64 model envs, ensemble and CVAE
  of MLP(256, 256), barely fitted, which does not change the cost), fed by a TorchRL ``Collector`` as the training loop
  feeds them: SAC's ``update`` takes one 64-frame batch (64 gradient steps of 256 from its replay buffer, ``utd_ratio``
  1, no random-action phase), MOC's and PPO's one 2,048-frame batch (GAE, then their epochs of minibatches of 256:
  80 gradient steps, and MOC's once-per-batch termination and option-policy steps). The collection of that batch (the
  model env's step through the ensemble and the CVAE decoder, the policy's forward) is timed beside it.

For each: the wall time of one ``update`` call (unprofiled, the median of ``--repeats`` calls after warm-up), the
gradient steps it takes, and where the time goes from a profiled stretch of the same calls (``torch.profiler`` self
time per op, grouped as ``fit_steps.py`` groups a fit's step, plus the random-number kernels): matrix products,
elementwise and reductions, the optimiser, indexing and copies, random numbers, and the rest (Python, TensorDict and
TorchRL bookkeeping, dispatch, autograd: the wall time no op accounts for). Also the host reads per call (``.item()``
and other reads of a tensor's value by the host: ``aten::_local_scalar_dense`` calls), with how many of them are the
fused Adam kernel's own reads of its step counts (a CPU kernel's: the CUDA one reads none); on a GPU each of the others
would be a wait for the device. Shares are of the unprofiled wall time; the profiler's own cost per op lands in the op groups, so read the "rest"
column as a lower bound.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch
from fit_steps import INDEXING, MATMUL, OPTIMISER  # one grouping of ops for every table of this folder

RANDOM = ("aten::normal", "aten::normal_", "aten::uniform_", "aten::randint", "aten::random_", "aten::randperm", "aten::multinomial",
          "aten::bernoulli_", "aten::exponential_", "aten::rand", "aten::randn", "aten::rand_like", "aten::randn_like")
GROUPS = ("matrix products", "elementwise and reductions", "optimiser", "indexing and copies", "random numbers")
DATASET_AGENTS = ("bc", "iql", "td3bc", "cql")


def group_of(op: str) -> str:
    if op in MATMUL:
        return "matrix products"
    if op.startswith(OPTIMISER):
        return "optimiser"
    if op in RANDOM:
        return "random numbers"
    if op in INDEXING:
        return "indexing and copies"
    return "elementwise and reductions"


def profile_calls(call, n: int) -> tuple[dict[str, float], tuple[int, int]]:
    """({group: self time in s}, (host reads, those of them inside fused Adam)) summed over ``n`` calls of ``call`` under
    ``torch.profiler``."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(n):
            call()
    groups = dict.fromkeys(GROUPS, 0.0)
    for e in prof.key_averages():
        if e.key.startswith("aten::"):
            groups[group_of(e.key)] += e.self_cpu_time_total / 1e6
    syncs = [0, 0]  # (all, those inside the fused Adam kernel)
    for e in prof.events():
        if e.name == "aten::_local_scalar_dense":
            syncs[0] += 1
            p = e.cpu_parent
            while p is not None and p.name != "aten::_fused_adam_":
                p = p.cpu_parent
            syncs[1] += p is not None
    return groups, tuple(syncs)


def median_time(call, n: int) -> float:
    times = []
    for _ in range(n):
        t = time.perf_counter()
        call()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def dataset_agent(algo: str):
    """(update call, gradient steps per call, None): ``algo`` on one random batch of its config's size."""
    from tensordict import TensorDict

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.utils import to_plain

    cfg = to_plain(compose("offline_train", [f"algo={algo}"]))["algo"]
    cfg.pop("reward_scale", None)
    b = int(cfg["batch_size"])
    torch.manual_seed(0)
    batch = TensorDict({"observation": torch.randn(b, 11), "action": torch.rand(b, 3) * 2 - 1, "next": {
        "observation": torch.randn(b, 11), "reward": torch.randn(b, 1), "done": torch.zeros(b, 1, dtype=torch.bool),
        "terminated": torch.zeros(b, 1, dtype=torch.bool)}}, [b])
    agent = make_agent(algo, make_gym_env("Hopper-v5"), cfg, action_key="action")
    return (lambda: agent.update(batch.clone())), 1, None


def model_env_agent(algo: str):
    """(update call on the next collected batch, gradient steps per call, collection call): ``algo`` on the demo's model env."""
    from omegaconf import OmegaConf
    from torchrl.collectors import Collector

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import collect_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.pipeline import make_model_env

    cfg = OmegaConf.to_container(compose("demo", [f"algo={algo}"]), resolve=True)
    acfg = dict(cfg["algo"])
    if algo == "sac":
        acfg.pop("minibatch_size", None)
        acfg["init_random_frames"] = 0
    torch.manual_seed(0)
    data = collect_dataset("Hopper-v5", 5000, num_envs=8, seed=0, progress=False)
    ens = DynamicsEnsemble.for_dataset(data, num_models=5, hidden_sizes=tuple(cfg["ensemble"]["hidden_sizes"])).fit(data, max_steps=20, progress=False)
    cvae = ConditionalVAE.for_dataset(data, hidden_sizes=tuple(cfg["cvae"]["hidden_sizes"])).fit(data, max_steps=20, progress=False)
    stats = data.stats()
    pcfg = {"seed": 0, "device": "cpu", "env": {"quantile": 0.99, "penalty": 20.0, "threshold": None}}
    pcfg["env"]["threshold"] = make_model_env(pcfg, ens, cvae, data, batch_size=1).base_env.threshold
    env = make_model_env(pcfg, ens, cvae, data, batch_size=int(cfg["collector"]["num_envs"]), latent=True)
    agent = make_agent(algo, env, acfg, obs_loc=stats.obs_mean, obs_scale=stats.obs_std, device=torch.device("cpu"),
                       action_key="latent_action")
    agent.use_dataset(data)
    agent.attach(env)
    collector = Collector(env, agent.policy, frames_per_batch=int(acfg["frames_per_batch"]), total_frames=-1,
                          auto_register_policy_transforms=False)
    it = iter(collector)
    batches = [next(it)]  # the batch the next update call takes; each collection call replaces it
    steps = agent.update(batches[0].clone())["updates"]

    def collect():
        batches[0] = next(it)

    return (lambda: agent.update(batches[0].clone())), int(steps), collect


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--algos", nargs="+", default=["iql", "td3bc", "cql", "sac", "moc", "ppo"])
    p.add_argument("--repeats", type=int, default=None, help="timed calls per agent (default: 200 for the dataset agents, "
                                                             "10 for SAC, 5 for MOC and PPO; as many again profiled)")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s)\n")
    print("| algo | ms per update call | gradient steps per call | ms per gradient step | " + " | ".join(GROUPS)
          + " | rest (Python, TensorDict, dispatch, autograd) | host reads per call (in fused Adam) | collection of the batch, ms |")
    print("|---|---|---|---|" + "---|" * (len(GROUPS) + 3), flush=True)
    for algo in a.algos:
        dataset = algo in DATASET_AGENTS
        update, steps, collect = dataset_agent(algo) if dataset else model_env_agent(algo)
        n = a.repeats or (200 if dataset else 10 if algo == "sac" else 5)
        for _ in range(max(3, n // 10)):  # warm-up (first calls allocate, build the losses' caches)
            update()
        wall = median_time(update, n)
        groups, syncs = profile_calls(update, n)
        shares = [groups[g] / n / wall for g in GROUPS]
        collect_ms = f"{1e3 * median_time(collect, max(3, n // 2)):.1f}" if collect else "n/a (dataset)"
        print(f"| {algo} | {1e3 * wall:.1f} | {steps} | {1e3 * wall / steps:.2f} | " + " | ".join(f"{s:.0%}" for s in shares)
              + f" | {max(0.0, 1 - sum(shares)):.0%} | {syncs[0] / n:.0f} ({syncs[1] / n:.0f}) | {collect_ms} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
