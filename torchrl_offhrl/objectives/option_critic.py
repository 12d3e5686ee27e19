"""Multi-updates Option Critic (MOC) as a TorchRL loss module."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictParams
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators
from torchrl.objectives.value import ValueEstimatorBase
from torchrl.objectives.value.functional import generalized_advantage_estimate

__all__ = ["OptionCriticLoss", "OptionGAE"]


class OptionGAE(ValueEstimatorBase):
    """GAE on option values: the advantage of ``Q(s_t, o_t)`` bootstrapped on ``U(s_{t+1}, o_t)``.

    ``delta_t = r_t + gamma * U(s_{t+1}, o_t) - Q(s_t, o_t)`` with
    ``U(s', o) = (1 - beta(s', o)) Q(s', o) + beta(s', o) V(s')`` and
    ``V(s) = sum_o pi_O(o|s) Q(s, o)``; ``U`` is dropped after a terminal
    step, and the trace is cut at every ``done``. ``forward`` (calling the
    module) writes ``advantage`` and ``value_target`` (= advantage +
    ``Q(s_t, o_t)``), both ``[*, T, 1]``, and returns the tensordict;
    :meth:`value_estimate` returns the target without writing anything.
    Computed without gradients (unless ``differentiable=True``), with the
    loss's current parameters (:meth:`OptionCriticLoss.option_heads` and
    :meth:`OptionCriticLoss.option_values`, on shallow copies: the heads and
    ``Q`` are not written into the data), on data whose last batch dimension is
    time (or ``time_dim``).

    It is a :class:`~torchrl.objectives.value.ValueEstimatorBase`, with TorchRL's
    conventions: :attr:`tensor_keys` / :meth:`set_keys` for ``advantage``,
    ``value_target``, ``value`` (the critic's ``Q(s, .)`` entry, ``[*, n]``),
    ``reward``, ``done``, ``terminated``, and for the option entries it reads
    (``option``, ``option_logits``, ``termination_probs``); an
    :class:`OptionCriticLoss` keeps them in sync with its own keys (set keys on
    the loss; setting them here directly only changes where this estimator
    reads and writes). The base class is used for its key handling and
    interface only: ``U(s', o)`` needs the actor's heads as well as the critic,
    so the values come from the loss (held by reference, not registered as a
    submodule) rather than from ``value_network`` alone (set to the loss's
    critic, for ``in_keys`` and the check of the ``value`` key), and there are
    no ``params``/``target_params`` arguments, no ``shifted`` or chunked
    calls. ``gamma`` and ``lmbda`` are plain floats, not buffers, so the
    loss's ``state_dict`` does not depend on whether the estimator was made.

    Args:
        loss: the :class:`OptionCriticLoss` (any object with ``option_heads``
            and ``option_values`` methods and a ``critic_network``).
        gamma, lmbda: discount and GAE lambda.

    Keyword Args:
        differentiable: keep gradients (default ``False``).
        time_dim: the time dimension of the data (default: the last batch
            dimension; dimension names are not used).

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl_offhrl.modules import OptionCriticActor, OptionHeads, make_option_critic
        >>> from torchrl_offhrl.objectives import OptionCriticLoss
        >>> loss = OptionCriticLoss(OptionCriticActor(OptionHeads(2, 1, 3, hidden=(8,))), make_option_critic(2, 3, hidden=(8,)))
        >>> gae = loss.value_estimator
        >>> gae.set_keys(advantage="adv", value_target="target")
        >>> td = TensorDict({"observation": torch.zeros(4, 2), "option": torch.zeros(4, dtype=torch.long),
        ...     "next": {"observation": torch.zeros(4, 2), "reward": torch.ones(4, 1),
        ...              "done": torch.zeros(4, 1, dtype=torch.bool), "terminated": torch.zeros(4, 1, dtype=torch.bool)}}, [4])
        >>> gae(td)["adv"].shape, bool((gae.value_estimate(td) == td["target"]).all())
        (torch.Size([4, 1]), True)
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read or written by :class:`OptionGAE`; change them with :meth:`set_keys`.

        Attributes:
            advantage: where the advantage is written.
            value_target: where the value target is written.
            value: the critic's option values ``Q(s, .)``, ``[*, n]``.
            option: the executed option.
            option_logits: the heads' ``pi_O`` logits.
            termination_probs: the heads' ``beta(s, o)`` for every option.
            reward, done, terminated: read under ``"next"``.
        """

        advantage: NestedKey = "advantage"
        value_target: NestedKey = "value_target"
        value: NestedKey = "option_value"
        option: NestedKey = "option"
        option_logits: NestedKey = "option_logits"
        termination_probs: NestedKey = "termination_probs"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    def __init__(self, loss: OptionCriticLoss, gamma: float = 0.99, lmbda: float = 0.95, *, differentiable: bool = False, time_dim: int | None = None):
        super().__init__(value_network=loss.critic_network, differentiable=differentiable)
        # held by reference only: registering the loss would make a module cycle (the loss owns its estimator)
        self.__dict__["loss"] = loss
        self.gamma = float(gamma)
        self.lmbda = float(lmbda)
        self.time_dim = time_dim

    @property
    def in_keys(self):
        k = self.tensor_keys
        obs = self.loss.tensor_keys.observation
        return [k.option, obs, ("next", obs), ("next", k.reward), ("next", k.done), ("next", k.terminated)]

    def gae_inputs(self, tensordict: TensorDictBase) -> TensorDict:
        """What the recursion needs, from the networks: ``value`` ``Q(s_t, o_t)`` and ``next_value`` ``U(s_{t+1}, o_t)``
        with ``reward``, ``done`` and ``terminated``, each ``[*, T, 1]`` (batch size: the data's).

        The networks' part alone, so that a seeds' batch can run it per seed
        under ``torch.vmap`` and the recursion (:meth:`advantage_from_inputs`)
        on all seeds at once.
        """
        keys = self.tensor_keys
        if tensordict.ndim < 1:
            raise ValueError("OptionGAE needs data with a time dimension (the last batch dimension)")
        with torch.set_grad_enabled(self.differentiable):
            option = tensordict.get(keys.option).long()
            q = self.loss.option_values(tensordict.copy()).get(keys.value)
            nxt = self.loss.option_heads(tensordict.get("next").copy())
            logits_n, beta_n = nxt.get(keys.option_logits), nxt.get(keys.termination_probs)
            q_n = self.loss.option_values(nxt).get(keys.value)
            v_n = (torch.softmax(logits_n, -1) * q_n).sum(-1)
            o = option.unsqueeze(-1)
            b = beta_n.gather(-1, o).squeeze(-1)
            u_n = (1 - b) * q_n.gather(-1, o).squeeze(-1) + b * v_n
            q_t = q.gather(-1, o).squeeze(-1)
            shape = q_t.shape + (1,)
            return TensorDict(value=q_t.unsqueeze(-1), next_value=u_n.unsqueeze(-1),
                              reward=tensordict.get(("next", keys.reward)).reshape(shape),
                              done=tensordict.get(("next", keys.done)).reshape(shape),
                              terminated=tensordict.get(("next", keys.terminated)).reshape(shape), batch_size=tensordict.batch_size)

    def advantage_from_inputs(self, inputs: TensorDictBase, time_dim: int | None = None):
        """GAE's recursion on :meth:`gae_inputs` (any leading dimensions; time: the last batch dimension unless given)."""
        time_dim = inputs.ndim - 1 if time_dim is None and self.time_dim is None else self._get_time_dim(time_dim, inputs)
        with torch.set_grad_enabled(self.differentiable):
            return generalized_advantage_estimate(
                self.gamma, self.lmbda, inputs.get("value"), inputs.get("next_value"), inputs.get("reward"), inputs.get("done"),
                inputs.get("terminated"), time_dim=time_dim,
            )

    def _advantage_and_target(self, tensordict: TensorDictBase, time_dim: int | None):
        return self.advantage_from_inputs(self.gae_inputs(tensordict), time_dim)

    def write(self, tensordict: TensorDictBase, adv: torch.Tensor, target: torch.Tensor) -> TensorDictBase:
        tensordict.set(self.tensor_keys.advantage, adv)
        tensordict.set(self.tensor_keys.value_target, target)
        return tensordict

    def forward(self, tensordict: TensorDictBase, *, time_dim: int | None = None) -> TensorDictBase:
        """Write ``advantage`` and ``value_target`` (``[*, T, 1]``) into ``tensordict`` and return it."""
        return self.write(tensordict, *self._advantage_and_target(tensordict, time_dim))

    def value_estimate(self, tensordict: TensorDictBase, *, time_dim: int | None = None, **kwargs) -> torch.Tensor:
        """The value target ``advantage + Q(s_t, o_t)``, ``[*, T, 1]``, without writing into ``tensordict``."""
        if kwargs:
            raise TypeError(f"OptionGAE.value_estimate got unexpected arguments {sorted(kwargs)}")
        return self._advantage_and_target(tensordict, time_dim)[1]


class OptionCriticLoss(LossModule):
    """Multi-updates Option Critic (Klissarov & Precup, 2021) with PPO clipping.

    Given a batch collected by an :class:`~torchrl_offhrl.modules.OptionCriticActor`
    (stored: ``option``, ``prev_option``, ``is_init``, ``option_log_probs``
    ``log pi_o_old(a_t|s_t)`` for every ``o``, ``option_assignment_log_prob``
    ``log P_t(o)``), the loss returns

    * ``loss_objective``: for **every** option ``o``, the PPO-clipped
      surrogate with ratio
      ``exp(log pi_o(a_t|s_t) - log pi_{o_t,old}(a_t|s_t) + log P_t(o) - log P_t(o_t))``
      (the update of ``o`` on data generated by ``o_t``, importance-corrected
      by the action and option-assignment probabilities) times the
      standardised GAE advantage of ``Q(s_t, o_t)``, weighted by
      ``w_t(o) = z P_t(o) + (1 - z) [o == o_t]``, ``z ~ Bernoulli(eta)``
      drawn once per call; summed over options, averaged over the batch.
      ``eta = 0`` updates only the executed option (PPOC);
    * ``loss_critic``: ``critic_coef * sum_o w_t(o) (Q(s_t, o) - G_t)^2``;
    * ``loss_termination``: ``beta(s_t, o_{t-1}) (Q(s_t, o_{t-1}) - V(s_t) + xi)``
      averaged over steps that are not episode starts, ``Q`` and ``V``
      detached: a worse-than-average option learns to terminate;
    * ``loss_option``: the gradient of ``U(s_t, o_{t-1})`` with respect to
      ``pi_O``, i.e. ``-beta_t sum_o pi_O(o|s_t) (Q(s_t, o) - V(s_t))`` with
      ``Q``, ``V`` and ``beta_t`` detached (``beta_t = 1`` at episode
      starts), and ``loss_option_entropy = -option_entropy_coef * H(pi_O)``;
    * ``loss_entropy``: ``-entropy_coef`` times the ``w``-weighted entropy of
      the intra-option (pre-tanh) Gaussians.

    and metrics: ``termination_rate`` (mean ``beta`` at non-start steps, from
    the data), ``option_duration`` (steps per option start),
    ``option_usage`` (``[n]``), ``clip_fraction``, ``approx_kl``,
    ``action_std`` (the mean pre-tanh standard deviation of the options the
    data ran: how much the intra-option policies still explore),
    ``option_entropy``, ``z``, ``explained_variance`` (of the value targets
    by ``Q(s_t, o_t)``, as PPO logs for ``V``).

    Sum every ``loss_*`` entry and call ``backward``. The advantage comes from
    :meth:`make_value_estimator` (:class:`OptionGAE`, gamma 0.99, lambda
    0.95); compute it once per batch with ``loss.value_estimator(batch)``
    before splitting into minibatches (``forward`` computes it when it is
    missing, treating the last batch dimension as time).

    **The actor** is reached through tensordicts only (duck-typed: any
    :class:`torch.nn.Module` with these methods works, a :class:`TypeError`
    names a missing one): ``actor.get_option_heads(td)`` writes the heads'
    outputs (``option_logits``, ``option_loc``, ``option_scale``,
    ``termination_probs``) into ``td``, ``actor.get_dist(td)`` returns the
    intra-option distributions of all options (batch ``[*, n]``), and
    ``actor.num_options`` (or the ``num_options`` argument) gives ``n``.
    The critic is a TensorDict module writing ``option_value`` ``[*, n]``.
    Both are called with the loss's functional parameters
    (:meth:`option_heads`, :meth:`option_values`, :meth:`option_dist`).

    **Keys**: every tensordict entry read is configurable with
    :meth:`set_keys` (fields of :attr:`tensor_keys`: ``observation``,
    ``action``, ``option``, ``prev_option``, ``is_init``, ``option_start``,
    ``termination_prob``, ``option_log_probs``, ``assignment_log_prob``, the
    heads' ``option_logits``, ``option_loc``, ``option_scale``,
    ``termination_probs``, the critic's ``option_value``, and ``advantage``,
    ``value_target``, ``reward``, ``done``, ``terminated``, forwarded to the
    value estimator). At construction the loss takes the names of the actor's
    ``tensor_keys`` (or its ``observation_key``/``action_key``) and the
    critic's output key; rename later on both sides
    (``actor.set_keys(...)`` and ``loss.set_keys(...)``).

    **Terms**: ``forward`` evaluates the heads and ``Q`` once on the
    (flattened) minibatch, writing them into a shallow copy of it, draws the
    multi-updates weights with :meth:`option_weights`, then assembles
    :meth:`intra_option_loss` (``loss_objective``, ``loss_entropy``, using
    :meth:`importance_log_ratio`), :meth:`critic_loss`,
    :meth:`termination_loss` and :meth:`option_policy_loss`
    (``loss_option``, ``loss_option_entropy``; both use
    :meth:`option_advantages`), the data metrics of :meth:`option_metrics`
    and :meth:`termination_diagnostics` (whether options are alive). Each term takes that tensordict (and the weights
    where it needs them) and returns ``(losses, metrics)``, two dicts of
    tensors; the output keeps the order of :attr:`out_keys`, then any extra
    entries. To change one term (Option-Critic's deliberation cost, PPOC's
    weights, a new HRL loss), subclass and override that method only.

    Args:
        actor_network: the :class:`~torchrl_offhrl.modules.OptionCriticActor`
            (or any module with ``get_option_heads`` and ``get_dist``).
        critic_network: a module ``observation -> option_value [*, n]``
            (:func:`~torchrl_offhrl.modules.make_option_critic`).
        num_options: checked against the actor's (required when the actor
            has no ``num_options``).
        eta: multi-updates probability (0.7 in the paper).
        clip_epsilon: PPO clip (0.2).
        xi: termination regulariser (0 in MOC; Option-Critic uses ~0.01).
        normalize_option_advantages: divide the option advantages
            ``Q(s, o) - V(s)`` of the termination and policy-over-options losses
            by their standard deviation over the batch (before adding ``xi``;
            not in MOC, off by default). With raw returns of order 100, the
            termination logits and pi_O otherwise saturate within a few
            thousand updates (one option runs whole episodes) and the entropy
            bonus and ``xi`` are negligible; normalised, they are in units of
            the advantages' spread.
        critic_coef, termination_coef, option_coef: loss weights.
        entropy_coef: intra-option entropy bonus.
        option_entropy_coef: entropy bonus of ``pi_O`` (0.01).
        prior_coef: weight of a soft trust region around the latent prior's
            mode (0: off): ``loss_prior = prior_coef * 0.5 * ||a_o(s)||^2``
            for every option's mode action ``a_o(s)`` (the action the
            deterministic policy runs), ``w``-weighted as the entropy term.
            In a latent action space whose prior is ``N(0, I)`` it is the
            prior's negative log-density at the mode, up to a constant: a
            penalty that grows as the evaluated policy leaves the region the
            decoder was trained on, where a box bound is all or nothing.
        normalize_advantage: standardise the advantage within each call.
        gamma, lmbda: the default value estimator's discount and GAE lambda.
        importance_correction: ``"assignment"`` (default, as before),
            ``"next_step"`` (the official MOC correction; call
            :meth:`prepare_batch` on each batch) or ``"none"``; see
            :attr:`IMPORTANCE_CORRECTIONS`.

    Examples:
        >>> import torch
        >>> from torchrl.envs import GymEnv, TransformedEnv, Compose
        >>> from torchrl_offhrl.modules import OptionCriticActor, OptionHeads, make_option_critic
        >>> from torchrl_offhrl.objectives import OptionCriticLoss
        >>> heads = OptionHeads(3, 1, num_options=4, hidden=(16,))
        >>> actor = OptionCriticActor(heads, low=-2.0, high=2.0)
        >>> critic = make_option_critic(3, num_options=4, hidden=(16,))
        >>> env = TransformedEnv(GymEnv("Pendulum-v1"), Compose(*actor.make_transforms()))
        >>> with torch.no_grad():
        ...     batch = env.rollout(16, actor)
        >>> loss = OptionCriticLoss(actor, critic, num_options=4, eta=0.7, clip_epsilon=0.2)
        >>> _ = loss.value_estimator(batch)
        >>> out = loss(batch)
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_critic', 'loss_entropy', 'loss_objective', 'loss_option', 'loss_option_entropy', 'loss_termination']
        >>> out["option_usage"].shape
        torch.Size([4])

        Overriding one term: Option-Critic's termination gradient with a
        constant deliberation cost instead of ``xi`` (the other terms are
        unchanged):

        >>> class DeliberationCostLoss(OptionCriticLoss):
        ...     def __init__(self, *args, deliberation_cost=0.01, **kwargs):
        ...         super().__init__(*args, **kwargs)
        ...         self.deliberation_cost = deliberation_cost
        ...
        ...     def termination_loss(self, td):
        ...         k = self.tensor_keys
        ...         prev = td.get(k.prev_option).long().reshape(-1, 1)
        ...         beta = td.get(k.termination_probs).gather(-1, prev).squeeze(-1)
        ...         q = td.get(k.option_value).detach()
        ...         v = (torch.softmax(td.get(k.option_logits).detach(), -1) * q).sum(-1)
        ...         cont = ~td.get(k.is_init).reshape(-1).bool()
        ...         adv = q.gather(-1, prev).squeeze(-1) - v + self.deliberation_cost
        ...         return {"loss_termination": (beta * adv)[cont].mean()}, {}
        >>> oc = DeliberationCostLoss(actor, critic, deliberation_cost=0.02)
        >>> _ = torch.manual_seed(0)  # the same z in both calls
        >>> a = loss(batch)
        >>> _ = torch.manual_seed(0)
        >>> b = oc(batch)
        >>> [k for k in a.keys() if not torch.equal(a[k], b[k])]
        ['loss_termination']
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss; change them with :meth:`set_keys`.

        Data: ``observation``, ``action``, ``option``, ``prev_option``,
        ``is_init``, ``option_start`` and ``termination_prob`` (metrics only,
        optional), ``option_log_probs``, ``assignment_log_prob``,
        ``advantage``, ``value_target``, ``reward``, ``done``, ``terminated``.
        Written by the actor's ``get_option_heads`` and read back by the
        terms: ``option_logits``, ``option_loc``, ``option_scale``,
        ``termination_probs``; by the critic: ``option_value``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        option: NestedKey = "option"
        prev_option: NestedKey = "prev_option"
        is_init: NestedKey = "is_init"
        option_start: NestedKey = "option_start"
        termination_prob: NestedKey = "termination_prob"
        option_log_probs: NestedKey = "option_log_probs"
        assignment_log_prob: NestedKey = "option_assignment_log_prob"
        advantage: NestedKey = "advantage"
        value_target: NestedKey = "value_target"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        option_logits: NestedKey = "option_logits"
        option_loc: NestedKey = "option_loc"
        option_scale: NestedKey = "option_scale"
        termination_probs: NestedKey = "termination_probs"
        option_value: NestedKey = "option_value"
        next_assignment_log_ratio: NestedKey = "next_assignment_log_ratio"

    #: ``"assignment"``: ``log P_t(o) - log P_t(o_t)`` (this project's first version; the weights
    #: ``w_t(o)`` already carry ``P_t(o)``, so it counts it twice); ``"next_step"``: the official MOC
    #: correction ``log P(o_{t+1}|s_{t+1}, o) - log P(o_{t+1}|s_{t+1}, o_t)``, precomputed per batch by
    #: :meth:`annotate_next_assignment` (0 where no next step is in the batch); ``"none"``: the action ratio only.
    IMPORTANCE_CORRECTIONS = ("assignment", "next_step", "none")

    #: methods the actor must provide (checked at construction)
    required_actor_methods = ("get_option_heads", "get_dist")

    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.GAE
    tensor_keys: _AcceptedKeys
    actor_network: nn.Module
    critic_network: TensorDictModule
    actor_network_params: TensorDictParams
    critic_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_critic_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: nn.Module,
        critic_network: TensorDictModule,
        *,
        num_options: int | None = None,
        eta: float = 0.7,
        clip_epsilon: float = 0.2,
        xi: float = 0.0,
        normalize_option_advantages: bool = False,
        critic_coef: float = 0.5,
        termination_coef: float = 1.0,
        option_coef: float = 1.0,
        entropy_coef: float = 0.0,
        option_entropy_coef: float = 0.01,
        prior_coef: float = 0.0,
        normalize_advantage: bool = True,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        importance_correction: str = "assignment",
    ):
        super().__init__()
        self._check_actor(actor_network)
        if importance_correction not in self.IMPORTANCE_CORRECTIONS:
            raise ValueError(f"importance_correction must be one of {self.IMPORTANCE_CORRECTIONS}, got {importance_correction!r}")
        self.importance_correction = importance_correction
        actor_options = getattr(actor_network, "num_options", None)
        if actor_options is None and num_options is None:
            raise TypeError(f"{type(actor_network).__name__} has no num_options attribute: pass num_options=")
        if num_options is not None and actor_options is not None and num_options != actor_options:
            raise ValueError(f"num_options={num_options} but the actor has {actor_options} options")
        if not 0.0 <= eta <= 1.0:
            raise ValueError(f"eta must be in [0, 1], got {eta}")
        if clip_epsilon <= 0:
            raise ValueError(f"clip_epsilon must be > 0, got {clip_epsilon}")
        self.num_options = int(actor_options if actor_options is not None else num_options)
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(critic_network, "critic_network")
        self.eta = float(eta)
        self.clip_epsilon = float(clip_epsilon)
        self.xi = float(xi)
        self.normalize_option_advantages = normalize_option_advantages
        self.critic_coef = float(critic_coef)
        self.termination_coef = float(termination_coef)
        self.option_coef = float(option_coef)
        self.entropy_coef = float(entropy_coef)
        self.option_entropy_coef = float(option_entropy_coef)
        if prior_coef < 0:
            raise ValueError(f"prior_coef must be >= 0, got {prior_coef}")
        self.prior_coef = float(prior_coef)
        self.normalize_advantage = normalize_advantage
        self._gamma, self._lmbda = gamma, lmbda
        self.set_keys(**self._keys_from_networks(actor_network, critic_network))
        self._value_estimator = None

    def _check_actor(self, actor_network) -> None:
        if not isinstance(actor_network, nn.Module):
            raise TypeError(f"actor_network must be a torch.nn.Module, got {type(actor_network).__name__}")
        for name in self.required_actor_methods:
            if not callable(getattr(actor_network, name, None)):
                raise TypeError(
                    f"actor_network ({type(actor_network).__name__}) has no method {name}(tensordict), which "
                    f"{type(self).__name__} needs (required: {', '.join(self.required_actor_methods)}; "
                    "see OptionCriticActor)"
                )

    def _keys_from_networks(self, actor_network, critic_network) -> dict:
        """The key names the actor and critic use, for the fields the loss shares with them."""
        names = set(self._AcceptedKeys.__dataclass_fields__)
        actor_keys = getattr(actor_network, "tensor_keys", None)
        keys = {}
        if actor_keys is not None:
            for name in names:
                value = getattr(actor_keys, name, None)
                if value is not None:
                    keys[name] = value
        else:
            for name, attr in (("observation", "observation_key"), ("action", "action_key")):
                value = getattr(actor_network, attr, None)
                if value is not None:
                    keys[name] = value
        critic_out = getattr(critic_network, "out_keys", None)
        if critic_out:
            keys["option_value"] = critic_out[0]
        return keys

    # ------------------------------------------------------------------ keys
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            k = self.tensor_keys
            self._value_estimator.set_keys(
                advantage=k.advantage,
                value_target=k.value_target,
                value=k.option_value,
                option=k.option,
                option_logits=k.option_logits,
                termination_probs=k.termination_probs,
                reward=k.reward,
                done=k.done,
                terminated=k.terminated,
            )
        self._set_in_keys()

    def _set_in_keys(self):
        k = self.tensor_keys
        self._in_keys = [
            k.observation, k.action, k.option, k.prev_option, k.is_init, k.option_log_probs, k.assignment_log_prob,
            ("next", k.observation), ("next", k.reward), ("next", k.done), ("next", k.terminated),
        ]

    @property
    def in_keys(self):
        if getattr(self, "_in_keys", None) is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values):
        self._in_keys = values

    @property
    def out_keys(self):
        return [
            "loss_objective", "loss_critic", "loss_termination", "loss_option", "loss_option_entropy", "loss_entropy", "loss_prior",
            "termination_rate", "option_duration", "option_usage", "clip_fraction", "approx_kl", "action_std", "option_entropy", "z",
            "option_usage_entropy", "termination_advantage", "termination_advantage_positive", "explained_variance",
        ]

    # ------------------------------------------------------- value estimator
    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams):
        """Only GAE over option values is supported (``gamma``, ``lmbda``, ``differentiable``, ``time_dim``)."""
        value_type = value_type or self.default_value_estimator
        if value_type != ValueEstimators.GAE:
            raise NotImplementedError(
                f"OptionCriticLoss supports ValueEstimators.GAE only (advantage of Q(s,o) bootstrapped on U(s',o)); got {value_type}"
            )
        gamma = hyperparams.pop("gamma", self._gamma)
        lmbda = hyperparams.pop("lmbda", self._lmbda)
        extra = {name: hyperparams.pop(name) for name in ("differentiable", "time_dim") if name in hyperparams}
        if hyperparams:
            raise TypeError(f"unexpected value-estimator arguments {sorted(hyperparams)}")
        self._value_estimator = OptionGAE(self, gamma=gamma, lmbda=lmbda, **extra)
        self._forward_value_estimator_keys()
        return self

    @property
    def value_estimator(self) -> OptionGAE:
        if self._value_estimator is None:
            self.make_value_estimator()
        return self._value_estimator

    @value_estimator.setter
    def value_estimator(self, value):
        self._value_estimator = value

    # ------------------------------------------------------- functional calls
    def option_heads(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The actor's ``get_option_heads`` with the loss's parameters: writes the heads' outputs into ``tensordict``."""
        with self.actor_network_params.to_module(self.actor_network):
            return self.actor_network.get_option_heads(tensordict)

    def option_values(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The critic with the loss's parameters: writes ``option_value`` ``[*, n]`` into ``tensordict``."""
        with self.critic_network_params.to_module(self.critic_network):
            return self.critic_network(tensordict)

    def option_dist(self, tensordict: TensorDictBase):
        """The actor's ``get_dist`` with the loss's parameters: the intra-option distributions of all options."""
        with self.actor_network_params.to_module(self.actor_network):
            return self.actor_network.get_dist(tensordict)

    @torch.no_grad()
    def annotate_next_assignment(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write ``next_assignment_log_ratio`` ``[*, T, n]``: ``log P(o_{t+1}|s_{t+1}, o) - log P(o_{t+1}|s_{t+1}, o_t)``.

        ``P(o'|s', o) = beta(s', o) pi_O(o'|s') + (1 - beta(s', o)) [o' == o]`` is
        the probability that the actor, holding option ``o``, runs ``o'`` at the
        next step; ``o_{t+1}`` is the option the data ran there. The data's
        last batch dimension is time; the ratio is 0 after a ``done`` and at
        the batch's last step (the next option is not in the batch), and 0
        for ``o = o_t``. Computed with the loss's current parameters.
        """
        k = self.tensor_keys
        option = tensordict.get(k.option).long()
        nxt = self.option_heads(tensordict.get("next").copy())
        pi_n = torch.softmax(nxt.get(k.option_logits), -1)  # [*, T, n]
        beta_n = nxt.get(k.termination_probs)  # [*, T, n]: beta(s_{t+1}, o) for every o
        o_next = torch.cat([option[..., 1:], option[..., -1:]], -1)  # [*, T]
        pi_next = pi_n.gather(-1, o_next.unsqueeze(-1))  # [*, T, 1]
        same = F.one_hot(o_next, self.num_options).to(beta_n.dtype)
        log_p = (beta_n * pi_next + (1 - beta_n) * same).clamp_min(1e-12).log()  # [*, T, n]
        ratio = log_p - log_p.gather(-1, option.unsqueeze(-1))
        done = tensordict.get(("next", k.done)).reshape(option.shape)
        valid = ~done
        valid[..., -1] = False
        tensordict.set(k.next_assignment_log_ratio, torch.where(valid.unsqueeze(-1), ratio, torch.zeros_like(ratio)))
        return tensordict

    @torch.no_grad()
    def prepare_batch(self, tensordict: TensorDictBase, advantage: bool = True) -> TensorDictBase:
        """Everything a ``[envs, time]`` batch needs before it is split into minibatches: the advantage (and the next-step ratio).

        ``advantage=False``: the rest only (a seeds' batch writes the advantage itself: the estimator's networks per
        seed, its recursion on all seeds at once).
        """
        if advantage:
            self.value_estimator(tensordict)
        if self.importance_correction == "next_step":
            self.annotate_next_assignment(tensordict)
        return tensordict

    # ----------------------------------------------------------------- terms
    def option_weights(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """Multi-updates weights ``w_t(o) = z P_t(o) + (1 - z) [o == o_t]`` (detached, ``[B, n]``) and ``z``.

        ``z ~ Bernoulli(eta)`` is drawn here (one ``torch.rand(())``, only when
        ``0 < eta < 1``).
        """
        k = self.tensor_keys
        option = td.get(k.option).long().reshape(-1)
        log_assign = td.get(k.assignment_log_prob)
        onehot = F.one_hot(option, self.num_options).to(log_assign.dtype)
        # a tensor, not a Python float: the draw stays on the device and the loss can run under torch.vmap (a seeds' batch)
        z = (torch.rand(()) < self.eta).to(log_assign) if 0.0 < self.eta < 1.0 else log_assign.new_tensor(self.eta)
        weights = z * log_assign.exp() + (1.0 - z) * onehot
        return weights.detach(), z

    def importance_log_ratio(self, td: TensorDictBase, log_prob: torch.Tensor) -> torch.Tensor:
        """The log importance ratio for updating every option ``o`` with the data of ``o_t``, ``[B, n]``.

        ``log pi_o(a|s) - log pi_{o_t,old}(a|s)`` plus, by ``importance_correction``,
        ``log P_t(o) - log P_t(o_t)`` (``"assignment"``), the stored
        next-step assignment ratio (``"next_step"``, official MOC) or nothing
        (``"none"``). ``log_prob`` is the current ``log pi_o(a_t|s_t)`` of every option.
        """
        k = self.tensor_keys
        o = td.get(k.option).long().reshape(-1).unsqueeze(-1)
        old_exec = td.get(k.option_log_probs).gather(-1, o)
        if self.importance_correction == "none":
            return log_prob - old_exec
        if self.importance_correction == "next_step":
            if k.next_assignment_log_ratio not in td.keys(True):
                raise KeyError(
                    f"importance_correction='next_step' needs {k.next_assignment_log_ratio!r}: call "
                    "loss.prepare_batch(batch) (or loss.annotate_next_assignment(batch)) on the [envs, time] batch before splitting it"
                )
            return log_prob - old_exec + td.get(k.next_assignment_log_ratio).reshape(log_prob.shape)
        log_assign = td.get(k.assignment_log_prob)
        return log_prob - old_exec + log_assign - log_assign.gather(-1, o)

    def intra_option_loss(self, td: TensorDictBase, weights: torch.Tensor) -> tuple[dict, dict]:
        """PPO-clipped surrogate of every option and the intra-option entropy bonus (and, with ``prior_coef``, the prior term).

        Returns ``({"loss_objective", "loss_entropy"[, "loss_prior"]}, {"clip_fraction", "approx_kl", "action_std"})``.
        """
        k = self.tensor_keys
        action = td.get(k.action)
        o = td.get(k.option).long().reshape(-1).unsqueeze(-1)
        dist = self.option_dist(td)
        new_logp = dist.log_prob(action.unsqueeze(-2))  # [B, n]
        ratio = self.importance_log_ratio(td, new_logp).exp()
        adv = td.get(k.advantage).reshape(-1)
        if self.normalize_advantage and adv.numel() > 1:
            adv = (adv - adv.mean()) / adv.std().clamp_min(1e-8)
        adv = adv.detach().unsqueeze(-1)
        eps = self.clip_epsilon
        surrogate = torch.minimum(ratio * adv, ratio.clamp(1 - eps, 1 + eps) * adv)
        loss_objective = -(weights * surrogate).sum(-1).mean()
        scale = td.get(k.option_scale)
        gauss_entropy = (0.5 * math.log(2 * math.pi * math.e) + scale.log()).sum(-1)  # [B, n]
        loss_entropy = -self.entropy_coef * (weights * gauss_entropy).sum(-1).mean()
        with torch.no_grad():
            clipped = ((ratio - 1).abs() > eps).to(ratio.dtype)
            clip_fraction = (weights * clipped).sum() / weights.sum().clamp_min(1e-8)
            old_exec = td.get(k.option_log_probs).gather(-1, o)
            approx_kl = (old_exec.squeeze(-1) - new_logp.gather(-1, o).squeeze(-1)).mean()
            action_std = scale.detach().gather(-2, o.unsqueeze(-1).expand(-1, 1, scale.shape[-1])).mean()
        metrics = {"clip_fraction": clip_fraction, "approx_kl": approx_kl, "action_std": action_std}
        losses = {"loss_objective": loss_objective, "loss_entropy": loss_entropy}
        if self.prior_coef > 0:  # every option's mode action (what the deterministic policy runs), [B, n, A]
            mode_sq = dist.deterministic_sample.pow(2).sum(-1)  # [B, n]
            losses["loss_prior"] = self.prior_coef * 0.5 * (weights * mode_sq).sum(-1).mean()
            metrics["mode_norm"] = mode_sq.detach().gather(-1, o).sqrt().mean()
        return losses, metrics

    def critic_loss(self, td: TensorDictBase, weights: torch.Tensor) -> tuple[dict, dict]:
        """``critic_coef * sum_o w_t(o) (Q(s_t, o) - G_t)^2``, averaged: ``({"loss_critic"}, {})``."""
        k = self.tensor_keys
        q = td.get(k.option_value)
        target = td.get(k.value_target).reshape(-1)
        loss_critic = self.critic_coef * (weights * (q - target.detach().unsqueeze(-1)).pow(2)).sum(-1).mean()
        with torch.no_grad():  # how much of the targets' variance Q(s_t, o_t) explains (PPO logs the same for V)
            o = td.get(k.option).long().reshape(-1).unsqueeze(-1)
            q_exec = q.detach().gather(-1, o).squeeze(-1)
            explained = 1 - (target - q_exec).var(unbiased=False) / target.var(unbiased=False).clamp_min(1e-12)
        return {"loss_critic": loss_critic}, {"explained_variance": explained}

    def option_advantages(self, td: TensorDictBase) -> torch.Tensor:
        """``Q(s, o) - V(s)`` for every option (detached, ``[B, n]``), optionally normalised by its std."""
        k = self.tensor_keys
        q_d = td.get(k.option_value).detach()
        pi = torch.softmax(td.get(k.option_logits).detach(), -1)
        v = (pi * q_d).sum(-1)
        option_adv = q_d - v.unsqueeze(-1)
        if self.normalize_option_advantages and option_adv.numel() > 1:
            option_adv = option_adv / option_adv.std().clamp_min(1e-8)
        return option_adv

    def termination_loss(self, td: TensorDictBase) -> tuple[dict, dict]:
        """``termination_coef * beta(s_t, o_{t-1}) (Q(s_t, o_{t-1}) - V(s_t) + xi)`` over non-start steps: ``({"loss_termination"}, {})``."""
        k = self.tensor_keys
        p = td.get(k.prev_option).long().reshape(-1).unsqueeze(-1)
        is_init = td.get(k.is_init).reshape(-1).bool()
        beta = td.get(k.termination_probs)
        beta_prev = beta.gather(-1, p).squeeze(-1)
        cont = (~is_init).to(beta.dtype)
        termination_adv = self.option_advantages(td).gather(-1, p).squeeze(-1) + self.xi
        loss_termination = self.termination_coef * (beta_prev * termination_adv * cont).sum() / cont.sum().clamp_min(1.0)
        return {"loss_termination": loss_termination}, {}

    def option_policy_loss(self, td: TensorDictBase) -> tuple[dict, dict]:
        """The policy-over-options gradient and its entropy bonus.

        Returns ``({"loss_option", "loss_option_entropy"}, {"option_entropy"})``.
        """
        k = self.tensor_keys
        logits = td.get(k.option_logits)
        pi = torch.softmax(logits, -1)
        log_pi = torch.log_softmax(logits, -1)
        p = td.get(k.prev_option).long().reshape(-1).unsqueeze(-1)
        is_init = td.get(k.is_init).reshape(-1).bool()
        beta_prev = td.get(k.termination_probs).detach().gather(-1, p).squeeze(-1)
        beta_sel = torch.where(is_init, torch.ones_like(beta_prev), beta_prev)
        loss_option = -self.option_coef * (beta_sel * (pi * self.option_advantages(td)).sum(-1)).mean()
        option_entropy = -(pi * log_pi).sum(-1).mean()
        loss_option_entropy = -self.option_entropy_coef * option_entropy
        return {"loss_option": loss_option, "loss_option_entropy": loss_option_entropy}, {"option_entropy": option_entropy.detach()}

    @torch.no_grad()
    def termination_diagnostics(self, td: TensorDictBase) -> dict:
        """Where terminations are decided (non-start steps): is the running option better than average?

        ``termination_advantage``: the mean of ``Q(s_t, o_{t-1}) - V(s_t)``
        (raw, current critic and pi_O); ``termination_advantage_positive``: the
        fraction of those steps where it is positive. The termination gradient
        pushes ``beta`` down where it is positive, so a fraction near 1 at every
        step means terminations collapse (options never end); near 0, options
        end at once.
        """
        k = self.tensor_keys
        p = td.get(k.prev_option).long().reshape(-1).unsqueeze(-1)
        cont = ~td.get(k.is_init).reshape(-1).bool()
        q = td.get(k.option_value).detach()
        v = (torch.softmax(td.get(k.option_logits).detach(), -1) * q).sum(-1)
        adv = q.gather(-1, p).squeeze(-1) - v
        c = cont.to(q.dtype)
        n = c.sum()  # means over the non-start steps as masked sums (no data-dependent shapes: vmappable); 0 / 0 = nan when none
        return {"termination_advantage": (adv * c).sum() / n, "termination_advantage_positive": ((adv > 0).to(q.dtype) * c).sum() / n}

    @torch.no_grad()
    def option_metrics(self, td: TensorDictBase) -> dict:
        """Metrics of the data: ``termination_rate``, ``option_duration``, ``option_usage`` and its entropy ``option_usage_entropy`` (nats; ``log n`` when every option runs equally often, 0 when one runs alone)."""
        k = self.tensor_keys
        option = td.get(k.option).long().reshape(-1)
        prev = td.get(k.prev_option).long().reshape(-1)
        is_init = td.get(k.is_init).reshape(-1).bool()
        data_beta = td.get(k.termination_prob, None)
        cont = (~is_init).to(data_beta.dtype if data_beta is not None else torch.float32)
        if data_beta is not None:  # 0 / 0 = nan without non-start steps
            termination_rate = (data_beta.reshape(-1) * cont).sum() / cont.sum()
        else:
            termination_rate = torch.tensor(float("nan"))
        starts = td.get(k.option_start, None)
        n_starts = starts.reshape(-1).sum() if starts is not None else (is_init | (option != prev)).sum()
        option_duration = option.numel() / n_starts.clamp_min(1).to(torch.float32)
        usage = F.one_hot(option, self.num_options).to(td.get(k.assignment_log_prob).dtype).mean(0)
        usage_entropy = -(usage * usage.clamp_min(1e-12).log()).sum()
        return {"termination_rate": termination_rate, "option_duration": option_duration, "option_usage": usage, "option_usage_entropy": usage_entropy}

    # ---------------------------------------------------------------- forward
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        k = self.tensor_keys
        if k.advantage not in tensordict.keys(True):
            tensordict = self.prepare_batch(tensordict.copy())
        # a shallow copy: the heads and Q are written into it, not into the caller's data
        td = tensordict.reshape(-1).copy()
        td = self.option_heads(td)
        td = self.option_values(td)
        weights, z = self.option_weights(td)
        entries = {}
        for losses, metrics in (
            self.intra_option_loss(td, weights),
            self.critic_loss(td, weights),
            self.termination_loss(td),
            self.option_policy_loss(td),
        ):
            entries.update(losses)
            entries.update(metrics)
        entries.update(self.option_metrics(td))
        entries.update(self.termination_diagnostics(td))
        entries["z"] = z
        out = {key: entries.pop(key) for key in self.out_keys if key in entries}
        out.update(entries)
        return TensorDict(out, batch_size=[])
