"""TD3+BC (TorchRL :class:`~torchrl.objectives.TD3BCLoss`): model-free offline RL on the dataset itself."""
from __future__ import annotations

from collections.abc import Sequence

from tensordict import TensorDict
from torchrl.objectives import SoftUpdate, TD3BCLoss

from .base import DatasetAgent, adam, backward, compile_setting, deterministic_actor, q_network
from .registry import register_agent

__all__ = ["TD3BCAgent"]


@register_agent("td3bc")
class TD3BCAgent(DatasetAgent):
    """TD3+BC (Fujimoto & Gu, 2021): TD3's twin critics and delayed deterministic actor, plus an MSE pull to the data's actions.

    Every update steps the critics (target actions smoothed with clipped
    noise); every ``policy_update_delay``-th also steps the actor on
    ``-lambda Q(s, pi(s)) + (pi(s) - a)^2`` with ``lambda = alpha / mean|Q|``
    and then the Polyak step of the target networks, as TorchRL's
    ``sota-implementations/td3_bc/td3_bc.py``. Hyper-parameters
    (``configs/algo/td3bc.yaml``) are that script's and the paper's: alpha
    2.5, policy noise 0.2 clipped at 0.5, delay 2, lr 3e-4, batch 256, tau
    0.005, MLP(256, 256); observations normalised with the dataset's
    statistics as in the paper; rewards unscaled.

    The loss's hyper-parameters (:attr:`loss_hyperparameters`: ``alpha``,
    ``policy_noise``, ``noise_clip``, ``loss_function``) are not arguments of
    the agent: they go to TorchRL's :class:`~torchrl.objectives.TD3BCLoss`
    unchanged (``**loss_kwargs``), documented and typed there;
    :attr:`loss_defaults` holds the value here that differs from the loss's.

    Examples:
        >>> from torchrl_offhrl.data import make_gym_env
        >>> agent = TD3BCAgent(make_gym_env("Pendulum-v1"), hidden_sizes=(32,), batch_size=8)
        >>> agent.policy_update_delay
        2
    """

    #: the loss the agent trains, and the arguments of it a config sets (the rest are TorchRL's plumbing, left at its defaults)
    loss_class = TD3BCLoss
    loss_hyperparameters: tuple = ("alpha", "policy_noise", "noise_clip", "loss_function")
    #: TorchRL's sota script's critic loss (the loss's default: smooth_l1); alpha and the noise are the loss's defaults
    loss_defaults: dict = {"loss_function": "l2"}

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
        policy_update_delay: int = 2,
        batch_size: int = 256,
        reward_scale: float = 1.0,
        fused_adam: bool = True,
        compile: bool | str = False,
        cudagraphs: bool = False,
        **loss_kwargs,
    ):
        self.compile = compile_setting(compile)
        self.cudagraphs = bool(cudagraphs)
        self.policy = deterministic_actor(env, action_key, hidden_sizes, obs_loc, obs_scale)
        qvalue = q_network(env, action_key, hidden_sizes, obs_loc, obs_scale)
        self.loss = self.loss_class(self.policy, qvalue, action_spec=env.full_action_spec_unbatched[action_key], num_qvalue_nets=2,
                                    **{**self.loss_defaults, **loss_kwargs})
        self.loss.set_keys(action=action_key)
        self.loss.make_value_estimator(gamma=gamma)
        self.target_updater = SoftUpdate(self.loss, tau=tau)
        # two optimisers, stepped at different rates: the critic's is the agent's `optimizer`, both are checkpointed
        self.optimizer = adam(self.loss.qvalue_network_params.flatten_keys().values(), lr=lr, fused=fused_adam)
        self.actor_optimizer = adam(self.loss.actor_network_params.flatten_keys().values(), lr=lr, fused=fused_adam)
        self.policy_update_delay = int(policy_update_delay)
        self.action_key = action_key
        self.set_sampling(batch_size, reward_scale)

    def step_variant(self) -> bool:
        """``True`` when this update also steps the actor and the targets (every ``policy_update_delay``-th)."""
        return (self.steps + 1) % self.policy_update_delay == 0

    def step(self, batch, with_actor: bool):
        q_loss, _ = self.loss_fn("qvalue_loss")(batch)
        self.optimizer.zero_grad()
        backward(q_loss)
        self.optimizer.step()
        out = TensorDict(loss_qvalue=q_loss.detach())
        if with_actor:
            actor_loss, meta = self.loss_fn("actor_loss")(batch)
            self.actor_optimizer.zero_grad()
            backward(actor_loss)
            self.actor_optimizer.step()
            self.target_updater.step()
            out.update(dict(loss_actor=actor_loss.detach(), bc_loss=meta["bc_loss"].detach(), lmbd=meta["lmbd"].detach()))
        return out

    def state_dict(self) -> dict:
        return {**super().state_dict(), "actor_optimizer": self.actor_optimizer.state_dict()}

    def load_state_dict(self, state) -> None:
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        super().load_state_dict(state)  # after it: it resets every optimiser's capturable flag
