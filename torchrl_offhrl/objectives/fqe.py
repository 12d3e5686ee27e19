"""Fitted Q evaluation (FQE): a policy's value estimated from a fixed dataset, without the env.

FQE (Le, Voloshin & Yue 2019; used for offline policy selection by Paine et
al. 2020) fits ``Q^pi`` by regression on the dataset's transitions to the
bootstrapped target of the *evaluated* policy's next action:

    Q(s, a) <- r + gamma * (1 - terminated) * Q_target(s', pi(s'))

and scores the policy by ``Q(s0, pi(s0))`` averaged over start states. It
reads only the dataset, never a model: where the pessimistic model ranks a
policy by how long its rollouts stay where the members agree, FQE ranks it
by the dataset's own rewards and transitions (it extrapolates, too, wherever
``pi`` acts far from the data's actions: that is its known weakness).

Everything is vectorised: the evaluated policy's next actions are computed
once for the whole dataset (``next_action``), and ``num_policies`` policies
are fitted side by side as one batched network (a leading policy dimension,
as :class:`~torchrl_offhrl.models.DynamicsEnsemble` stacks its members), so
scoring 8 candidate policies is one fit, not 8.
"""
from __future__ import annotations

import math

import torch
from torch import nn

__all__ = ["BatchedQ", "fitted_q_evaluation"]


class BatchedQ(nn.Module):
    """``P`` independent MLP critics ``Q_p(s, a)`` evaluated in one batched matmul per layer.

    ``forward(obs, action)`` takes ``[P, B, obs_dim]`` and ``[P, B, act_dim]``
    and returns ``[P, B]``. Inputs are normalised with ``obs_loc`` /
    ``obs_scale`` (the dataset's statistics) before the first layer.

    Examples:
        >>> q = BatchedQ(3, 11, 3, hidden=(16, 16))
        >>> q(torch.zeros(3, 5, 11), torch.zeros(3, 5, 3)).shape
        torch.Size([3, 5])
    """

    def __init__(self, num_policies: int, obs_dim: int, act_dim: int, hidden=(256, 256), obs_loc=None, obs_scale=None):
        super().__init__()
        sizes = [obs_dim + act_dim, *hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(sizes[:-1], sizes[1:]):
            bound = 1.0 / math.sqrt(fan_in)  # nn.Linear's default initialisation, per policy
            self.weights.append(nn.Parameter(torch.empty(num_policies, fan_in, fan_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(num_policies, 1, fan_out).uniform_(-bound, bound)))
        self.register_buffer("obs_loc", torch.zeros(obs_dim) if obs_loc is None else torch.as_tensor(obs_loc, dtype=torch.float32))
        self.register_buffer("obs_scale", torch.ones(obs_dim) if obs_scale is None else torch.as_tensor(obs_scale, dtype=torch.float32))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        x = torch.cat([(obs - self.obs_loc) / self.obs_scale, action], -1)
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(b, x, w)
            if i < len(self.weights) - 1:
                x = torch.relu(x)
        return x.squeeze(-1)


@torch.no_grad()
def _polyak(target: nn.Module, source: nn.Module, tau: float) -> None:
    for t, s in zip(target.parameters(), source.parameters()):
        t.lerp_(s, tau)


def fitted_q_evaluation(
    obs: torch.Tensor,
    action: torch.Tensor,
    reward: torch.Tensor,
    next_obs: torch.Tensor,
    terminated: torch.Tensor,
    next_action: torch.Tensor,
    start_obs: torch.Tensor,
    start_action: torch.Tensor,
    *,
    gamma: float = 0.99,
    hidden=(256, 256),
    steps: int = 5000,
    batch_size: int = 256,
    lr: float = 3e-4,
    tau: float = 0.005,
    reward_scale: float = 1.0,
    obs_loc=None,
    obs_scale=None,
    seed: int = 0,
) -> dict:
    """FQE of ``P`` deterministic policies on one dataset of ``N`` transitions, fitted side by side.

    Args:
        obs, action, reward, next_obs, terminated: the dataset (``[N, obs_dim]``,
            ``[N, act_dim]``, ``[N]``, ``[N, obs_dim]``, ``[N]`` bool: a true
            termination, not a time-limit truncation; the target bootstraps
            through truncations).
        next_action: each policy's action at each ``next_obs``, ``[P, N, act_dim]``.
        start_obs, start_action: the states the value is reported at and each
            policy's action there, ``[S, obs_dim]`` and ``[P, S, act_dim]``.
        gamma: the discount of the value estimated.
        steps, batch_size, lr, tau: Adam steps on minibatches (one index draw
            shared by the policies), and the Polyak rate of the target critics.
        reward_scale: rewards are multiplied by it while fitting (targets of
            order 1) and the value is divided by it again.
        obs_loc, obs_scale: input normalisation (the dataset's statistics).

    Returns ``{"value": [P] mean of Q(s0, pi(s0)) over the start states,
    "td_error": [P] mean squared TD error of the last 100 steps (fitting
    units), "q": the fitted BatchedQ}``.

    Examples:
        A one-state chain with reward 1 and no termination: ``Q = 1 / (1 - gamma)``.

        >>> n = 512
        >>> s, a = torch.zeros(n, 1), torch.zeros(n, 1)
        >>> out = fitted_q_evaluation(s, a, torch.ones(n), s, torch.zeros(n, dtype=torch.bool), torch.zeros(1, n, 1),
        ...                           s[:4], torch.zeros(1, 4, 1), gamma=0.5, steps=1500, hidden=(16,), lr=1e-2, tau=0.05)
        >>> round(float(out["value"][0]), 1)
        2.0
    """
    n = obs.shape[0]
    if next_action.dim() != 3 or next_action.shape[1] != n:
        raise ValueError(f"next_action must be [num_policies, {n}, act_dim] (each policy's action at every next_obs), got {tuple(next_action.shape)}")
    if start_action.dim() != 3 or start_action.shape[:2] != (next_action.shape[0], start_obs.shape[0]):
        raise ValueError(f"start_action must be [{next_action.shape[0]}, {start_obs.shape[0]}, act_dim], got {tuple(start_action.shape)}")
    num_policies = next_action.shape[0]
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        q = BatchedQ(num_policies, obs.shape[-1], action.shape[-1], hidden, obs_loc, obs_scale).to(obs.device)
    target = BatchedQ(num_policies, obs.shape[-1], action.shape[-1], hidden, obs_loc, obs_scale).to(obs.device)
    target.load_state_dict(q.state_dict())
    target.requires_grad_(False)
    opt = torch.optim.Adam(q.parameters(), lr=lr)
    r = reward.reshape(n).float() * reward_scale
    cont = (~terminated.reshape(n).bool()).float() * gamma
    td_tail = []
    for step in range(steps):
        idx = torch.randint(n, (batch_size,), generator=gen).to(obs.device)
        s, a = obs[idx].expand(num_policies, -1, -1), action[idx].expand(num_policies, -1, -1)
        with torch.no_grad():
            y = r[idx] + cont[idx] * target(next_obs[idx].expand(num_policies, -1, -1), next_action[:, idx])
        loss = (q(s, a) - y).pow(2).mean(1)  # [P]: each policy's own regression
        opt.zero_grad(set_to_none=True)
        loss.sum().backward()
        opt.step()
        _polyak(target, q, tau)
        if step >= steps - 100:
            td_tail.append(loss.detach())
    with torch.no_grad():
        value = q(start_obs.expand(num_policies, -1, -1), start_action).mean(1) / reward_scale
    return {"value": value, "td_error": torch.stack(td_tail).mean(0) if td_tail else torch.full((num_policies,), float("nan")), "q": q}
