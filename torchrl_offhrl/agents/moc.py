"""Multi-updates Option Critic (:class:`~torchrl_offhrl.objectives.OptionCriticLoss`): options with PPO-clipped intra-option policies.

Besides the update, the agent reports how options are used in real-env
evaluations: ``option_usage_mean`` (the share of steps each option ran) in
every evaluation record, and at the last evaluation ``option_usage.pt`` /
``option_usage.png`` (the fraction of still-running episodes in which each
option is active at each step).
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F

from ..modules import OptionCriticActor, OptionHeads, make_option_critic
from ..objectives import OptionCriticLoss
from ..rollouts import first_episode_mask
from .base import OnPolicyAgent, action_box
from .registry import register_agent

__all__ = ["MOCAgent", "option_usage", "plot_option_usage"]


def option_usage(td, num_options: int, alive: torch.Tensor | None = None, option_key="option") -> torch.Tensor:
    """``[T, n]``: the fraction of still-running episodes in which each option is active at each step.

    ``td`` is a ``[E, T]`` evaluation rollout of auto-resetting envs;
    ``alive`` (``[E, T]``, default: from ``("next", "done")``) marks each
    env's first episode (:func:`~torchrl_offhrl.rollouts.first_episode_mask`):
    steps after an env's first ``done`` are ignored, and ``T`` stops at the
    last step any episode is still running.
    """
    if alive is None:
        alive = first_episode_mask(td["next", "done"].reshape(td.batch_size[0], -1))
    opt = td[option_key].reshape(alive.shape)
    onehot = F.one_hot(opt, num_options).float() * alive.unsqueeze(-1)
    running = alive.sum(0)
    last = int(running.nonzero().max()) + 1 if running.any() else 0
    return (onehot.sum(0) / running.clamp_min(1).unsqueeze(-1))[:last]


def plot_option_usage(usage: torch.Tensor, path, title: str = "option usage"):
    """``usage [T, n]``: fraction of running episodes in which each option is active at each step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, n = usage.shape
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.stackplot(range(t), usage.T.numpy(), labels=[f"option {i}" for i in range(n)], alpha=0.85)
    ax.set_xlim(0, max(t - 1, 1))
    ax.set_ylim(0, 1)
    ax.set_xlabel("time step in episode")
    ax.set_ylabel("fraction of episodes")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8, ncol=min(n, 4))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


@register_agent("moc")
class MOCAgent(OnPolicyAgent):
    """MOC: option-critic actor (``pi_O``, intra-option policies, terminations) and ``Q(s, o)``, on-policy.

    The paper's values (Hopper and HalfCheetah) are in ``configs/algo/moc.yaml``:
    lr 1e-4, clip 0.2, eta 0.7, gamma 0.99, lambda 0.95; every argument is
    documented in :class:`~torchrl_offhrl.modules.OptionHeads` and
    :class:`~torchrl_offhrl.objectives.OptionCriticLoss`.
    """

    evaluation_files = ("option_usage.png",)

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "latent_action",
        device="cpu",
        num_options: int = 4,
        hidden_sizes: Sequence[int] = (64, 64),
        activation: str = "tanh",
        shared_trunk: bool = False,
        init_log_std: float = 0.0,
        lr: float = 1e-4,
        eta: float = 0.7,
        clip_epsilon: float = 0.2,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        xi: float = 0.0,
        normalize_option_advantages: bool = False,
        critic_coef: float = 0.5,
        entropy_coef: float = 0.0,
        option_entropy_coef: float = 0.01,
        frames_per_batch: int = 2048,
        epochs: int = 10,
        minibatch_size: int = 64,
        max_grad_norm: float | None = 0.5,
    ):
        super().__init__(frames_per_batch=frames_per_batch, epochs=epochs, minibatch_size=minibatch_size, max_grad_norm=max_grad_norm)
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim, low, high = action_box(env, action_key)
        n = int(num_options)
        hidden = list(hidden_sizes)
        heads = OptionHeads(
            obs_dim, act_dim, n, hidden=hidden, shared_trunk=shared_trunk, activation=activation,
            obs_loc=obs_loc, obs_scale=obs_scale, init_log_std=init_log_std,
        )
        self.policy = OptionCriticActor(heads, low=low, high=high, action_key=action_key)
        critic = make_option_critic(obs_dim, n, hidden, activation, obs_loc, obs_scale)
        self.loss = OptionCriticLoss(
            self.policy,
            critic,
            num_options=n,
            eta=eta,
            clip_epsilon=clip_epsilon,
            xi=xi,
            normalize_option_advantages=normalize_option_advantages,
            critic_coef=critic_coef,
            entropy_coef=entropy_coef,
            option_entropy_coef=option_entropy_coef,
            gamma=gamma,
            lmbda=lmbda,
        )
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.action_key = action_key
        self.num_options = n

    def env_transforms(self) -> list:
        return self.policy.make_transforms()

    def evaluation_metrics(self, rollout, alive) -> dict:
        usage = F.one_hot(rollout["option"].reshape(alive.shape), self.num_options).float()[alive].mean(0)
        return {"option_usage_mean": usage.tolist()}

    def save_evaluation(self, rollout, alive, run_dir: Path, title: str) -> None:
        usage = option_usage(rollout, self.num_options, alive)
        torch.save(usage, Path(run_dir) / "option_usage.pt")
        plot_option_usage(usage, Path(run_dir) / "option_usage.png", title=f"MOC option usage, {title}")
