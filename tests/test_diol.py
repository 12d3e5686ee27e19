"""DIOL (UOF's high level): targets and loss on hand-computed cases."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_offhrl.objectives import DIOLLoss, uof_epsilon


def constant_loss(biases, target_biases, **kwargs):
    """A DIOL loss whose networks ignore the state: Q_j(s, .) = biases[j], Q'_j(s, .) = target_biases[j]."""
    net = TensorDictModule(torch.nn.Linear(2, 3), in_keys=["observation"], out_keys=["option_values"])
    loss = DIOLLoss(net, **kwargs)
    with torch.no_grad():
        for params, b in ((loss.value_network_params, biases), (loss.target_value_network_params, target_biases)):
            params["module", "weight"].data.zero_()
            params["module", "bias"].data.copy_(torch.tensor(b))
    return loss


def batch(option, met, reward, done):
    n = len(option)
    flags = torch.zeros(n, 3)
    flags[torch.arange(n), torch.tensor(option)] = torch.tensor(met, dtype=torch.float32)
    return TensorDict({
        "observation": torch.randn(n, 2), "option": torch.tensor(option),
        "next": {"observation": torch.randn(n, 2), "reward": torch.tensor(reward).unsqueeze(-1), "done": torch.tensor(done).unsqueeze(-1),
                 "achieved_goal": flags},
    }, batch_size=[n])


def test_targets_and_loss_by_hand():
    loss = constant_loss([[1.0, 2.0, 3.0], [0.0, 5.0, 1.0]], [[-1.0, -2.0, -3.0], [-2.0, -1.0, -4.0]])
    td = batch(option=[0, 1, 2], met=[1, 0, 1], reward=[-1.0, -1.0, 0.0], done=[False, False, True])
    # 0: option 0's sub-goal met -> max over options: min(-1, -1) = -1 -> -1 + 0.98 * -1
    # 1: not met -> the same option: min(-2, -1) = -2 -> -1 + 0.98 * -2
    # 2: done -> no bootstrap
    torch.testing.assert_close(loss.target(td), torch.tensor([-1.98, -2.96, 0.0]))
    out = loss(td)

    def smooth_l1(x):
        return 0.5 * x * x if abs(x) < 1 else abs(x) - 0.5

    net0 = sum(smooth_l1(q - y) for q, y in zip([1.0, 2.0, 3.0], [-1.98, -2.96, 0.0])) / 3
    net1 = sum(smooth_l1(q - y) for q, y in zip([0.0, 5.0, 1.0], [-1.98, -2.96, 0.0])) / 3
    torch.testing.assert_close(out["loss_qvalue"], torch.tensor(net0 + net1))
    torch.testing.assert_close(out["q_value"], torch.tensor((1 + 2 + 3 + 0 + 5 + 1) / 6))
    # gradients reach the trained networks only
    out["loss_qvalue"].backward()
    assert loss.value_network_params["module", "bias"].grad.abs().sum() > 0
    assert all(p.grad is None for p in loss.target_value_network_params.values(True, True))


def test_targets_are_clamped_and_the_soft_update_moves_the_targets():
    from torchrl.objectives import SoftUpdate

    loss = constant_loss([[0.0] * 3] * 2, [[-100.0] * 3] * 2)
    td = batch(option=[0, 1], met=[0, 0], reward=[5.0, -1.0], done=[True, False])
    torch.testing.assert_close(loss.target(td), torch.tensor([0.0, -50.0]))  # +5 -> 0; -1 + 0.98 * -100 -> -50
    unclamped = constant_loss([[0.0] * 3] * 2, [[-100.0] * 3] * 2, target_range=None)
    torch.testing.assert_close(unclamped.target(td), torch.tensor([5.0, -99.0]))
    updater = SoftUpdate(loss, tau=0.1)  # TorchRL's updater starts the targets as copies of the networks
    torch.testing.assert_close(loss.target_value_network_params["module", "bias"], torch.zeros(2, 3))
    with torch.no_grad():
        loss.target_value_network_params["module", "bias"].data.fill_(-100.0)
    updater.step()
    torch.testing.assert_close(loss.target_value_network_params["module", "bias"], torch.full((2, 3), -90.0))


def test_two_networks_are_independent_and_learn_a_fixed_point():
    """On a one-state chain with reward -1 and no sub-goal met, Q(o) converges to -1 / (1 - 0.98) (clamped at -50)."""
    from torchrl.objectives import SoftUpdate

    torch.manual_seed(0)
    net = TensorDictModule(torch.nn.Linear(2, 3), in_keys=["observation"], out_keys=["option_values"])
    loss = DIOLLoss(net, target_range=None)
    p = loss.value_network_params["module", "weight"]
    assert not torch.equal(p[0], p[1])  # the copies start apart (independent initialisation)
    updater = SoftUpdate(loss, tau=0.5)
    opt = torch.optim.Adam(loss.parameters(), lr=0.2)
    td = TensorDict({"observation": torch.ones(8, 2), "option": torch.arange(8) % 3,
                     "next": {"observation": torch.ones(8, 2), "reward": -torch.ones(8, 1), "done": torch.zeros(8, 1, dtype=torch.bool),
                              "achieved_goal": torch.zeros(8, 3)}}, batch_size=[8])
    for _ in range(800):
        opt.zero_grad()
        loss(td)["loss_qvalue"].backward()
        opt.step()
        updater.step()
    q = loss.option_values(td[:1], loss.value_network_params)
    torch.testing.assert_close(q, torch.full_like(q, -50.0), atol=1.0, rtol=0)


def test_uof_epsilon_schedule_and_bad_arguments():
    assert uof_epsilon(0) == 1.0 and abs(uof_epsilon(1e9) - 0.02) < 1e-12
    net = TensorDictModule(torch.nn.Linear(2, 3), in_keys=["observation"], out_keys=["option_values"])
    with pytest.raises(ValueError, match="loss_function"):
        DIOLLoss(net, loss_function="huber")
    with pytest.raises(ValueError, match="target_range"):
        DIOLLoss(net, target_range=(0.0, -50.0))
