"""Conservative Q-Learning (TorchRL :class:`~torchrl.objectives.CQLLoss`): model-free offline RL on the dataset itself."""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torchrl.objectives import CQLLoss, SoftUpdate, group_optimizers

from .base import DatasetAgent, adam, backward, compile_setting, gaussian_actor, q_network, scalar_metrics
from .registry import register_agent

__all__ = ["BatchableCQLLoss", "CQLAgent"]


class _DataIsDetach:
    """A view of a parameter TensorDict whose ``.data`` is ``.detach()``: the same values, cut from the graph, and allowed under
    ``torch.vmap`` (``.data`` is not). Everything else is the TensorDict's own."""

    def __init__(self, params):
        self._params = params

    @property
    def data(self):
        return self._params.detach()

    def __getattr__(self, name):
        return getattr(self._params, name)


class BatchableCQLLoss(CQLLoss):
    """TorchRL's :class:`~torchrl.objectives.CQLLoss`, the same maths, runnable under ``torch.vmap`` (seeds as a batch dimension).

    TorchRL's loss reads ``.data`` of its parameters in three places: the
    actor's weights for the sampled actions of the CQL penalty and of the
    TD target, the target critics' weights for that target, and
    ``log_alpha`` for the temperature (where it also clamps ``log_alpha`` in
    place when ``min_alpha`` / ``max_alpha`` are set). ``torch.vmap``
    refuses ``.data``; here the first two are given ``.detach()`` instead
    (the same values, also outside the graph) and the temperature is
    ``exp(log_alpha.detach())``, clamped out of place. The in-place clamp of
    the parameter itself, where bounds are set, is :meth:`clamp_log_alpha`,
    which :class:`CQLAgent` calls after each optimiser step (outside any
    vmap). ``tests/test_seed_batch.py`` checks that its outputs equal
    ``CQLLoss``'s on the same draws.
    """

    def _get_policy_actions(self, data, actor_params, num_actions=10):
        return super()._get_policy_actions(data, _DataIsDetach(actor_params), num_actions=num_actions)

    def _get_value_v(self, tensordict, _alpha, actor_params, qval_params):
        return super()._get_value_v(tensordict, _alpha, _DataIsDetach(actor_params), _DataIsDetach(qval_params))

    @property
    def _alpha(self):
        log_alpha = self.log_alpha.detach()
        if self.min_log_alpha is not None or self.max_log_alpha is not None:
            log_alpha = log_alpha.clamp(self.min_log_alpha, self.max_log_alpha)
        return log_alpha.exp()

    def clamp_log_alpha(self) -> None:
        """Keep the ``log_alpha`` parameter within ``[min_log_alpha, max_log_alpha]`` (nothing when no bound is set)."""
        if self.min_log_alpha is not None or self.max_log_alpha is not None:
            with torch.no_grad():
                self.log_alpha.clamp_(self.min_log_alpha, self.max_log_alpha)


@register_agent("cql")
class CQLAgent(DatasetAgent):
    """CQL (Kumar et al., 2020): SAC whose critics are pushed down on sampled actions and up on the data's.

    One update steps the actor, the twin critics (TD loss plus the CQL
    penalty), the entropy temperature and, with ``with_lagrange``, the CQL
    weight, then the Polyak step of the target critics. For the first
    ``policy_eval_start`` updates the actor is trained by behaviour cloning
    (``loss_actor_bc``), as the official CQL code and TorchRL's
    ``sota-implementations/cql/cql_offline.py`` do. Hyper-parameters
    (``configs/algo/cql.yaml``) are that script's for ``hopper-medium``:
    actor and critic lr 3e-4, batch 256, tau 0.005, 10 random actions,
    min_q_weight 1 with the Lagrange rule at threshold 5, stochastic backup,
    MLP(256, 256).

    The loss's hyper-parameters (:attr:`loss_hyperparameters`) are not
    arguments of the agent: they go to :class:`BatchableCQLLoss` (TorchRL's
    :class:`~torchrl.objectives.CQLLoss`) unchanged (``**loss_kwargs``),
    documented and typed there; :attr:`loss_defaults` holds the values here
    that differ from the loss's own.

    Examples:
        >>> from torchrl_offhrl.data import make_gym_env
        >>> agent = CQLAgent(make_gym_env("Pendulum-v1"), hidden_sizes=(32,), batch_size=8)
        >>> agent.policy_eval_start
        40000
    """

    #: the loss the agent trains, and the arguments of it a config sets (the rest are TorchRL's plumbing, left at its defaults)
    loss_class = BatchableCQLLoss
    loss_hyperparameters: tuple = ("temperature", "min_q_weight", "max_q_backup", "deterministic_backup", "num_random", "with_lagrange",
                                   "lagrange_thresh", "loss_function")
    #: TorchRL's sota script's for hopper-medium (the loss's defaults: no Lagrange rule, threshold 0, deterministic backup, smooth_l1)
    loss_defaults: dict = {"with_lagrange": True, "lagrange_thresh": 5.0, "deterministic_backup": False, "loss_function": "l2"}

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "action",
        device="cpu",
        hidden_sizes: Sequence[int] = (256, 256),
        actor_lr: float = 3e-4,
        critic_lr: float = 3e-4,
        gamma: float = 0.99,
        tau: float = 0.005,
        policy_eval_start: int = 40_000,
        batch_size: int = 256,
        reward_scale: float = 1.0,
        default_policy_scale: float = 1.0,
        scale_lb: float = 0.1,
        fused_adam: bool = True,
        compile: bool | str = False,
        cudagraphs: bool = False,
        **loss_kwargs,
    ):
        self.compile = compile_setting(compile)
        self.cudagraphs = bool(cudagraphs)
        self.policy = gaussian_actor(env, action_key, hidden_sizes, obs_loc, obs_scale, default_policy_scale, scale_lb)
        qvalue = q_network(env, action_key, hidden_sizes, obs_loc, obs_scale)
        self.loss = self.loss_class(self.policy, qvalue, action_spec=env.full_action_spec_unbatched[action_key],
                                    **{**self.loss_defaults, **loss_kwargs})
        self.loss.set_keys(action=action_key)
        self.loss.make_value_estimator(gamma=gamma)
        self.target_updater = SoftUpdate(self.loss, tau=tau)
        optimizers = [
            adam(self.loss.actor_network_params.flatten_keys().values(), lr=actor_lr, fused=fused_adam),
            adam(self.loss.qvalue_network_params.flatten_keys().values(), lr=critic_lr, fused=fused_adam),
            adam([self.loss.log_alpha], lr=actor_lr, fused=fused_adam),
        ]
        if self.loss.with_lagrange:
            optimizers.append(adam([self.loss.log_alpha_prime], lr=critic_lr, fused=fused_adam))
        self.optimizer = group_optimizers(*optimizers)
        self.policy_eval_start = int(policy_eval_start)
        self.action_key = action_key
        self.set_sampling(batch_size, reward_scale)

    def step_variant(self) -> bool:
        """``True`` during the behaviour-cloning phase (the first ``policy_eval_start`` updates)."""
        return self.steps < self.policy_eval_start

    def step(self, batch, bc_phase: bool):
        out = self.loss_fn()(batch)
        actor = out["loss_actor_bc"] if bc_phase else out["loss_actor"]
        total = actor + out["loss_qvalue"] + out["loss_cql"] + out["loss_alpha"]
        if out.get("loss_alpha_prime", None) is not None:
            total = total + out["loss_alpha_prime"]
        self.optimizer.zero_grad()
        backward(total)
        self.optimizer.step()
        self.loss.clamp_log_alpha()
        self.target_updater.step()
        metrics = scalar_metrics(out)
        metrics["bc_phase"] = torch.full(metrics.batch_size, float(bc_phase), device=total.device)  # [N] under a SeedBatch
        return metrics
