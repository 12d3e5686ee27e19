"""Deep intra-option Q-learning (DIOL): the high level of the Universal Option Framework (UOF).

UOF's high level learns ``Q(s, g, o)``: for the state and the one-hot goal
``g``, one value per option (each option pursues one sub-goal). As the
official UOF code runs it (``agent/universal_option_framework.py``, see the
reference notes): two Q networks with target copies; for a transition in
which option ``o`` ran, the target is

    U_j = (1 - b) Q'_j(s', g, o) + b max_o' Q'_j(s', g, o'),   b = 1 when o's sub-goal is met at s'
    y   = r_H + gamma (1 - done) min(U_1, U_2),   clamped to [-50, 0]

(intra-option: the option continues unless its sub-goal is met, where the
high level picks again), and each network regresses ``Q_j(s, g, o)`` on
``y`` with the smooth-L1 loss. ``done`` is the key that stops the bootstrap
(UOF: the time limit). Target networks follow with TorchRL's
``SoftUpdate`` (UOF: ``tau = 0.1`` after every update).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule
from torchrl.objectives.utils import _vmap_func

__all__ = ["DIOLLoss", "uof_epsilon"]


def uof_epsilon(episode: int | float, floor: float = 0.02, decay_episodes: float = 30000.0) -> float:
    """UOF's exploration rate of the high level after ``episode`` episodes: ``0.02 + 0.98 exp(-episode / 30000)``.

    Examples:
        >>> uof_epsilon(0), round(uof_epsilon(30000), 4)
        (1.0, 0.3805)
    """
    return floor + (1.0 - floor) * math.exp(-float(episode) / decay_episodes)


class DIOLLoss(LossModule):
    """UOF's high-level loss: double intra-option Q-learning over options, conditioned on the goal (module docstring).

    Args:
        value_network: a TensorDict module writing ``option_values``
            (``[..., num_options]``) from the state and the goal (e.g.
            ``in_keys=["observation", "desired_goal"]``); copied
            ``num_qvalue_nets`` times with independent parameters, and into
            target copies.
        num_options: the number of options (default: the size of the
            network's output, read on the first call).
        num_qvalue_nets: 2 (UOF).
        gamma: 0.98 (UOF).
        target_range: ``(low, high)`` the targets are clamped to (UOF:
            ``(-50, 0)``, the returns' range under rewards in ``{-1, 0}`` and
            gamma 0.98); ``None`` for no clamping.
        loss_function: ``"smooth_l1"`` (UOF) or ``"l2"``.

    Reads ``option`` (the option that ran at s, ``[...]`` int), the network's
    in-keys at s and at s' (``("next", ...)``), ``("next", reward)`` (the
    high level's reward), ``("next", done)`` and ``("next", achieved_goal)``
    (success flags of every sub-goal at s'; index ``o`` is option ``o``'s).
    Returns ``loss_qvalue`` and the metrics ``q_value`` (mean of the taken
    option's values) and ``target_value``.
    """

    @dataclass
    class _AcceptedKeys:
        """Keys read by the loss; change them with :meth:`set_keys`."""

        option_values: NestedKey = "option_values"
        option: NestedKey = "option"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        achieved_goal: NestedKey = "achieved_goal"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(self, value_network: TensorDictModule, *, num_options: int | None = None, num_qvalue_nets: int = 2, gamma: float = 0.98,
                 target_range: tuple[float, float] | None = (-50.0, 0.0), loss_function: str = "smooth_l1"):
        super().__init__()
        if loss_function not in ("smooth_l1", "l2"):
            raise ValueError(f"loss_function must be 'smooth_l1' or 'l2', got {loss_function!r}")
        if num_qvalue_nets < 1:
            raise ValueError(f"num_qvalue_nets must be >= 1, got {num_qvalue_nets}")
        if target_range is not None and not target_range[0] < target_range[1]:
            raise ValueError(f"target_range must be (low, high) with low < high, got {target_range}")
        self.num_qvalue_nets = int(num_qvalue_nets)
        self.num_options = num_options
        self.gamma = float(gamma)
        self.target_range = None if target_range is None else (float(target_range[0]), float(target_range[1]))
        self.loss_function = loss_function
        self.convert_to_functional(value_network, "value_network", expand_dim=self.num_qvalue_nets, create_target_params=True)
        self._vmap_values = _vmap_func(self.value_network, (None, 0))
        self.set_keys(option_values=value_network.out_keys[0])
        self._network_in_keys = list(value_network.in_keys)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        k = self.tensor_keys
        return [*self._network_in_keys, k.option, *[("next", key) for key in self._network_in_keys],
                ("next", k.reward), ("next", k.done), ("next", k.achieved_goal)]

    @property
    def out_keys(self):
        return ["loss_qvalue", "q_value", "target_value"]

    def option_values(self, tensordict: TensorDictBase, params) -> torch.Tensor:
        """``[num_qvalue_nets, ..., num_options]``: every network's option values at the states of ``tensordict``."""
        out = self._vmap_values(tensordict.select(*self._network_in_keys), params)
        return out.get(self.tensor_keys.option_values)

    @torch.no_grad()
    def target(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``[...]`` the clamped intra-option targets ``y`` (no gradient)."""
        k = self.tensor_keys
        nxt = tensordict.get("next")
        option = tensordict.get(k.option).long()
        q_next = self.option_values(nxt, self.target_value_network_params)  # [J, ..., O]
        idx = option.unsqueeze(-1).expand(q_next.shape[0], *option.shape, 1)
        continuing = q_next.gather(-1, idx).squeeze(-1)
        flags = nxt.get(k.achieved_goal)
        met = flags.gather(-1, option.unsqueeze(-1)).squeeze(-1) > 0.5
        u = torch.where(met, q_next.max(-1).values, continuing).min(0).values
        reward = nxt.get(k.reward).reshape(option.shape).to(u.dtype)
        done = nxt.get(k.done).reshape(option.shape)
        y = reward + self.gamma * (~done).to(u.dtype) * u
        if self.target_range is not None:
            y = y.clamp(*self.target_range)
        return y

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        k = self.tensor_keys
        option = tensordict.get(k.option).long()
        q = self.option_values(tensordict, self.value_network_params)  # [J, ..., O]
        if self.num_options is None:
            self.num_options = q.shape[-1]
        q_taken = q.gather(-1, option.unsqueeze(-1).expand(q.shape[0], *option.shape, 1)).squeeze(-1)
        y = self.target(tensordict).expand_as(q_taken)
        if self.loss_function == "smooth_l1":
            per = torch.nn.functional.smooth_l1_loss(q_taken, y, reduction="none")
        else:
            per = (q_taken - y).pow(2)
        loss = per.flatten(1).mean(1).sum()  # each network's mean loss, summed over the networks
        return TensorDict({"loss_qvalue": loss, "q_value": q_taken.detach().mean(), "target_value": y[0].mean()}, batch_size=[])
