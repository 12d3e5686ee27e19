"""PPO (TorchRL :class:`~torchrl.objectives.ClipPPOLoss`) with a tanh-Gaussian actor and a state-value critic."""
from __future__ import annotations

import warnings
from collections.abc import Sequence

import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives import BCLoss, ClipPPOLoss, KLPENPPOLoss

from ..nets import NormalizedMLP, tanh_gaussian_actor
from .base import OnPolicyAgent, action_box, adam
from .registry import register_agent

__all__ = ["PPOAgent"]


@register_agent("ppo")
class PPOAgent(OnPolicyAgent):
    """PPO with GAE; the paper's values are in ``configs/algo/ppo.yaml`` (lr and clip per env in ``configs/env/``).

    Speed switches (the same algorithm either way): ``fused_adam`` (one fused
    Adam kernel, see :func:`~torchrl_offhrl.agents.adam`) and ``functional``
    (TorchRL's functionalised loss; ``False`` calls the networks directly).

    ``loss_type``: ``"clip"`` (PPO's clipped ratio, TorchRL's
    :class:`~torchrl.objectives.ClipPPOLoss`) or ``"kl"`` (PPO's adaptive KL
    penalty, TorchRL's :class:`~torchrl.objectives.KLPENPPOLoss`, with target
    ``kl_target``: a trust region on the policy's KL divergence per batch,
    this library's stand-in for MOReL's natural policy gradient, whose step
    is also bounded in KL).

    ``bc_init_steps`` (0: off): before training from scratch
    (:meth:`pretrain`), that many Adam steps of behaviour cloning (TorchRL's
    :class:`~torchrl.objectives.BCLoss`: the actor's negative log-likelihood
    of the dataset's actions, minibatches of ``bc_init_batch_size``, step
    size ``bc_init_lr``), as MOReL initialises its policy. It clones the
    dataset's real actions, so the agent must act in them
    (``ablation.no_cvae=true``); the critic starts untrained.
    """

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "latent_action",
        device="cpu",
        hidden_sizes: Sequence[int] = (64, 64),
        activation: str = "tanh",
        lr: float = 3e-4,
        clip_epsilon: float = 0.2,
        vf_coef: float = 0.5,
        ent_coef: float = 0.0,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        frames_per_batch: int = 2048,
        epochs: int = 10,
        minibatch_size: int = 64,
        max_grad_norm: float | None = 0.5,
        fused_adam: bool = True,
        functional: bool = False,
        compile: bool | str = False,
        anneal_lr: bool = False,
        loss_type: str = "clip",
        kl_target: float = 0.01,
        bc_init_steps: int = 0,
        bc_init_lr: float = 1e-3,
        bc_init_batch_size: int = 256,
    ):
        super().__init__(frames_per_batch=frames_per_batch, epochs=epochs, minibatch_size=minibatch_size, max_grad_norm=max_grad_norm, compile=compile, anneal_lr=anneal_lr)
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim, low, high = action_box(env, action_key)
        hidden = list(hidden_sizes)
        net = nn.Sequential(
            NormalizedMLP(obs_dim, 0, act_dim, hidden, activation, obs_loc, obs_scale),
            AddStateIndependentNormalScale(act_dim, scale_lb=1e-4),
        )
        self.policy = tanh_gaussian_actor(TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]), low, high, action_key)
        critic = ValueOperator(NormalizedMLP(obs_dim, 0, 1, hidden, activation, obs_loc, obs_scale), in_keys=["observation"])
        if loss_type not in ("clip", "kl"):
            raise ValueError(f"algo.loss_type must be 'clip' (PPO's clipped ratio) or 'kl' (its adaptive KL penalty), got {loss_type!r}")
        if int(bc_init_steps) < 0:
            raise ValueError(f"algo.bc_init_steps must be >= 0 (0: no behaviour-cloning start), got {bc_init_steps}")
        self.bc_init = {"steps": int(bc_init_steps), "lr": float(bc_init_lr), "batch_size": int(bc_init_batch_size)}
        loss_class, trust = (ClipPPOLoss, {"clip_epsilon": clip_epsilon}) if loss_type == "clip" else (KLPENPPOLoss, {"dtarg": float(kl_target)})
        self.loss = loss_class(
            self.policy,
            critic,
            **trust,
            entropy_coeff=ent_coef,
            critic_coeff=vf_coef,
            loss_critic_type="l2",  # squared error, as SB3 (whose values the paper took) and as MOC's critic
            normalize_advantage=True,
            functional=functional,  # False: the networks are called directly, not through a copy of their parameters (faster, same maths)
        )
        self.loss.set_keys(action=action_key, sample_log_prob=f"{action_key}_log_prob")
        self.loss.make_value_estimator(gamma=gamma, lmbda=lmbda)
        self.optimizer = adam(self.loss.parameters(), lr=lr, fused=fused_adam)
        self.action_key = action_key

    def pretrain(self, data) -> dict:
        """MOReL's start: behaviour cloning of the dataset's actions (``bc_init_steps`` Adam steps; nothing when 0)."""
        steps = self.bc_init["steps"]
        if not steps:
            return {}
        if self.action_key not in data:
            raise ValueError(f"algo.bc_init_steps clones the dataset's actions, but this agent acts in {self.action_key!r}, which the "
                             "dataset does not hold: give ablation.no_cvae=true (act in real actions), or algo.bc_init_steps=0")
        with warnings.catch_warnings():  # TorchRL's BCLoss notes an attribute its annotations lack; nothing to act on
            warnings.filterwarnings("ignore", message="The name target_actor_network_params")
            bc = BCLoss(self.policy)
        bc.set_keys(action=self.action_key)
        opt = adam(self.policy.parameters(), lr=self.bc_init["lr"], fused=False)
        device = next(self.policy.parameters()).device
        n, size = len(data), min(self.bc_init["batch_size"], len(data))
        first = last = None
        for _ in range(steps):
            idx = torch.randint(n, (size,))
            batch = data[idx].select("observation", self.action_key).to(device)
            loss = bc(batch)["loss_bc"]
            opt.zero_grad()
            loss.backward()
            opt.step()
            last = float(loss.detach())
            first = last if first is None else first
        return {"bc_init_steps": steps, "bc_init_nll_first": first, "bc_init_nll_last": last}
