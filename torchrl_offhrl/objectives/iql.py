"""TorchRL's IQL loss with each network pass of a minibatch computed once (:class:`SharedPassIQLLoss`)."""
from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import IQLLoss

__all__ = ["SharedPassIQLLoss"]

_PARAMS = ("actor_network_params", "qvalue_network_params", "value_network_params", "target_actor_network_params",
           "target_qvalue_network_params", "target_value_network_params")


class SharedPassIQLLoss(IQLLoss):
    """:class:`~torchrl.objectives.IQLLoss`, the same three losses from fewer forward passes.

    TorchRL's ``forward`` calls ``actor_loss``, ``qvalue_loss`` and
    ``value_loss``, and two of them need the same two quantities: the
    target critics' ``min Q(s, a)`` (the advantage's first term and the
    expectile regression's target) and ``V(s)`` (the advantage's baseline,
    without its gradient, and the expectile regression's prediction, with
    it). Each is computed twice there, once per method. Here ``forward``
    computes them once and hands them to both terms: one twin-critic pass and
    one value pass fewer per update, about a sixth of an update's matrix
    products at the IQL paper's widths (``benchmarks/peer_updates.py``).

    Everything else is the parent's: constructor, keys, parameters and
    targets, value estimator (``qvalue_loss`` is called as it is), and the
    arithmetic of each term, so the losses, and their gradients, are equal to
    ``IQLLoss``'s on the same minibatch (``tests/test_agents.py`` checks both,
    to the last bit on this CPU). The individual methods (``actor_loss``, ...)
    still compute their terms alone, as the parent's do.
    """

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        min_q, value = self._target_min_q(tensordict), self._state_value(tensordict)
        loss_actor = self._actor_term(tensordict, min_q, value.detach())
        loss_qvalue, metadata = self.qvalue_loss(tensordict)
        loss_value = self._reduce_loss(self.loss_value_diff(min_q - value, self.expectile), tensordict=tensordict)
        tensordict.set(self.tensor_keys.priority, metadata.pop("td_error").detach().max(0).values)
        entropy = -tensordict.get(self.tensor_keys.log_prob).detach()
        out = {"loss_actor": loss_actor, "loss_qvalue": loss_qvalue, "loss_value": loss_value}
        if self.reduction == "none":
            td_out = TensorDict(out, batch_size=tensordict.batch_size)
            if self.scalar_output_mode == "non_tensor":
                td_out.set_non_tensor("entropy", entropy.mean())
        else:
            td_out = TensorDict({**out, "entropy": entropy.mean()})
        self._clear_weakrefs(tensordict, td_out, *_PARAMS)
        return td_out

    def _target_min_q(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The target critics' smallest ``Q(s, a)`` on the minibatch's pairs (no gradient: target parameters)."""
        td_q = self._vmap_qvalue_networkN0(tensordict.select(*self.qvalue_network.in_keys, strict=False), self.target_qvalue_network_params)
        return td_q.get(self.tensor_keys.state_action_value).min(0)[0].squeeze(-1)

    def _state_value(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``V(s)`` with its gradient (the value network's current parameters)."""
        td_v = tensordict.select(*self.value_network.in_keys, strict=False)
        with self.value_network_params.to_module(self.value_network, preserve_module_state=False):
            self.value_network(td_v)
        return td_v.get(self.tensor_keys.value).squeeze(-1)

    def _actor_term(self, tensordict: TensorDictBase, min_q: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
        """The advantage-weighted log-likelihood of the minibatch's actions, weights ``exp(temperature (Q - V))`` capped at 100;
        the log-likelihood is written to ``tensordict`` (the entropy the loss reports)."""
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            dist = self.actor_network.get_dist(tensordict)
        log_prob = dist.log_prob(tensordict[self.tensor_keys.action])
        if log_prob.shape != min_q.shape:
            raise RuntimeError(f"SharedPassIQLLoss: the actor's log-likelihood has shape {tuple(log_prob.shape)} and the critics' "
                               f"values {tuple(min_q.shape)}: the actor and the critics must see the same batch")
        weight = torch.exp((min_q - value) * self.temperature).clamp_max(100)
        tensordict.set(self.tensor_keys.log_prob, log_prob.detach())
        return self._reduce_loss(-(weight * log_prob), tensordict=tensordict)
