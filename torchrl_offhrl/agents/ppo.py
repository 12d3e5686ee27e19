"""PPO (TorchRL :class:`~torchrl.objectives.ClipPPOLoss`) with a tanh-Gaussian actor and a state-value critic."""
from __future__ import annotations

from collections.abc import Sequence

from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.objectives import ClipPPOLoss

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
        self.loss = ClipPPOLoss(
            self.policy,
            critic,
            clip_epsilon=clip_epsilon,
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
