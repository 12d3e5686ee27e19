"""DDPG with twin critics and clamped targets: the low level of the Universal Option Framework (UOF).

As the official UOF code runs its low level (``agent/universal_option_framework.py``,
see the reference notes): a deterministic actor ``pi(s, g)`` on the state
and the low-level goal (the sub-goal), two critics ``Q_j(s, g, a)`` with
target copies of the actor and the critics, and

    y = r + gamma (1 - done) min_j Q'_j(s', g, pi'(s', g)),   clamped to [-25, 0]
    loss_qvalue = sum_j mean (Q_j(s, g, a) - y)^2
    loss_actor  = -mean min_j Q_j(s, g, pi(s, g))

``done`` is the low level's end: the sub-goal met at s' (UOF) or an episode
end that stops the bootstrap. Why not TorchRL's ``TD3Loss``: it smooths the
target policy with noise, delays the actor and scores the actor with the
first critic only, and has no target clamping; UOF does none of the first
three and relies on the last (the returns of rewards in ``{-1, 0}`` with
``gamma = 0.98`` over 25 steps lie in ``[-25, 0]``). Target networks follow
with TorchRL's ``SoftUpdate`` (UOF: ``tau = 0.1`` after every update).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule
from torchrl.objectives.utils import _vmap_func

__all__ = ["TwinDDPGLoss"]


class TwinDDPGLoss(LossModule):
    """UOF's low-level loss (module docstring): deterministic actor, twin critics, clamped TD(0) targets.

    Args:
        actor_network: a TensorDict module writing the action (``action_key``)
            from the state and the goal.
        qvalue_network: a TensorDict module writing ``state_action_value``
            from the state, the goal and the action; copied twice with
            independent parameters (``num_qvalue_nets``).
        num_qvalue_nets: 2 (UOF).
        gamma: 0.98 (UOF).
        target_range: ``(low, high)`` the targets are clamped to (UOF
            ``(-25, 0)``); ``None`` for no clamping.

    Reads the networks' in-keys at s and at s' (``("next", ...)``), the
    action and ``("next", reward)``, ``("next", done)`` (rename them with
    :meth:`set_keys`, e.g. to the low level's own reward). Returns
    ``loss_actor``, ``loss_qvalue`` and the metrics ``q_value`` and
    ``target_value``.
    """

    @dataclass
    class _AcceptedKeys:
        """Keys read by the loss; change them with :meth:`set_keys`."""

        action: NestedKey = "action"
        state_action_value: NestedKey = "state_action_value"
        reward: NestedKey = "reward"
        done: NestedKey = "done"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    actor_network: TensorDictModule
    qvalue_network: TensorDictModule
    actor_network_params: TensorDictParams
    qvalue_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(self, actor_network: TensorDictModule, qvalue_network: TensorDictModule, *, num_qvalue_nets: int = 2, gamma: float = 0.98,
                 target_range: tuple[float, float] | None = (-25.0, 0.0)):
        super().__init__()
        if num_qvalue_nets < 1:
            raise ValueError(f"num_qvalue_nets must be >= 1, got {num_qvalue_nets}")
        if target_range is not None and not target_range[0] < target_range[1]:
            raise ValueError(f"target_range must be (low, high) with low < high, got {target_range}")
        self.num_qvalue_nets = int(num_qvalue_nets)
        self.gamma = float(gamma)
        self.target_range = None if target_range is None else (float(target_range[0]), float(target_range[1]))
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        self.convert_to_functional(qvalue_network, "qvalue_network", expand_dim=self.num_qvalue_nets, create_target_params=True)
        self._vmap_q = _vmap_func(self.qvalue_network, (None, 0))
        self.set_keys(action=actor_network.out_keys[-1], state_action_value=qvalue_network.out_keys[0])
        self._actor_in = list(actor_network.in_keys)
        self._q_in = list(qvalue_network.in_keys)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        k = self.tensor_keys
        state = [key for key in dict.fromkeys([*self._actor_in, *self._q_in]) if key != k.action]
        return [*state, k.action, *[("next", key) for key in state], ("next", k.reward), ("next", k.done)]

    @property
    def out_keys(self):
        return ["loss_actor", "loss_qvalue", "q_value", "target_value"]

    def _act(self, td: TensorDictBase, params) -> torch.Tensor:
        with params.to_module(self.actor_network):
            return self.actor_network(td.select(*self._actor_in, strict=False).copy()).get(self.tensor_keys.action)

    def _q(self, td: TensorDictBase, action: torch.Tensor, params) -> torch.Tensor:
        """``[J, ...]`` every critic's value of ``action`` at the states of ``td``."""
        k = self.tensor_keys
        sub = td.select(*[key for key in self._q_in if key != k.action]).copy()
        sub.set(k.action, action)
        return self._vmap_q(sub, params).get(k.state_action_value).squeeze(-1)

    @torch.no_grad()
    def target(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``[...]`` the clamped targets ``y`` (no gradient)."""
        k = self.tensor_keys
        nxt = tensordict.get("next")
        q_next = self._q(nxt, self._act(nxt, self.target_actor_network_params), self.target_qvalue_network_params).min(0).values
        reward = nxt.get(k.reward).reshape(q_next.shape).to(q_next.dtype)
        done = nxt.get(k.done).reshape(q_next.shape).bool()
        y = reward + self.gamma * (~done).to(q_next.dtype) * q_next
        if self.target_range is not None:
            y = y.clamp(*self.target_range)
        return y

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        k = self.tensor_keys
        q = self._q(tensordict, tensordict.get(k.action), self.qvalue_network_params)  # [J, ...]
        y = self.target(tensordict)
        loss_q = (q - y).pow(2).flatten(1).mean(1).sum()
        # the actor is scored by critics that do not learn from this term
        q_pi = self._q(tensordict, self._act(tensordict, self.actor_network_params), self.qvalue_network_params.detach())
        loss_actor = -q_pi.min(0).values.mean()
        return TensorDict({"loss_actor": loss_actor, "loss_qvalue": loss_q, "q_value": q.detach().mean(), "target_value": y.mean()}, batch_size=[])
