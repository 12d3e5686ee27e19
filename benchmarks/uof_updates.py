"""Where one UOF update's time goes, and how far it is from this machine's matrix-multiply bound (issue 74).

    python benchmarks/uof_updates.py [--updates 200] [--threads 1] [--device cpu]

Builds UOF as `offhrl train algo=uof env=blockstack2` builds it (configs/algo/uof.yaml: both levels MLP 3 x 256, batch
128, the twin critics vmapped, HER on the low level) on a block-stacking model env (an untrained 5-member ensemble and
CVAE of the shipped sizes: an update's cost does not depend on the weights' values), fills both replay buffers with
4,000 collected frames, then times ``--updates`` updates of the loop in ``UOFAgent.update`` part by part: the HER
sample (TorchRL's ``HERReplayBuffer``, relabelling included), the high level's sample, each loss's forward, the
backward, Adam and the two target updates. The FLOPs of one update's matrix products are counted by
``torch.profiler`` (``with_flops``), and the same run measures the dense matmul rate at the update's own shapes
(``[2, 128, 256] x [2, 256, 256]``, the twin critics' layers, taken as the bound; ``[128, 256] x [256, 256]`` with one
weight matrix hot in the cache runs faster and is shown for reference), so the table shows the update's rate as a
fraction of the matmul bound and what UOF's own budget, 602k low-level updates per seed on task 1
(301 epochs x 50 cycles x 40), costs at that rate. ``bf16`` repeats the timing with the losses under
``torch.autocast(dtype=bfloat16)`` (a measured alternative, not the library's setting: it changes the numerics).
"""
from __future__ import annotations

import argparse
import time

import torch
from flops import leaf_flops

UOF_UPDATES = 602_000  # UOF's own low-level updates per seed on task 1: 301 epochs x 50 cycles x 40 updates


def matmul_rate(device, shape, steps=400) -> float:
    """GFLOP/s of ``torch.bmm`` / ``@`` at ``shape`` ((b, m, k, n); b 0: a plain matrix product), measured now."""
    b, m, k, n = shape
    x = torch.randn(*((b,) if b else ()), m, k, device=device)
    w = torch.randn(*((b,) if b else ()), k, n, device=device)
    for _ in range(20):
        x @ w
    t = time.perf_counter()
    for _ in range(steps):
        x @ w
    if device.type == "cuda":
        torch.cuda.synchronize()
    return 2 * max(b, 1) * m * k * n * steps / (time.perf_counter() - t) / 1e9


def build(device):
    from torchrl.collectors import Collector

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data.stacking import collect_stacking
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.pipeline import make_model_env
    from torchrl_offhrl.utils import to_plain

    cfg = to_plain(compose("offline_train", ["algo=uof", "env=blockstack2"]))
    torch.manual_seed(0)
    data = collect_stacking("BlockStack2-v0", 2000, 0.1, 0.1, num_envs=4, seed=1, progress=False)
    ens = DynamicsEnsemble.for_dataset(data, num_models=cfg["ensemble"]["num_models"], hidden_sizes=cfg["ensemble"]["hidden_sizes"],
                                       learn_reward=False).to(device)
    cvae = ConditionalVAE.for_dataset(data, goal_key="sub_goal", hidden_sizes=cfg["cvae"]["hidden_sizes"]).to(device)
    env = make_model_env({"env": {"penalty": 50.0, "quantile": 0.99, "horizon": 25}, "seed": 0, "device": str(device)}, ens, cvae, data,
                         batch_size=16)
    stats = data.stats()
    algo = {k: v for k, v in cfg["algo"].items() if k != "name"}
    agent = make_agent("uof", env, algo, obs_loc=stats.obs_mean, obs_scale=stats.obs_std, goal_key="sub_goal", device=device)
    agent.attach(env)
    agent.updates_per_frame = 1 / 400  # one update per collected batch while the buffers fill
    col = Collector(env, agent.policy, frames_per_batch=400, total_frames=4000, auto_register_policy_transforms=False, device=device)
    for batch in col:
        agent.update(batch)
    col.shutdown()
    return agent


def time_parts(agent, updates: int, autocast: bool = False) -> dict:
    """Seconds per update of each part of ``UOFAgent.update``'s loop (its code, split by timers)."""
    from torchrl_offhrl.agents.her import low_level_done

    rb_low, rb_high = agent.replay_buffer["low"], agent.replay_buffer["high"]
    names = ["HER sample (low)", "sample (high)", "low loss forward", "high loss forward", "backward", "Adam", "target updates"]
    parts = dict.fromkeys(names, 0.0)
    ctx = (lambda: torch.autocast("cpu", dtype=torch.bfloat16)) if autocast else torch.enable_grad
    for i in range(updates + 20):
        t = [time.perf_counter()]
        low_batch = low_level_done(rb_low.sample())
        t.append(time.perf_counter())
        high_batch = rb_high.sample()
        t.append(time.perf_counter())
        with ctx():
            low = agent.low(low_batch)
            t.append(time.perf_counter())
            high = agent.high(high_batch)
            loss = low["loss_actor"] + low["loss_qvalue"] + high["loss_qvalue"]
        t.append(time.perf_counter())
        agent.optimizer.zero_grad()
        loss.float().backward()
        t.append(time.perf_counter())
        agent.optimizer.step()
        t.append(time.perf_counter())
        for u in agent.target_updaters:
            u.step()
        t.append(time.perf_counter())
        if i >= 20:  # warm-up
            for name, a, b in zip(names, t, t[1:]):
                parts[name] += b - a
    return {k: v / updates for k, v in parts.items()}


def update_flops(agent) -> float:
    """FLOPs of one update's matrix products (forward and backward), counted by torch.profiler."""
    from torch.profiler import ProfilerActivity, profile

    from torchrl_offhrl.agents.her import low_level_done

    with profile(activities=[ProfilerActivity.CPU], with_flops=True) as prof:
        for _ in range(5):
            low, high = agent.low(low_level_done(agent.replay_buffer["low"].sample())), agent.high(agent.replay_buffer["high"].sample())
            agent.optimizer.zero_grad()
            (low["loss_actor"] + low["loss_qvalue"] + high["loss_qvalue"]).backward()
    return leaf_flops(prof) / 5  # each product once, not again at the vmap levels above it (flops.py)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--updates", type=int, default=200)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    device = torch.device(a.device)
    agent = build(device)
    flops = update_flops(agent)
    rates = {"bmm [2,128,256]x[2,256,256] (the twin critics' layers: the bound)": matmul_rate(device, (2, 128, 256, 256)),
             "mm [128,256]x[256,256] (one weight, hot in cache: not reachable by an update over 0.7M weights)": matmul_rate(device, (0, 128, 256, 256))}
    bound = next(iter(rates.values()))
    print(f"UOF update (configs/algo/uof.yaml), {device}, {a.threads} thread(s), torch {torch.__version__}; "
          f"{flops / 1e9:.3f} GFLOP per update (torch.profiler, matrix products)")
    for name, r in rates.items():
        print(f"  same-run matmul rate, {name}: {r:.1f} GFLOP/s")
    rows = [("fp32 (the library)", time_parts(agent, a.updates))]
    if device.type == "cpu":
        rows.append(("bf16 autocast (not used)", time_parts(agent, a.updates, autocast=True)))
    names = list(rows[0][1])
    print("\n| part | " + " | ".join(f"{label} ms" for label, _ in rows) + " |")
    print("|---|" + "---|" * len(rows))
    for name in names:
        print(f"| {name} | " + " | ".join(f"{1e3 * parts[name]:.2f}" for _, parts in rows) + " |")
    totals = [sum(parts.values()) for _, parts in rows]
    print("| **update** | " + " | ".join(f"**{1e3 * t:.2f}**" for t in totals) + " |")
    print("| updates/s | " + " | ".join(f"{1 / t:.1f}" for t in totals) + " |")
    print(f"| share of the matmul bound ({1e3 * flops / bound / 1e9:.2f} ms at {bound:.0f} GFLOP/s) | "
          + " | ".join(f"{flops / bound / 1e9 / t:.0%}" for t in totals) + " |")
    print(f"| {UOF_UPDATES:,} updates (UOF's task-1 budget), hours | " + " | ".join(f"{UOF_UPDATES * t / 3600:.2f}" for t in totals) + " |")
    print(f"| the same at the matmul bound, hours | {UOF_UPDATES * flops / bound / 1e9 / 3600:.2f} |" + " |" * (len(rows) - 1))


if __name__ == "__main__":
    main()
