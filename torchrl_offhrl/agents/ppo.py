"""PPO (TorchRL :class:`~torchrl.objectives.ClipPPOLoss`) with a tanh-Gaussian actor and a state-value critic."""
from __future__ import annotations

import contextlib
import warnings
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from torch import nn
from torchrl.modules import ValueOperator
from torchrl.modules.distributions.utils import has_analytic_kl, sample_and_log_prob
from torchrl.objectives import BCLoss, ClipPPOLoss, KLPENPPOLoss, PPOLoss

from ..nets import NormalizedMLP, tanh_gaussian_actor
from .base import OnPolicyAgent, action_box, adam
from .registry import loss_kwargs_for, register_agent

__all__ = ["BatchableKLPENPPOLoss", "PPOAgent"]


class BatchableKLPENPPOLoss(KLPENPPOLoss):
    """TorchRL's :class:`~torchrl.objectives.KLPENPPOLoss`, the same objective, runnable under ``torch.vmap`` (seeds batched).

    TorchRL's loss adapts its KL coefficient ``beta`` inside ``forward``
    with Python control flow on the minibatch's KL (``if kl > 1.5 x dtarg:
    beta *= increment``; ``elif kl < dtarg / 1.5: beta *= decrement``),
    which ``torch.vmap`` refuses. Here ``forward`` only computes: PPO's
    importance-weighted surrogate, entropy and critic terms
    (:class:`~torchrl.objectives.PPOLoss`'s), plus ``beta`` times the KL
    of the current policy from the one that collected the data (analytic
    where the distributions have one, else ``samples_mc_kl`` draws), and
    reports that KL's minibatch mean as ``"kl"``. The coefficient then moves
    in :meth:`adapt_beta`, one elementwise ``torch.where`` that the caller
    runs after the forward pass (:meth:`PPOAgent.observe_minibatch`): with
    the seeds' ``beta`` stacked ``[N]`` and their KLs ``[N]``, each seed's
    coefficient follows its own rule in one call. The loss a minibatch
    is given uses the coefficient from before that minibatch, as TorchRL's,
    and so does its gradient. (TorchRL's differs there: its in-place
    ``beta.data *= ...`` also rewrites the tensor autograd saved for the
    backward pass, so its penalty's gradient already uses the adapted
    coefficient: a one-minibatch lag between the two.)
    ``tests/test_seed_batch.py`` checks, against ``KLPENPPOLoss``, the
    losses and weights update after update with the coefficient held, and
    the coefficient's rule on each of its three branches.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        if self.delay_actor:
            raise ValueError("BatchableKLPENPPOLoss measures the KL from the policy that collected the data; delay_actor=True "
                             "(a proximal copy of the actor) is TorchRL's KLPENPPOLoss's")

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        kl = self._kl_from_behaviour(tensordict)  # first: TorchRL's loss draws the KL's samples before the entropy's
        out = PPOLoss.forward(self, tensordict)  # the importance-weighted surrogate (no clip), entropy and critic terms
        # a copy of the coefficient in the graph: adapt_beta may change the buffer before this loss's backward pass
        penalty = self._reduce_loss((self.beta.clone() * kl).unsqueeze(-1), tensordict).squeeze(-1)
        out.set("loss_objective", out.get("loss_objective") + penalty)
        out.set("kl", kl.detach().mean())
        return out

    def _kl_from_behaviour(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``KL(collecting policy || current policy)`` per sample (``[*batch]``)."""
        try:
            previous = self.actor_network.build_dist_from_params(tensordict)
        except KeyError as err:
            raise KeyError(f"{type(self).__name__}: the batch lacks the collecting policy's distribution parameters "
                           f"({err}); collect it with the agent's own policy, which writes them") from err
        params = (self.actor_network_params.to_module(self.actor_network, preserve_module_state=False) if self.functional
                  else contextlib.nullcontext())
        with params:
            current = self.actor_network.get_dist(tensordict.clone(False))
        if has_analytic_kl(previous, current):
            return torch.distributions.kl.kl_divergence(previous, current)
        x, previous_log_prob = sample_and_log_prob(previous, (self.samples_mc_kl,))
        return (previous_log_prob - current.log_prob(x)).mean(0)

    @torch.no_grad()
    def adapt_beta(self, kl: torch.Tensor) -> None:
        """TorchRL's rule, elementwise: ``beta`` x ``increment`` where ``kl`` > 1.5 ``dtarg``, x ``decrement`` where < ``dtarg`` / 1.5.

        ``kl`` has ``beta``'s shape: a scalar for one agent, ``[N]`` for a seeds' batch (whose ``beta`` is stacked).
        """
        beta = self.beta
        kl = kl.detach().to(beta.dtype).reshape(beta.shape)
        beta.copy_(torch.where(kl > self.dtarg * 1.5, beta * self.increment, torch.where(kl < self.dtarg / 1.5, beta * self.decrement, beta)))


@register_agent("ppo")
class PPOAgent(OnPolicyAgent):
    """PPO with GAE; the paper's values are in ``configs/algo/ppo.yaml`` (lr and clip per env in ``configs/env/``).

    Speed switches (the same algorithm either way): ``fused_adam`` (one fused
    Adam kernel, see :func:`~torchrl_offhrl.agents.adam`) and ``functional``
    (TorchRL's functionalised loss; ``False`` calls the networks directly).

    ``loss_type``: ``"clip"`` (PPO's clipped ratio, TorchRL's
    :class:`~torchrl.objectives.ClipPPOLoss`) or ``"kl"`` (PPO's adaptive KL
    penalty, TorchRL's :class:`~torchrl.objectives.KLPENPPOLoss` as
    :class:`BatchableKLPENPPOLoss`, which seeds can batch, with target
    ``dtarg``: a trust region on the policy's KL divergence per batch,
    this library's stand-in for MOReL's natural policy gradient, whose step
    is also bounded in KL).

    The losses' hyper-parameters (:attr:`loss_hyperparameters`) are not
    arguments of the agent: they reach the loss unchanged (``**loss_kwargs``),
    under the loss's names and documented there; the one of the loss the run
    does not train is left out (:func:`~torchrl_offhrl.agents.registry.loss_kwargs_for`).

    ``head_gain`` (1.0: the initialisation TorchRL's PPO actor has) scales
    the actor's last layer at initialisation (its bias zeroed): at 0.01 (the
    shipped config, as MOC's ``intra_head_gain``) the untrained actor's means
    sit at the latent box's centre, which the latent origin
    (``model_env.latent_origin=best``, the default) decodes to the action of
    the data's best episodes: the agent starts as a behaviour cloner.

    ``bc_init_steps`` (0: off): before training from scratch
    (:meth:`pretrain`), that many Adam steps of behaviour cloning (TorchRL's
    :class:`~torchrl.objectives.BCLoss`: the actor's negative log-likelihood
    of the dataset's actions, minibatches of ``bc_init_batch_size``, step
    size ``bc_init_lr``), as MOReL initialises its policy. It clones the
    dataset's real actions, so the agent must act in them
    (``ablation.no_cvae=true``); the critic starts untrained.
    """

    #: ``loss_type`` -> the TorchRL loss the agent trains
    loss_classes: dict = {"clip": ClipPPOLoss, "kl": BatchableKLPENPPOLoss}
    loss_class = ClipPPOLoss
    #: the losses' knobs a config sets, under the losses' names: the clipped ratio's ``clip_epsilon``, the KL penalty's
    #: target ``dtarg``, and both losses' ``entropy_coeff`` / ``critic_coeff`` (Stable-Baselines3's ``ent_coef`` / ``vf_coef``)
    loss_hyperparameters: tuple = ("clip_epsilon", "dtarg", "entropy_coeff", "critic_coeff")
    #: Stable-Baselines3's values (TorchRL's losses default to 0.01 and 1.0)
    loss_defaults: dict = {"entropy_coeff": 0.0, "critic_coeff": 0.5}

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
        bc_init_steps: int = 0,
        bc_init_lr: float = 1e-3,
        bc_init_batch_size: int = 256,
        head_gain: float = 1.0,
        **loss_kwargs,
    ):
        super().__init__(frames_per_batch=frames_per_batch, epochs=epochs, minibatch_size=minibatch_size, max_grad_norm=max_grad_norm, compile=compile, anneal_lr=anneal_lr)
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim, low, high = action_box(env, action_key)
        hidden = list(hidden_sizes)
        if not float(head_gain) > 0:
            raise ValueError(f"algo.head_gain must be > 0 (the scale of the actor's last layer at initialisation), got {head_gain}")
        body = NormalizedMLP(obs_dim, 0, act_dim, hidden, activation, obs_loc, obs_scale)
        if float(head_gain) != 1.0:  # the untrained actor's means near the box's centre: the latent origin (MOC's intra_head_gain)
            last = [m for m in body.modules() if isinstance(m, nn.Linear)][-1]
            with torch.no_grad():
                last.weight.mul_(float(head_gain))
                last.bias.zero_()
        net = nn.Sequential(body, AddStateIndependentNormalScale(act_dim, scale_lb=1e-4))
        self.policy = tanh_gaussian_actor(TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]), low, high, action_key)
        critic = ValueOperator(NormalizedMLP(obs_dim, 0, 1, hidden, activation, obs_loc, obs_scale), in_keys=["observation"])
        if loss_type not in self.loss_classes:
            raise ValueError(f"algo.loss_type must be 'clip' (PPO's clipped ratio) or 'kl' (its adaptive KL penalty), got {loss_type!r}")
        if int(bc_init_steps) < 0:
            raise ValueError(f"algo.bc_init_steps must be >= 0 (0: no behaviour-cloning start), got {bc_init_steps}")
        self.bc_init = {"steps": int(bc_init_steps), "lr": float(bc_init_lr), "batch_size": int(bc_init_batch_size)}
        loss_class = self.loss_classes[loss_type]
        self.loss = loss_class(
            self.policy,
            critic,
            loss_critic_type="l2",  # squared error, as SB3 (whose values the paper took) and as MOC's critic
            normalize_advantage=True,
            functional=functional,  # False: the networks are called directly, not through a copy of their parameters (faster, same maths)
            **loss_kwargs_for(type(self), loss_class, loss_kwargs),  # the trust region and the coefficients, as the loss names them
        )
        self.loss.set_keys(action=action_key, sample_log_prob=f"{action_key}_log_prob")
        self.loss.make_value_estimator(gamma=gamma, lmbda=lmbda)
        self.optimizer = adam(self.loss.parameters(), lr=lr, fused=fused_adam)
        self.action_key = action_key

    def observe_minibatch(self, out: TensorDictBase) -> None:
        """With ``loss_type="kl"``, the KL coefficient adapts to the minibatch's KL (:meth:`BatchableKLPENPPOLoss.adapt_beta`)."""
        if isinstance(self.loss, BatchableKLPENPPOLoss):
            self.loss.adapt_beta(out.get("kl"))

    def pretrain(self, data, progress: bool = False) -> dict:
        """MOReL's start: behaviour cloning of the dataset's actions (``bc_init_steps`` Adam steps; nothing when 0), with a
        progress bar when ``progress``."""
        from tqdm.auto import tqdm

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
        for _ in tqdm(range(steps), desc="behaviour-cloning start", unit="step", disable=not progress, leave=False):
            idx = torch.randint(n, (size,))
            batch = data[idx].select("observation", self.action_key).to(device)
            loss = bc(batch)["loss_bc"]
            opt.zero_grad()
            loss.backward()
            opt.step()
            last = float(loss.detach())
            first = last if first is None else first
        return {"bc_init_steps": steps, "bc_init_nll_first": first, "bc_init_nll_last": last}
