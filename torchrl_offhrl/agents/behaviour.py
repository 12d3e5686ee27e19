"""The learner of a behaviour-policy run: online SAC (the SAC agents' update) or CrossQ, for the D4RL-style data's policies.

A behaviour-policy run (:func:`torchrl_offhrl.recipes.behaviour.train_behaviour`)
trains the actor format the shipped policies are read back in
(:func:`~torchrl_offhrl.data.policies.actors.make_behaviour_actor`, no
observation normalisation) with the losses, optimisers and update rule
here. Not a registered agent: it learns in the real env's actions, from its
own replay of a real env, and the recipe loop's settings (model env, latent
actions, dataset agents) do not apply to it.
"""
from __future__ import annotations

import torch
from torch import nn

from ..data.policies.actors import algorithm_defaults
from .sac import make_sac_loss, sac_step

__all__ = ["BehaviourLearner", "CrossQCritic"]


class CrossQCritic(nn.Module):
    """CrossQ's critic: batch renormalisation on the input and after each hidden layer, no target copy."""

    def __init__(self, in_dim: int, hidden, momentum: float = 0.01, warmup_steps: int = 10_000):
        from torchrl.modules import BatchRenorm1d

        super().__init__()
        layers: list[nn.Module] = [BatchRenorm1d(in_dim, momentum=momentum, warmup_steps=warmup_steps)]
        for h in hidden:
            layers += [nn.Linear(in_dim, h), BatchRenorm1d(h, momentum=momentum, warmup_steps=warmup_steps), nn.ReLU()]
            in_dim = h
        layers.append(nn.Linear(in_dim, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, observation, action):
        return self.net(torch.cat([observation, action], -1))


class BehaviourLearner:
    """The losses, optimisers and update rule of a behaviour-policy run (SAC or CrossQ) for one actor.

    The actor must already be on ``device``, where the critics are built.
    ``update(batch)`` does one critic update (and, every ``policy_delay``
    updates, one actor and temperature update). SAC's is the SAC agents'
    gradient step (:func:`~torchrl_offhrl.agents.sac.sac_step` on the loss
    of :func:`~torchrl_offhrl.agents.sac.make_sac_loss`, then the Polyak step
    of its target critics); the actor (:func:`~torchrl_offhrl.data.policies.actors.make_behaviour_actor`,
    the shipped policies' format), the critic widths and one Adam per part
    (with the algorithm's betas) are the behaviour runs' own. ``state_dict`` / ``load_state_dict``
    cover the networks, the temperature and the optimisers.
    """

    def __init__(self, actor, obs_dim: int, act_dim: int, action_spec, algorithm: str = "sac", critic_hidden=(256, 256), lr: float | None = None, gamma: float = 0.99, tau: float = 0.005, device=None):
        from torchrl.modules import MLP, ValueOperator
        from torchrl.objectives import CrossQLoss

        algo = algorithm_defaults(algorithm)
        self.algorithm = algorithm
        self.policy_delay = algo["policy_delay"]
        lr = algo["lr"] if lr is None else lr
        if algorithm == "sac":
            qnet = MLP(in_features=obs_dim + act_dim, out_features=1, num_cells=list(critic_hidden), activation_class=nn.ReLU)
            qvalue = ValueOperator(qnet, in_keys=["observation", "action"]).to(device)
            self.loss, self.target_updater = make_sac_loss(actor, qvalue, action_spec, gamma=gamma, tau=tau)
        else:
            qvalue = ValueOperator(CrossQCritic(obs_dim + act_dim, critic_hidden), in_keys=["observation", "action"]).to(device)
            self.loss = CrossQLoss(actor, qvalue, num_qvalue_nets=2, loss_function="l2", action_spec=action_spec)
            self.target_updater = None
            self.loss.make_value_estimator(gamma=gamma)
        adam = lambda params: torch.optim.Adam(params, lr=lr, betas=algo["betas"])
        self.opt_actor = adam(self.loss.actor_network_params.flatten_keys().values())
        self.opt_q = adam(self.loss.qvalue_network_params.flatten_keys().values())
        self.opt_alpha = adam([self.loss.log_alpha])
        self.updates = 0

    def update(self, batch) -> None:
        self.updates += 1
        if self.algorithm == "sac":
            sac_step(self.loss, batch, (self.opt_q, self.opt_actor, self.opt_alpha), self.target_updater)
            return
        loss_q, _ = self.loss.qvalue_loss(batch)
        self._step((self.opt_q,), loss_q)
        if self.updates % self.policy_delay == 0:
            loss_pi, meta = self.loss.actor_loss(batch)
            self._step((self.opt_actor, self.opt_alpha), loss_pi + self.loss.alpha_loss(meta["log_prob"]))

    @staticmethod
    def _step(opts, total) -> None:
        for opt in opts:
            opt.zero_grad()
        total.backward()
        for opt in opts:
            opt.step()

    def state_dict(self) -> dict:
        return {
            "loss": self.loss.state_dict(),
            "opt_actor": self.opt_actor.state_dict(),
            "opt_q": self.opt_q.state_dict(),
            "opt_alpha": self.opt_alpha.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict) -> None:
        self.loss.load_state_dict(state["loss"])
        for key in ("opt_actor", "opt_q", "opt_alpha"):
            getattr(self, key).load_state_dict(state[key])
        self.updates = state["updates"]
