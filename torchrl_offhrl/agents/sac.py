"""Soft Actor-Critic (TorchRL :class:`~torchrl.objectives.SACLoss`): off-policy, from a replay buffer of collected frames."""
from __future__ import annotations

from collections.abc import Sequence

from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.modules import ValueOperator
from torchrl.objectives import SACLoss, group_optimizers

from ..nets import NormalizedMLP, tanh_gaussian_actor
from .base import Agent, MetricMeans, action_box, adam, backward, compile_setting, sum_losses
from .registry import register_agent

__all__ = ["SACAgent", "make_sac_loss", "sac_optimizer", "sac_step"]


def make_sac_loss(actor, qvalue, action_spec, gamma: float = 0.99, tau: float = 0.005, action_key: str = "action", **loss_kwargs):
    """TorchRL's :class:`~torchrl.objectives.SACLoss` as this project uses it, and its Polyak target updater.

    Two Q networks, squared-error critic loss, target critics (not a target
    actor) updated with ``tau``, the default target entropy
    ``-(action elements)`` of ``action_spec`` (one env's, unbatched). Shared
    by :class:`SACAgent`, :class:`~torchrl_offhrl.agents.sac_her.SACHERAgent`
    and the behaviour-policy learner
    (:class:`~torchrl_offhrl.agents.behaviour.BehaviourLearner`). Returns
    ``(loss, target_updater)``. ``loss_kwargs``: the loss's hyper-parameters
    (``alpha_init``, ...), passed to it as they are.
    """
    from torchrl.objectives import SoftUpdate

    loss = SACLoss(
        actor, qvalue, num_qvalue_nets=2, loss_function="l2", delay_actor=False, delay_qvalue=True,
        action_spec=action_spec, **loss_kwargs,
    )
    loss.set_keys(action=action_key)
    loss.make_value_estimator(gamma=gamma)
    return loss, SoftUpdate(loss, tau=tau)


def sac_step(loss_fn, minibatch, optimizers, target_updater):
    """SAC's gradient step, the one every SAC trainer of the project takes; returns the losses.

    One forward of the three losses (``loss_fn(minibatch)``: TorchRL's
    ``SACLoss`` detaches the critic in the actor loss and the log-prob in the
    temperature loss, so their sum steps each part on its own loss), one
    backward of the sum, a step of each optimiser in ``optimizers`` (one
    grouped optimiser, as :func:`sac_optimizer` makes, or one per part), then
    the Polyak step of the target critics.
    """
    out = loss_fn(minibatch)
    for opt in optimizers:
        opt.zero_grad()
    backward(sum_losses(out))  # a seeds' batch: each seed's loss, summed
    for opt in optimizers:
        opt.step()
    target_updater.step()
    return out


def sac_optimizer(loss, lr: float, fused_adam: bool = True):
    """One optimiser over a ``SACLoss``'s actor, critics and temperature (TorchRL's ``group_optimizers`` of one Adam each)."""
    return group_optimizers(
        adam(loss.actor_network_params.flatten_keys().values(), lr=lr, fused=fused_adam),
        adam(loss.qvalue_network_params.flatten_keys().values(), lr=lr, fused=fused_adam),
        adam([loss.log_alpha], lr=lr, fused=fused_adam),
    )


@register_agent("sac")
class SACAgent(Agent):
    """SAC with twin target critics (standard defaults, as Stable-Baselines3 which the paper used).

    Each collected batch goes into the replay buffer; once
    ``init_random_frames`` frames were collected (uniformly random actions),
    every collected frame buys ``utd_ratio`` gradient steps on minibatches of
    ``batch_size``, each followed by the Polyak update of the target critics.

    The loss's hyper-parameter (:attr:`loss_hyperparameters`: the entropy
    temperature's start ``alpha_init``) is not an argument of the agent: it
    reaches TorchRL's :class:`~torchrl.objectives.SACLoss` unchanged
    (``**loss_kwargs``), documented there.
    """

    loss_class = SACLoss
    loss_hyperparameters: tuple = ("alpha_init",)

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "latent_action",
        device="cpu",
        hidden_sizes: Sequence[int] = (256, 256),
        lr: float = 3e-4,
        gamma: float = 0.99,
        tau: float = 0.005,
        batch_size: int = 256,
        buffer_size: int = 1_000_000,
        init_random_frames: int = 5000,
        utd_ratio: float = 1.0,
        frames_per_batch: int = 64,
        fused_adam: bool = True,
        compile: bool | str = False,
        **loss_kwargs,
    ):
        self.compile = compile_setting(compile)
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim, low, high = action_box(env, action_key)
        hidden = list(hidden_sizes)
        net = nn.Sequential(NormalizedMLP(obs_dim, 0, 2 * act_dim, hidden, "relu", obs_loc, obs_scale), NormalParamExtractor())
        self.policy = tanh_gaussian_actor(TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]), low, high, action_key)
        qnet = NormalizedMLP(obs_dim, act_dim, 1, hidden, "relu", obs_loc, obs_scale)
        qvalue = ValueOperator(qnet, in_keys=["observation", action_key], out_keys=["state_action_value"])
        # the unbatched spec: the default target entropy is -(action elements), per env
        self.loss, self.target_updater = make_sac_loss(
            self.policy, qvalue, env.full_action_spec_unbatched[action_key], gamma=gamma, tau=tau, action_key=action_key, **loss_kwargs,
        )
        self.optimizer = sac_optimizer(self.loss, lr, fused_adam)
        self.action_key = action_key
        self.frames_per_batch = int(frames_per_batch)
        self.init_random_frames = int(init_random_frames)
        self.utd_ratio = float(utd_ratio)
        self.replay_buffer = ReplayBuffer(storage=LazyTensorStorage(int(buffer_size), device=device), batch_size=int(batch_size))
        self.frames = 0

    def update(self, batch):
        self.store(batch)
        return self.gradient_steps(batch.numel(), self.minibatch)

    def store(self, batch) -> None:
        """Add a collected batch (any batch shape) to the replay buffer."""
        self.replay_buffer.extend(batch.reshape(-1))

    def minibatch(self):
        """One minibatch of ``batch_size`` for a gradient step (SAC: from the replay buffer)."""
        return self.replay_buffer.sample()

    def gradient_steps(self, frames: int, sample, metrics: MetricMeans | None = None) -> dict:
        """Count ``frames`` collected frames; once ``init_random_frames`` are in, ``utd_ratio`` steps per frame on minibatches
        from ``sample()``. ``metrics`` collects the losses (default: a fresh :class:`MetricMeans`; a seeds' batch passes
        one per seed)."""
        self.frames += frames
        metrics = MetricMeans() if metrics is None else metrics
        if self.frames >= self.init_random_frames:
            for _ in range(max(1, round(frames * self.utd_ratio))):
                metrics.add(sac_step(self.loss_fn(), sample(), (self.optimizer,), self.target_updater))
        return {**metrics.means(), "updates": metrics.count}

    def new_task(self) -> None:
        """A fresh, empty replay buffer; updates resume once ``init_random_frames`` frames of the new task are in it.

        Those frames are collected by the agent's own (fine-tuned) policy,
        not by random actions: the loop asks for random actions only when a
        run starts from scratch.
        """
        self.replay_buffer.empty()
        self.frames = 0

    def state_dict(self) -> dict:
        return {**super().state_dict(), "target_updater": self.target_updater.state_dict(), "frames": self.frames}

    def load_state_dict(self, state) -> None:
        super().load_state_dict(state)
        self.target_updater.load_state_dict(state["target_updater"])
        self.frames = int(state.get("frames", 0))
