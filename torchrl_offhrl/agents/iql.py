"""Implicit Q-Learning (TorchRL :class:`~torchrl.objectives.IQLLoss`): model-free offline RL on the dataset itself."""
from __future__ import annotations

from collections.abc import Sequence

from torchrl.modules import ValueOperator
from torchrl.objectives import SoftUpdate, group_optimizers

from ..nets import NormalizedMLP
from ..objectives import SharedPassIQLLoss
from .base import (DatasetAgent, adam, backward, compile_setting, gaussian_actor, q_network, scalar_metrics, sum_losses,
                   tanh_mean_gaussian_actor)
from .registry import register_agent

__all__ = ["IQLAgent"]


@register_agent("iql")
class IQLAgent(DatasetAgent):
    """IQL (Kostrikov et al., 2022): expectile value regression, twin Q, advantage-weighted tanh-Gaussian actor.

    One update is one gradient step of every loss on a minibatch of the
    dataset, then the Polyak step of the target Q networks, as TorchRL's
    ``sota-implementations/iql/iql_offline.py``. Hyper-parameters
    (``configs/algo/iql.yaml``) are that script's and the IQL paper's for the
    D4RL locomotion tasks: expectile 0.7, temperature 3.0, lr 3e-4, batch 256,
    tau 0.005, MLP(256, 256); the config scales rewards by ``1000 / (max - min
    episode return)`` (``reward_scale: return_range``, the IQL paper's
    normalisation; the class itself takes a number, default 1).

    The loss's hyper-parameters (:attr:`loss_hyperparameters`: ``expectile``,
    ``temperature``, ``loss_function``) are not arguments of the agent: they
    go to TorchRL's :class:`~torchrl.objectives.IQLLoss` unchanged
    (``**loss_kwargs``), documented and typed there; :attr:`loss_defaults`
    holds the values here that differ from the loss's own.

    Examples:
        >>> from torchrl_offhrl.data import make_gym_env
        >>> agent = IQLAgent(make_gym_env("Pendulum-v1"), hidden_sizes=(32,), batch_size=8)
        >>> sorted(k for k in agent.loss.state_dict() if k.endswith("0.weight"))[:1]
        ['actor_network_params.module.0.module.0.net.0.weight']
    """

    #: the loss the agent trains (TorchRL's IQLLoss, each network pass computed once: the same losses and gradients), and
    #: the arguments of it a config sets (the rest are TorchRL's plumbing, left at its defaults)
    loss_class = SharedPassIQLLoss
    loss_hyperparameters: tuple = ("expectile", "temperature", "loss_function")
    #: the IQL paper's locomotion values and TorchRL's sota script's loss (the loss's defaults: 0.5, 1.0, smooth_l1)
    loss_defaults: dict = {"expectile": 0.7, "temperature": 3.0, "loss_function": "l2"}

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "action",
        device="cpu",
        hidden_sizes: Sequence[int] = (256, 256),
        lr: float = 3e-4,
        gamma: float = 0.99,
        tau: float = 0.005,
        batch_size: int = 256,
        reward_scale: float = 1.0,
        default_policy_scale: float = 1.0,
        scale_lb: float = 0.1,
        actor: str = "tanh_normal",
        log_std_min: float = -5.0,
        fused_adam: bool = True,
        compile: bool | str = False,
        cudagraphs: bool = False,
        **loss_kwargs,
    ):
        self.compile = compile_setting(compile)
        self.cudagraphs = bool(cudagraphs)
        obs_dim = env.observation_spec["observation"].shape[-1]
        if actor == "tanh_normal":
            self.policy = gaussian_actor(env, action_key, hidden_sizes, obs_loc, obs_scale, default_policy_scale, scale_lb)
        elif actor == "tanh_mean_gaussian":
            self.policy = tanh_mean_gaussian_actor(env, action_key, hidden_sizes, obs_loc, obs_scale, log_std_min)
        else:
            raise ValueError(f"IQLAgent: actor={actor!r} is not one of 'tanh_normal' (TorchRL's sota script: a tanh-Gaussian, "
                             "state-dependent scale) or 'tanh_mean_gaussian' (the IQL paper's: a Gaussian around a squashed mean, "
                             "one learned scale per action dimension)")
        qvalue = q_network(env, action_key, hidden_sizes, obs_loc, obs_scale)
        value = ValueOperator(NormalizedMLP(obs_dim, 0, 1, list(hidden_sizes), "relu", obs_loc, obs_scale), in_keys=["observation"],
                              out_keys=["state_value"])
        self.loss = self.loss_class(self.policy, qvalue, value, num_qvalue_nets=2, **{**self.loss_defaults, **loss_kwargs})
        self.loss.set_keys(action=action_key)
        self.loss.make_value_estimator(gamma=gamma)
        self.target_updater = SoftUpdate(self.loss, tau=tau)
        self.optimizer = group_optimizers(
            adam(self.loss.actor_network_params.flatten_keys().values(), lr=lr, fused=fused_adam),
            adam(self.loss.qvalue_network_params.flatten_keys().values(), lr=lr, fused=fused_adam),
            adam(self.loss.value_network_params.flatten_keys().values(), lr=lr, fused=fused_adam),
        )
        self.action_key = action_key
        self.set_sampling(batch_size, reward_scale)

    def step(self, batch, variant=None):
        out = self.loss_fn()(batch)
        self.optimizer.zero_grad()
        backward(sum_losses(out))
        self.optimizer.step()
        self.target_updater.step()
        return scalar_metrics(out)
