"""Multi-updates Option Critic (:class:`~torchrl_offhrl.objectives.OptionCriticLoss`): options with PPO-clipped intra-option policies.

Besides the update, the agent reports how options are used in real-env
evaluations: ``option_usage_mean`` (the share of steps each option ran) in
every evaluation record, and at the last evaluation ``option_usage.pt`` /
``option_usage.png`` (the fraction of still-running episodes in which each
option is active at each step).
"""
from __future__ import annotations

import copy
from collections.abc import Sequence
from pathlib import Path

import torch
import torch.nn.functional as F

from ..modules import OptionCriticActor, OptionHeads, make_option_critic
from ..objectives import OptionCriticLoss
from ..rollouts import first_episode_mask
from ..utils import import_class
from .base import OnPolicyAgent, action_box, adam, backward
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

    The defaults are ``configs/algo/moc.yaml``: the official continuous-control
    MOC with the paper's values (Hopper and HalfCheetah: lr 1e-4, clip 0.2,
    eta 0.7, gamma 0.99, lambda 0.95) and three measured deviations, each one
    switch away from the official code (``configs/algo/moc_official.yaml``):

    * ``termination_lr`` / ``option_lr`` 1e-3 (official: ``lr``). Under the
      per-term schedule beta and pi_O take one full-batch Adam step per
      batch; at 1e-4 neither moves in 80 batches (beta stays 0.50, pi_O
      uniform, options switch every ~2 steps), at 1e-3 they learn.
    * ``xi`` 0.01 (official: 0): the deliberation cost in
      ``beta (Q - V + xi)``, in units of the rewards the agent learns from
      (``model_env.reward_scale=auto``).
    * ``anneal_lr`` True (official, as we read it: constant step sizes):
      every step size decays linearly to 0 over the frame budget, so the
      policy settles instead of drifting late in training. Chosen on the
      development seed at the demo's budget; it does not cure the late fall
      of the last policy on Hopper, which the run's guard answers
      (``selection`` in ``configs/offline_train.yaml``).

    What these settings give (option lengths, pi_O's entropy, scores) is
    measured in ``docs/results/moc_demo_experiments.md`` (row
    ``official_fast_xi``).
    The network arguments are documented in
    :class:`~torchrl_offhrl.modules.OptionHeads`. The loss's (``eta``,
    ``clip_epsilon``, ``gamma``, ``lmbda``, ``xi``, the coefficients,
    ``importance_correction``, ...) are not arguments of the agent: every
    keyword it does not take is passed on to the loss unchanged
    (``**loss_kwargs``), so they are declared and documented once, in
    :class:`~torchrl_offhrl.objectives.OptionCriticLoss`, and a loss named by
    ``algo.loss`` brings its own; :attr:`loss_defaults` holds the two whose
    default here is not the loss's.

    Switches between this project's first version
    (``configs/algo/moc_joint.yaml``) and the official continuous-control MOC
    code (``configs/algo/moc_official.yaml`` sets all of them the official
    way, as do the defaults):

    * ``update_schedule``: ``"joint"`` sums every loss term and steps every
      parameter in each minibatch (hundreds of Adam steps per batch on the
      termination and pi_O heads); ``"per_term"`` (official) steps the
      intra-option policies and the critic over the minibatch epochs and the
      termination head and pi_O once per batch on the full batch, with their
      own learning rates ``termination_lr`` / ``option_lr`` (default: ``lr``).
    * ``importance_correction``: ``"assignment"`` or ``"next_step"`` (official).
    * ``adam_eps``: 1e-8 (torch's default) or 1e-5 (official).
    * ``obs_clip``: None or 5.0 (official: normalised observations clipped).
    * ``option_head_gain`` / ``termination_head_gain``: 0.01 (near-uniform
      start) or 1.0 (official ``normc(1.0)``: O(1) logits).
    * ``intra_head_gain``: 0.01 (baselines' ``normc(0.01)`` scale: every
      option starts near the box's centre) or 1.0 (O(1) means, like TorchRL's PPO
      actor).

    ``loss`` (``algo.loss``): a dotted path to a subclass of
    :class:`~torchrl_offhrl.objectives.OptionCriticLoss` to train instead of
    it (None: :attr:`loss_class`), built with the same arguments.

    ``policy_ema`` (``algo.policy_ema``, default None: off): after each
    batch's update the weights of a copy of the policy move this far towards
    the policy's (``avg += policy_ema * (policy - avg)``); evaluations, the
    offline policy selection, the returned policy and ``offhrl evaluate`` act
    with that average (:attr:`eval_policy`), the collector with the policy.

    ``log_std_lr`` (``algo.log_std_lr``, default None: ``lr``): the step
    size of the intra-option policies' state-independent log-stds. At
    ``lr`` 1e-4 and the demo's ~3,200 annealed Adam steps they can move by
    at most ~0.16, so the std stays at its initial value and PPO optimises
    a policy as wide as the prior while the evaluation runs its mean
    (docs/results/demo_robustness_notes.md, row 22).

    ``final_log_std`` (``algo.final_log_std``, default None: learned): a
    schedule for the intra-option log-stds instead of learning them. Before
    each update (:meth:`set_progress`) they are set to the line from
    ``init_log_std`` to ``final_log_std`` at the fraction of the frame budget
    done, the same for every option and action dimension: wide early (the
    CVAE prior's own spread, where the demo's runs find their gaits), narrow
    late (where a std of exp(-1) from the start kept the gaits runs found;
    docs/results/demo_robustness_notes.md, rows 22-24). PPO's ratio compares
    each batch with the log-probs it was collected with, so the step from one
    batch's std to the next is part of the ratio.

    ``prior_coef`` (``algo.prior_coef``, default 0: off): the loss's soft
    trust region around the latent prior's mode
    (:class:`~torchrl_offhrl.objectives.OptionCriticLoss`'s ``loss_prior``,
    ``0.5 * prior_coef * ||a_o(s)||^2`` at every option's mode action),
    stepped with the intra-option policies.

    ``fused_adam`` is a speed switch (the same update rule, see
    :func:`~torchrl_offhrl.agents.adam`).
    """

    evaluation_files = ("option_usage.png",)
    #: the loss the agent trains unless ``loss`` (``algo.loss``) names another: a subclass of
    #: :class:`~torchrl_offhrl.objectives.OptionCriticLoss` (a new option-critic variant) trains through this agent
    #: unchanged, from the config (``algo.loss=my_package.MyOptionLoss``, a dotted path) or from a registered subclass
    #: of the agent that sets this attribute (CONTRIBUTING.md). It is built with the actor, the critic, the option count
    #: and every config key the agent does not take itself (its own arguments); the optimisers group its parameters by name.
    loss_class: type[OptionCriticLoss] = OptionCriticLoss
    #: what ``algo.loss`` must subclass (the agent's optimisers and schedule rely on its terms)
    loss_base: type[OptionCriticLoss] = OptionCriticLoss
    #: the loss arguments whose default here differs from the loss's own (the measured deviations above): xi 0.01 (the
    #: loss: 0) and the official MOC's importance correction (the loss: this project's first version, ``assignment``)
    loss_defaults: dict = {"xi": 0.01, "importance_correction": "next_step"}
    #: the loss arguments the agent sets itself, not from its config
    loss_set_by_agent: tuple = ("actor_network", "critic_network", "num_options")

    def __init__(
        self,
        env,
        *,
        obs_loc=None,
        obs_scale=None,
        action_key: str = "latent_action",
        device="cpu",
        num_options: int = 2,
        hidden_sizes: Sequence[int] = (64, 64),
        activation: str = "tanh",
        shared_trunk: bool = False,
        init_log_std: float = 0.0,
        lr: float = 1e-4,
        frames_per_batch: int = 2048,
        epochs: int = 10,
        minibatch_size: int = 64,
        max_grad_norm: float | None = None,
        update_schedule: str = "per_term",
        termination_lr: float | None = 1e-3,
        option_lr: float | None = 1e-3,
        adam_eps: float = 1e-5,
        obs_clip: float | None = 5.0,
        option_head_gain: float = 1.0,
        termination_head_gain: float = 1.0,
        intra_head_gain: float = 0.01,
        fused_adam: bool = True,
        compile: bool | str = False,
        anneal_lr: bool = True,
        loss: str | None = None,
        policy_ema: float | None = None,
        log_std_lr: float | None = None,
        final_log_std: float | None = None,
        **loss_kwargs,
    ):
        super().__init__(frames_per_batch=frames_per_batch, epochs=epochs, minibatch_size=minibatch_size, max_grad_norm=max_grad_norm, compile=compile, anneal_lr=anneal_lr)
        if update_schedule not in self.UPDATE_SCHEDULES:
            raise ValueError(f"update_schedule must be one of {self.UPDATE_SCHEDULES}, got {update_schedule!r}")
        obs_dim = env.observation_spec["observation"].shape[-1]
        act_dim, low, high = action_box(env, action_key)
        n = int(num_options)
        hidden = list(hidden_sizes)
        heads = OptionHeads(
            obs_dim, act_dim, n, hidden=hidden, shared_trunk=shared_trunk, activation=activation,
            obs_loc=obs_loc, obs_scale=obs_scale, init_log_std=init_log_std, obs_clip=obs_clip,
            option_head_gain=option_head_gain, termination_head_gain=termination_head_gain, intra_head_gain=intra_head_gain,
        )
        if final_log_std is not None and log_std_lr is not None:
            raise ValueError("algo.final_log_std schedules the log-stds, so they are not learned: leave algo.log_std_lr null")
        self.log_std_schedule = None if final_log_std is None else (float(init_log_std), float(final_log_std))
        if self.log_std_schedule is not None:
            heads.log_std.requires_grad_(False)
        self.policy = OptionCriticActor(heads, low=low, high=high, action_key=action_key)
        critic = make_option_critic(obs_dim, n, hidden, activation, obs_loc, obs_scale, obs_clip=obs_clip)
        loss_class = self.loss_class if loss is None else import_class(loss, self.loss_base, "algo.loss")
        # the loss's hyper-parameters (eta, clip_epsilon, gamma, lmbda, xi, the coefficients, ...) go to it as they are: declared
        # once, in its signature; the agent only fills in the ones it deviates on (loss_defaults) and the option count
        self.loss = loss_class(self.policy, critic, num_options=n, **{**self.loss_defaults, **loss_kwargs})
        self.update_schedule = update_schedule
        self.action_key = action_key
        self.num_options = n
        if policy_ema is not None and not 0.0 < float(policy_ema) <= 1.0:
            raise ValueError(f"algo.policy_ema must be in (0, 1] (the weight of the new policy per batch) or null, got {policy_ema}")
        self.policy_ema = None if policy_ema is None else float(policy_ema)
        # evaluated, selected and returned instead of the policy: the weights' Polyak average over the batches (eval_policy)
        self.averaged_policy = copy.deepcopy(self.policy).requires_grad_(False) if self.policy_ema is not None else None
        if update_schedule == "joint":
            self.optimizer = adam(self.loss.parameters(), lr=lr, eps=adam_eps, fused=fused_adam)
            self.termination_optimizer = self.option_optimizer = None
            return
        groups = {"termination": [], "option": [], "main": [], "log_std": []}
        for name, p in self.loss.named_parameters():
            if not p.requires_grad:  # scheduled log-stds (final_log_std)
                continue
            group = "termination" if ".termination_head." in name else "option" if ".option_head." in name else "main"
            groups["log_std" if log_std_lr is not None and name.endswith(".log_std") else group].append(p)
        if log_std_lr is not None and float(log_std_lr) <= 0:
            raise ValueError(f"algo.log_std_lr must be a positive step size or null (the intra-option policies' lr), got {log_std_lr}")
        # the intra-option log-stds in their own Adam group when log_std_lr is set (the same optimiser, annealed alike)
        main = groups["main"] if log_std_lr is None else [{"params": groups["main"]}, {"params": groups["log_std"], "lr": float(log_std_lr)}]
        self.optimizer = adam(main, lr=lr, eps=adam_eps, fused=fused_adam)
        self.termination_optimizer = adam(groups["termination"], lr=lr if termination_lr is None else termination_lr, eps=adam_eps, fused=fused_adam)
        self.option_optimizer = adam(groups["option"], lr=lr if option_lr is None else option_lr, eps=adam_eps, fused=fused_adam)

    UPDATE_SCHEDULES = ("joint", "per_term")
    #: the loss terms stepped over the minibatch epochs by the per-term schedule
    MINIBATCH_TERMS = ("loss_objective", "loss_critic", "loss_entropy", "loss_prior")

    def prepare(self, batch) -> None:
        self.loss.prepare_batch(batch)

    def set_progress(self, fraction: float) -> None:
        """Anneal the step sizes (``anneal_lr``) and, with ``final_log_std``, set the log-stds on their line."""
        super().set_progress(fraction)
        if self.log_std_schedule is not None:
            start, end = self.log_std_schedule
            f = min(max(float(fraction), 0.0), 1.0)
            for policy in filter(None, (self.policy, self.averaged_policy)):
                policy.heads.log_std.fill_(start + (end - start) * f)

    def update(self, batch) -> dict:
        metrics = self._update(batch)
        if self.averaged_policy is not None:
            with torch.no_grad():
                for avg, p in zip(self.averaged_policy.parameters(), self.policy.parameters()):
                    avg.lerp_(p, self.policy_ema)
        return metrics

    def _update(self, batch) -> dict:
        return super().update(batch)

    def minibatch_objective(self, out):
        """``joint``: every loss term; ``per_term``: the intra-option policies' and the critic's terms (:attr:`MINIBATCH_TERMS`)."""
        if self.update_schedule == "joint":
            return super().minibatch_objective(out)
        return sum(out[k] for k in self.MINIBATCH_TERMS if k in out.keys())

    def finish_update(self, flat) -> None:
        """``per_term``: termination and pi_O, one step each on the whole batch (official MOC), with the updated critic."""
        if self.update_schedule == "joint":
            return
        out = self.batch_loss(flat)
        self.termination_optimizer.zero_grad()
        self.option_optimizer.zero_grad()
        backward(out["loss_termination"] + out["loss_option"] + out["loss_option_entropy"])
        self.termination_optimizer.step()
        self.option_optimizer.step()

    def state_dict(self) -> dict:
        state = super().state_dict()
        if self.averaged_policy is not None:
            state["averaged_policy"] = self.averaged_policy.state_dict()
        if self.update_schedule == "per_term":
            state["termination_optimizer"] = self.termination_optimizer.state_dict()
            state["option_optimizer"] = self.option_optimizer.state_dict()
        return state

    def load_state_dict(self, state) -> None:
        super().load_state_dict(state)
        if self.averaged_policy is not None:
            self.averaged_policy.load_state_dict(state["averaged_policy"])
        if self.update_schedule == "per_term":
            self.termination_optimizer.load_state_dict(state["termination_optimizer"])
            self.option_optimizer.load_state_dict(state["option_optimizer"])

    def env_transforms(self) -> list:
        return self.policy.make_transforms()

    def evaluation_metrics(self, rollout, alive) -> dict:
        """Option usage and whether the options differ, on the states the evaluation visited.

        ``option_usage_mean``: the share of steps each option ran;
        ``option_starts``: option starts per episode after its first step
        (a termination and a new pick, which may pick the same option
        again); ``option_kl``: the mean KL divergence between two options'
        intra-option policies at the same states, over the ordered pairs of
        options (0 with one option, or when the options act alike: the
        tanh-Gaussians' KL is their Gaussians', tanh and the box's affine map
        being bijections).
        """
        usage = F.one_hot(rollout["option"].reshape(alive.shape), self.num_options).float()[alive].mean(0)
        out = {"option_usage_mean": usage.tolist()}
        start = rollout.get("option_start", None)
        if start is not None:  # every episode starts an option at its first step: those do not count
            starts = (start.reshape(alive.shape) & alive)[:, 1:].sum(1).float()
            out["option_starts"] = float(starts.mean())
        n = self.num_options
        if n > 1:
            obs = rollout["observation"].reshape(*alive.shape, -1)[alive]
            with torch.no_grad():
                _, loc, scale, _ = self.policy.heads(obs)  # [S, n, A]
            mu_i, mu_j = loc.unsqueeze(2), loc.unsqueeze(1)
            s_i, s_j = scale.unsqueeze(2), scale.unsqueeze(1)
            kl = (torch.log(s_j / s_i) + (s_i ** 2 + (mu_i - mu_j) ** 2) / (2 * s_j ** 2) - 0.5).sum(-1)  # [S, n, n]
            off = ~torch.eye(n, dtype=torch.bool, device=kl.device)
            out["option_kl"] = float(kl[:, off].mean())
        else:
            out["option_kl"] = 0.0
        return out

    def save_evaluation(self, rollout, alive, run_dir: Path, title: str) -> None:
        usage = option_usage(rollout, self.num_options, alive)
        torch.save(usage, Path(run_dir) / "option_usage.pt")
        plot_option_usage(usage, Path(run_dir) / "option_usage.png", title=f"MOC option usage, {title}")
