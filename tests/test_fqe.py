"""Fitted Q evaluation (torchrl_offhrl.objectives.fqe): values of hand-computable MDPs, policies fitted side by side."""
from __future__ import annotations

import torch

from torchrl_offhrl.objectives.fqe import BatchedQ, fitted_q_evaluation

FAST = dict(hidden=(32,), lr=1e-2, tau=0.05, batch_size=256)


def test_two_policies_on_one_dataset_get_their_own_values():
    """Reward = the action (0 or 1), the state never changes, gamma 0.5. The dataset holds both actions.
    A policy that always takes 1 is worth 1 / (1 - 0.5) = 2 at every state, one that takes 0 is worth 0,
    one that takes 1 now and 0 afterwards is worth exactly 1: three values from one batched fit."""
    g = torch.Generator().manual_seed(0)
    n = 1024
    s = torch.randint(0, 2, (n, 1), generator=g).float()
    a = torch.randint(0, 2, (n, 1), generator=g).float()
    ones, zeros = torch.ones(1, n, 1), torch.zeros(1, n, 1)
    next_action = torch.cat([ones, zeros, zeros])  # policies: always 1 | always 0 | 1 first, then 0
    start_action = torch.stack([torch.ones(4, 1), torch.zeros(4, 1), torch.ones(4, 1)])
    out = fitted_q_evaluation(s, a, a.squeeze(-1), s, torch.zeros(n, dtype=torch.bool), next_action, s[:4], start_action,
                              gamma=0.5, steps=2000, **FAST)
    torch.testing.assert_close(out["value"], torch.tensor([2.0, 0.0, 1.0]), atol=0.05, rtol=0)
    assert (out["td_error"] < 1e-3).all()


def test_termination_stops_the_bootstrap_and_reward_scale_is_undone():
    """Every transition terminates: Q = r whatever the policy does next (5.0 here), also when fitted on rewards x 0.1."""
    n = 512
    s = torch.randn(n, 3, generator=torch.Generator().manual_seed(1))
    a = torch.zeros(n, 1)
    for scale in (1.0, 0.1):
        out = fitted_q_evaluation(s, a, torch.full((n,), 5.0), s, torch.ones(n, dtype=torch.bool), torch.full((1, n, 1), 3.0),
                                  s[:8], torch.zeros(1, 8, 1), gamma=0.99, steps=1500, reward_scale=scale, **FAST)
        assert abs(float(out["value"][0]) - 5.0) < 0.1


def test_batched_critics_are_independent():
    """Changing one policy's weights changes only that policy's Q values (no mixing across the leading dimension)."""
    q = BatchedQ(3, 4, 2, hidden=(8, 8))
    obs, act = torch.randn(3, 5, 4), torch.randn(3, 5, 2)
    before = q(obs, act)
    with torch.no_grad():
        q.weights[0][1].add_(1.0)
    after = q(obs, act)
    assert not torch.allclose(before[1], after[1])
    torch.testing.assert_close(before[[0, 2]], after[[0, 2]])


def test_shape_errors_say_what_is_expected():
    import pytest

    n = 8
    s = torch.zeros(n, 2)
    with pytest.raises(ValueError, match=r"next_action must be \[num_policies, 8, act_dim\]"):
        fitted_q_evaluation(s, torch.zeros(n, 1), torch.zeros(n), s, torch.zeros(n, dtype=torch.bool), torch.zeros(n, 1),
                            s[:2], torch.zeros(1, 2, 1))
    with pytest.raises(ValueError, match=r"start_action must be \[1, 2, act_dim\]"):
        fitted_q_evaluation(s, torch.zeros(n, 1), torch.zeros(n), s, torch.zeros(n, dtype=torch.bool), torch.zeros(1, n, 1),
                            s[:2], torch.zeros(2, 1))
