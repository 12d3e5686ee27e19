"""Behaviour cloning (TorchRL :class:`~torchrl.objectives.BCLoss`) on the dataset itself: the model-free floor."""
from __future__ import annotations

from collections.abc import Sequence

from torchrl.objectives import BCLoss

from .base import DatasetAgent, adam, backward, compile_setting, deterministic_actor, gaussian_actor, scalar_metrics
from .registry import register_agent

__all__ = ["BCAgent"]


@register_agent("bc")
class BCAgent(DatasetAgent):
    """Behaviour cloning: regress the dataset's actions from its observations.

    ``stochastic=False`` (the default, as CORL's and the TD3+BC paper's BC
    baseline): a deterministic tanh-squashed MLP fitted by mean squared
    error. ``stochastic=True``: a tanh-Gaussian actor fitted by negative
    log-likelihood, evaluated at its mode. Rewards are not used.

    On a goal-conditioned task (block stacking) the loop passes ``goal_key``
    (``"sub_goal"``): the policy maps (state, low-level goal) to the action,
    as the paper's BC baseline, learning from the sub-goal the data's
    collector pursued; at test the env's
    :class:`~torchrl_offhrl.envs.SubGoalTracker` gives it the sub-goals
    along the goal's abstract demonstration.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_offhrl.data import make_gym_env
        >>> agent = BCAgent(make_gym_env("Pendulum-v1"), hidden_sizes=(16,), batch_size=4)
        >>> batch = TensorDict(observation=torch.zeros(4, 3), action=torch.full((4, 1), 0.5), batch_size=[4])
        >>> agent.update(batch)["updates"]
        1
    """

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "action",
        device="cpu",
        goal_key: str | None = None,
        hidden_sizes: Sequence[int] = (256, 256),
        lr: float = 3e-4,
        stochastic: bool = False,
        batch_size: int = 256,
        fused_adam: bool = True,
        compile: bool | str = False,
        cudagraphs: bool = False,
    ):
        self.compile = compile_setting(compile)
        self.cudagraphs = bool(cudagraphs)
        if stochastic:
            self.policy = gaussian_actor(env, action_key, hidden_sizes, obs_loc, obs_scale, goal_key=goal_key)
            self.loss = BCLoss(self.policy)
        else:
            self.policy = deterministic_actor(env, action_key, hidden_sizes, obs_loc, obs_scale, goal_key=goal_key)
            self.loss = BCLoss(self.policy, loss_function="l2")
        self.loss.set_keys(action=action_key)
        self.optimizer = adam(self.loss.parameters(), lr=lr, fused=fused_adam)
        self.action_key = action_key
        self.set_sampling(batch_size, 1.0)

    def step(self, batch, variant=None):
        out = self.loss_fn()(batch)
        self.optimizer.zero_grad()
        backward(out["loss_bc"])
        self.optimizer.step()
        return scalar_metrics(out)
