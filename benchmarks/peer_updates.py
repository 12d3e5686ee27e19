"""Our IQL and TD3+BC updates next to a minimal plain-PyTorch update of the same networks, in one process (issue 75).

    python benchmarks/peer_updates.py [--updates 1000] [--threads 1] [--algos iql iql_stock td3bc]

"Plain" is what a single-file implementation does (CORL's style, written here from the papers, not copied): the
networks as ``nn.Sequential`` MLPs of the same widths (256 x 256, Hopper-v5's 11 observations and 3 actions), twin
critics as two modules, one fused Adam per network, the targets updated with ``torch._foreach_lerp_``, batch 256, the
same losses (IQL: expectile 0.7 value loss, TD(0) twin-Q loss on V(s'), advantage-weighted tanh-Gaussian log-likelihood
with temperature 3 clipped at 100; TD3+BC: target smoothing noise 0.2 clipped at 0.5, actor every second update with
lambda = 2.5 / mean|Q| and the BC term). "Ours" is ``make_agent(algo).update(batch)`` with the shipped config: TorchRL's
``IQLLoss`` / ``TD3BCLoss`` through the agent layer (fused Adam, inputs normalised inside the networks). Both take the
same number of updates on fresh copies of one random batch (an update's cost does not depend on the values), in
alternating blocks so that a busy neighbour slows both alike; the FLOPs of one update's matrix products are counted by
``torch.profiler`` for each, so the table also shows whether the two do the same work.
"""
from __future__ import annotations

import argparse
import math
import time

import torch
from flops import leaf_flops
from torch import nn

OBS, ACT, WIDTH, BATCH = 11, 3, 256, 256


def mlp(inp: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inp, WIDTH), nn.ReLU(), nn.Linear(WIDTH, WIDTH), nn.ReLU(), nn.Linear(WIDTH, out))


def adam(module: nn.Module, lr: float = 3e-4) -> torch.optim.Adam:
    return torch.optim.Adam(module.parameters(), lr=lr, fused=True)


def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def target_copy(module: nn.Module) -> nn.Module:
    import copy

    out = copy.deepcopy(module)
    out.requires_grad_(False)
    return out


class PlainIQL:
    """IQL (Kostrikov et al. 2022) in plain PyTorch: V, twin Q with a target, a tanh-Gaussian actor."""

    def __init__(self, gamma=0.99, tau=0.005, expectile=0.7, temperature=3.0):
        self.v, self.q1, self.q2, self.actor = mlp(OBS, 1), mlp(OBS + ACT, 1), mlp(OBS + ACT, 1), mlp(OBS, 2 * ACT)
        self.q1_t, self.q2_t = target_copy(self.q1), target_copy(self.q2)
        self.opt_v, self.opt_q, self.opt_a = adam(self.v), adam(nn.ModuleList([self.q1, self.q2])), adam(self.actor)
        self.gamma, self.tau, self.expectile, self.temperature = gamma, tau, expectile, temperature

    def update(self, b: dict) -> None:
        s, a, r, s2, d = b["obs"], b["act"], b["rew"], b["next_obs"], b["done"]
        sa = torch.cat([s, a], -1)
        with torch.no_grad():
            q_t = torch.min(self.q1_t(sa), self.q2_t(sa))
            y = r + self.gamma * (1 - d) * self.v(s2)
        v = self.v(s)
        adv = q_t - v
        v_loss = (torch.abs(self.expectile - (adv < 0).float()) * adv.pow(2)).mean()
        self.opt_v.zero_grad(set_to_none=True)
        v_loss.backward()
        self.opt_v.step()
        q_loss = (self.q1(sa) - y).pow(2).mean() + (self.q2(sa) - y).pow(2).mean()
        self.opt_q.zero_grad(set_to_none=True)
        q_loss.backward()
        self.opt_q.step()
        weight = torch.exp(self.temperature * adv.detach()).clamp(max=100.0)
        loc, scale = self.actor(s).chunk(2, -1)
        scale = nn.functional.softplus(scale) + 0.1
        a_in = a.clamp(-1 + 1e-6, 1 - 1e-6)
        pre = torch.atanh(a_in)
        log_prob = (torch.distributions.Normal(loc, scale).log_prob(pre) - torch.log1p(-a_in.pow(2) + 1e-6)).sum(-1, keepdim=True)
        a_loss = -(weight * log_prob).mean()
        self.opt_a.zero_grad(set_to_none=True)
        a_loss.backward()
        self.opt_a.step()
        soft_update(nn.ModuleList([self.q1_t, self.q2_t]), nn.ModuleList([self.q1, self.q2]), self.tau)


class PlainTD3BC:
    """TD3+BC (Fujimoto and Gu 2021) in plain PyTorch: a deterministic actor, twin critics, targets of both."""

    def __init__(self, gamma=0.99, tau=0.005, alpha=2.5, noise=0.2, noise_clip=0.5, delay=2):
        self.actor, self.q1, self.q2 = mlp(OBS, ACT), mlp(OBS + ACT, 1), mlp(OBS + ACT, 1)
        self.actor_t, self.q1_t, self.q2_t = target_copy(self.actor), target_copy(self.q1), target_copy(self.q2)
        self.opt_q, self.opt_a = adam(nn.ModuleList([self.q1, self.q2])), adam(self.actor)
        self.gamma, self.tau, self.alpha, self.noise, self.noise_clip, self.delay = gamma, tau, alpha, noise, noise_clip, delay
        self.steps = 0

    def update(self, b: dict) -> None:
        s, a, r, s2, d = b["obs"], b["act"], b["rew"], b["next_obs"], b["done"]
        self.steps += 1
        with torch.no_grad():
            eps = (torch.randn_like(a) * self.noise).clamp(-self.noise_clip, self.noise_clip)
            a2 = (torch.tanh(self.actor_t(s2)) + eps).clamp(-1, 1)
            s2a2 = torch.cat([s2, a2], -1)
            y = r + self.gamma * (1 - d) * torch.min(self.q1_t(s2a2), self.q2_t(s2a2))
        sa = torch.cat([s, a], -1)
        q_loss = (self.q1(sa) - y).pow(2).mean() + (self.q2(sa) - y).pow(2).mean()
        self.opt_q.zero_grad(set_to_none=True)
        q_loss.backward()
        self.opt_q.step()
        if self.steps % self.delay == 0:
            pi = torch.tanh(self.actor(s))
            q = self.q1(torch.cat([s, pi], -1))
            lmbda = self.alpha / q.abs().mean().detach()
            a_loss = -lmbda * q.mean() + (pi - a).pow(2).mean()
            self.opt_a.zero_grad(set_to_none=True)
            a_loss.backward()
            self.opt_a.step()
            soft_update(nn.ModuleList([self.actor_t, self.q1_t, self.q2_t]), nn.ModuleList([self.actor, self.q1, self.q2]), self.tau)


PLAIN = {"iql": PlainIQL, "td3bc": PlainTD3BC}


def flops_of(step) -> float:
    from torch.profiler import profile

    with profile(with_flops=True) as prof:
        step()
        step()  # TD3+BC: one critic-only and one critic + actor update
    return leaf_flops(prof) / 2  # each product once, not again at the vmap levels above it (flops.py)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--updates", type=int, default=1000)
    p.add_argument("--blocks", type=int, default=4, help="alternating blocks per implementation")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--algos", nargs="+", default=["iql", "iql_stock", "td3bc"],
                   help="iql_stock: our IQL agent on TorchRL's IQLLoss as it ships, instead of SharedPassIQLLoss; "
                        "<algo>_compiled: with algo.compile=true (torch.compile of the loss); <algo>_step_compiled: the "
                        "whole update (losses, backward, Adam, targets) through torch.compile, as TorchRL's sota scripts "
                        "compile theirs, with --backend")
    p.add_argument("--backend", default="inductor", help="torch.compile backend of the _step_compiled variants (inductor, "
                                                         "aot_eager, eager)")
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    from tensordict import TensorDict

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.utils import to_plain

    env = make_gym_env("Hopper-v5")
    torch.manual_seed(0)
    obs, nobs = torch.randn(BATCH, OBS), torch.randn(BATCH, OBS)
    act, rew = torch.rand(BATCH, ACT) * 2 - 1, torch.randn(BATCH, 1)
    done = torch.zeros(BATCH, 1)
    plain_batch = {"obs": obs, "act": act, "rew": rew, "next_obs": nobs, "done": done}
    ours_batch = TensorDict({"observation": obs, "action": act, "next": {"observation": nobs, "reward": rew, "done": done.bool(),
                                                                          "terminated": done.bool()}}, [BATCH])
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s); {a.updates} updates each, in {a.blocks} alternating blocks\n")
    print("| algo | plain PyTorch updates/s | ours updates/s | ours / plain | GFLOP per update, plain / ours | GFLOP/s, plain / ours |")
    print("|---|---|---|---|---|---|", flush=True)
    for algo in a.algos:
        name = algo.removesuffix("_stock").removesuffix("_compiled").removesuffix("_step")
        loss_compiled = algo.endswith("_compiled") and not algo.endswith("_step_compiled")
        cfg = to_plain(compose("offline_train", [f"algo={name}"] + (["algo.compile=true"] if loss_compiled else [])))["algo"]
        cfg.pop("reward_scale", None)
        if algo == "iql_stock":  # the agent on TorchRL's IQLLoss as it ships (each term's own forward passes)
            from torchrl.objectives import IQLLoss

            from torchrl_offhrl.agents import AGENTS

            stock = type("StockIQLAgent", (AGENTS["iql"],), {"loss_class": IQLLoss})
            ours = stock(env, action_key="action", **{k: v for k, v in cfg.items() if k != "name"})
        else:
            ours = make_agent(name, env, cfg, action_key="action")
        if algo.endswith("_step_compiled"):  # each form of the update (TD3+BC: with and without the actor) compiled once
            eager_step = ours.step
            compiled = {}

            def step_fn(variant, eager_step=eager_step, compiled=compiled):
                if variant not in compiled:
                    compiled[variant] = torch.compile(lambda batch: eager_step(batch, variant), backend=a.backend)
                return compiled[variant]

            ours._step_fn = step_fn
        plain = PLAIN[name]()
        steps = {"plain": lambda: plain.update(plain_batch), "ours": lambda: ours.update(ours_batch.clone())}
        for step in steps.values():
            for _ in range(20):
                step()
        flops = {k: flops_of(step) for k, step in steps.items()}
        spent = dict.fromkeys(steps, 0.0)
        per_block = max(1, math.ceil(a.updates / a.blocks))
        for _ in range(a.blocks):
            for name, step in steps.items():
                t = time.perf_counter()
                for _ in range(per_block):
                    step()
                spent[name] += time.perf_counter() - t
        rate = {k: a.blocks * per_block / v for k, v in spent.items()}
        label = f"{algo} ({a.backend})" if algo.endswith("_step_compiled") else algo
        print(f"| {label} | {rate['plain']:.1f} | {rate['ours']:.1f} | {rate['ours'] / rate['plain']:.2f} | "
              f"{flops['plain'] / 1e9:.3f} / {flops['ours'] / 1e9:.3f} | {rate['plain'] * flops['plain'] / 1e9:.1f} / "
              f"{rate['ours'] * flops['ours'] / 1e9:.1f} |", flush=True)


if __name__ == "__main__":
    main()
