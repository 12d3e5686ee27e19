"""Option-critic networks and rollout-time option selection.

An agent with ``n`` options has, for a state ``s``:

* a policy over options ``pi_O(o|s)`` (categorical logits ``[n]``),
* ``n`` intra-option policies ``pi_o(a|s)``: tanh-squashed Gaussians bounded
  to the action box (or the latent-action box under
  :class:`~torchrl_offhrl.envs.LatentActionTransform`),
* a termination head ``beta(s, o)`` (one sigmoid per option),
* option values ``Q(s, o)`` (the critic, :class:`OptionValueNet`).

:class:`OptionHeads` computes the first three for every option at once;
:class:`OptionCriticActor` runs them during rollouts: it carries the current
option across steps in ``prev_option`` (declared with a
:class:`~torchrl.envs.TensorDictPrimer`, see :meth:`OptionCriticActor.make_transforms`),
terminates it with probability ``beta(s, prev_option)``, picks a new option
from ``pi_O`` when it terminates or when the episode starts (``is_init`` from
:class:`~torchrl.envs.InitTracker`), then acts with that option's policy.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey, unravel_key
from torch import nn

from ..nets import ObservationNormalizer, activation_class, mlp

__all__ = ["ObservationNormalizer", "OptionCriticActor", "OptionHeads", "OptionValueNet", "make_option_critic"]

class OptionHeads(nn.Module):
    """Policy over options, intra-option Gaussians and terminations for all options.

    ``forward(observation)`` returns ``(option_logits [*, n], loc [*, n, A],
    scale [*, n, A], termination [*, n])``. ``loc``/``scale`` parametrise the
    pre-tanh Gaussian of each option; ``scale`` is a state-independent learned
    parameter per option and action dimension (as in PPO for MuJoCo).

    Args:
        obs_dim, act_dim, num_options: sizes.
        hidden: hidden layer sizes of each tower (or of the shared trunk).
        shared_trunk: one trunk feeding three linear heads (``True``) or a
            separate tower per head (``False``, the official MOC layout).
        activation: ``"tanh"`` (default, MOC's choice), ``"relu"`` or ``"elu"``.
        obs_loc, obs_scale: optional normalisation statistics.
        init_log_std: initial log standard deviation of the pre-tanh Gaussians.
        obs_clip: clip the normalised observations to ``[-obs_clip, obs_clip]``
            (official MOC: 5; None: no clip).
        option_head_gain, termination_head_gain: orthogonal-init gain of the
            last layer of pi_O and of the termination head. 0.01 (default)
            starts near-uniform pi_O and beta ~ 0.5 everywhere; 1.0 starts
            with O(1) logits that depend on the state, as the official code's
            ``normc(1.0)`` initialisation.
        intra_head_gain: orthogonal-init gain of the last layer of the
            intra-option means. 0.01 (default, the scale of
            baselines' ``normc(0.01)`` policy head) starts every option near
            the box's centre; 1.0
            starts with O(1) state-dependent means, about the scale of a
            default-initialised layer (TorchRL's PPO actor).

    Examples:
        >>> heads = OptionHeads(5, 2, num_options=3, hidden=(16,))
        >>> logits, loc, scale, beta = heads(torch.zeros(4, 5))
        >>> logits.shape, loc.shape, scale.shape, beta.shape
        (torch.Size([4, 3]), torch.Size([4, 3, 2]), torch.Size([4, 3, 2]), torch.Size([4, 3]))
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        num_options: int,
        hidden: Sequence[int] = (64, 64),
        shared_trunk: bool = False,
        activation: str = "tanh",
        obs_loc: torch.Tensor | None = None,
        obs_scale: torch.Tensor | None = None,
        init_log_std: float = 0.0,
        obs_clip: float | None = None,
        option_head_gain: float = 0.01,
        termination_head_gain: float = 0.01,
        intra_head_gain: float = 0.01,
    ):
        super().__init__()
        if num_options < 1:
            raise ValueError(f"num_options must be >= 1, got {num_options}")
        self.obs_dim, self.act_dim, self.num_options = obs_dim, act_dim, num_options
        self.shared_trunk = shared_trunk
        self.normalizer = ObservationNormalizer(obs_dim, obs_loc, obs_scale, clip=obs_clip)
        n, a = num_options, act_dim
        if shared_trunk:
            hidden = list(hidden)
            self.trunk = nn.Sequential(mlp(obs_dim, hidden[-1], hidden[:-1], activation), activation_class(activation)())
            self.option_head = nn.Linear(hidden[-1], n)
            self.intra_head = nn.Linear(hidden[-1], n * a)
            self.termination_head = nn.Linear(hidden[-1], n)
        else:
            self.trunk = nn.Identity()
            self.option_head = mlp(obs_dim, n, hidden, activation)
            self.intra_head = mlp(obs_dim, n * a, hidden, activation)
            self.termination_head = mlp(obs_dim, n, hidden, activation)
        self.log_std = nn.Parameter(torch.full((n, a), float(init_log_std)))
        # small last layers by default: near-uniform pi_O, near-zero means, beta ~ 0.5
        for head, gain in ((self.option_head, option_head_gain), (self.intra_head, intra_head_gain), (self.termination_head, termination_head_gain)):
            last = head if isinstance(head, nn.Linear) else head[-1]
            nn.init.orthogonal_(last.weight, gain=gain)
            nn.init.zeros_(last.bias)

    def forward(self, observation: torch.Tensor):
        h = self.trunk(self.normalizer(observation))
        logits = self.option_head(h)
        loc = self.intra_head(h).unflatten(-1, (self.num_options, self.act_dim))
        scale = self.log_std.clamp(-5.0, 2.0).exp().expand_as(loc)
        termination = torch.sigmoid(self.termination_head(h))
        return logits, loc, scale, termination


class OptionValueNet(nn.Module):
    """``Q(s, o)`` for every option: ``observation [*, D] -> [*, n]``."""

    def __init__(self, obs_dim: int, num_options: int, hidden: Sequence[int] = (64, 64), activation: str = "tanh", obs_loc=None, obs_scale=None,
                 obs_clip: float | None = None):
        super().__init__()
        self.num_options = num_options
        self.normalizer = ObservationNormalizer(obs_dim, obs_loc, obs_scale, clip=obs_clip)
        self.net = mlp(obs_dim, num_options, hidden, activation)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.net(self.normalizer(observation))


def make_option_critic(obs_dim: int, num_options: int, hidden=(64, 64), activation: str = "tanh", obs_loc=None, obs_scale=None, observation_key="observation",
                       out_key="option_value", obs_clip: float | None = None) -> TensorDictModule:
    """The critic as a TensorDict module: ``observation -> option_value [*, n]``.

    Examples:
        >>> from tensordict import TensorDict
        >>> critic = make_option_critic(3, num_options=4, hidden=(8,))
        >>> critic(TensorDict(observation=torch.zeros(2, 3), batch_size=[2]))["option_value"].shape
        torch.Size([2, 4])
    """
    return TensorDictModule(OptionValueNet(obs_dim, num_options, hidden, activation, obs_loc, obs_scale, obs_clip), in_keys=[observation_key], out_keys=[out_key])


def _is_deterministic() -> bool:
    from torchrl.envs.utils import ExplorationType, exploration_type

    return exploration_type() in (ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.MEAN)


class OptionCriticActor(TensorDictModuleBase):
    """Rollout-time option-critic policy: keeps an option, terminates it, picks the next, acts.

    At every step, with ``beta = beta(s, prev_option)`` (forced to 1 where
    ``is_init`` marks an episode start): terminate with probability ``beta``;
    on termination draw a new option from ``pi_O(.|s)``; then sample the action
    from that option's tanh-Gaussian. In deterministic exploration mode
    (``set_exploration_type(ExplorationType.DETERMINISTIC)``) it terminates
    when ``beta > 0.5``, takes the most likely option and the mode of the
    action distribution.

    Reads ``observation``, ``prev_option`` and ``is_init``; writes ``option``,
    ``option_start`` (a new option was picked this step),
    ``termination_prob`` (``beta(s, prev_option)``, 1 at episode starts),
    ``option_log_probs`` (``log pi_o(a|s)`` of the taken action under every
    option, ``[*, n]``), ``option_assignment_log_prob`` (``log P_t(o)``, the
    log-probability that option ``o`` executes at this step given
    ``prev_option``, ``[*, n]``), the action, and ``("next", "prev_option")``
    so the option is carried to the next step. The env needs
    :meth:`make_transforms` (an :class:`~torchrl.envs.InitTracker` and a
    :class:`~torchrl.envs.TensorDictPrimer` for ``prev_option``); partial
    resets re-pick the option only in the envs that reset.

    For losses (:class:`~torchrl_offhrl.objectives.OptionCriticLoss`) the actor
    also exposes its heads through tensordicts:
    :meth:`get_option_heads` writes ``option_logits`` (``[*, n]``),
    ``option_loc`` and ``option_scale`` (pre-tanh Gaussian parameters,
    ``[*, n, A]``) and ``termination_probs`` (``beta(s, o)`` for every option,
    ``[*, n]``; not to be confused with the rollout's ``termination_prob``);
    :meth:`get_dist` returns the intra-option distributions of all options from
    those entries (as ``actor.get_dist(td)`` in TorchRL's PPO loss).

    Every key read or written is configurable with :meth:`set_keys` (names in
    :attr:`tensor_keys`: ``observation``, ``action``, ``prev_option``,
    ``is_init``, ``option``, ``option_start``, ``termination_prob``,
    ``option_log_probs``, ``assignment_log_prob``, ``option_logits``,
    ``option_loc``, ``option_scale``, ``termination_probs``);
    :meth:`make_transforms` follows the configured ``prev_option`` and
    ``is_init`` keys. A loss built on the actor afterwards takes the same names.

    Args:
        heads: an :class:`OptionHeads`.
        low, high: the action box the tanh squashes to.
        observation_key: shortcut for ``set_keys(observation=...)``.
        action_key: where to write the action (``"latent_action"`` under the
            latent transform); shortcut for ``set_keys(action=...)``.

    Examples:
        >>> from torchrl.envs import GymEnv, TransformedEnv, Compose
        >>> from torchrl.envs.utils import set_exploration_type, ExplorationType
        >>> heads = OptionHeads(3, 1, num_options=2, hidden=(16,))
        >>> actor = OptionCriticActor(heads, low=-2.0, high=2.0)
        >>> env = TransformedEnv(GymEnv("Pendulum-v1"), Compose(*actor.make_transforms()))
        >>> td = env.rollout(5, actor)
        >>> td["option"].shape, td["option_log_probs"].shape, bool(td["option_start"][0])
        (torch.Size([5]), torch.Size([5, 2]), True)
        >>> bool((td["next", "prev_option"] == td["option"]).all())
        True
        >>> _ = actor.get_option_heads(td)
        >>> td["option_loc"].shape, td["termination_probs"].shape
        (torch.Size([5, 2, 1]), torch.Size([5, 2]))
        >>> actor.get_dist(td).log_prob(td["action"].unsqueeze(-2)).shape  # every option's log-density
        torch.Size([5, 2])

        Renamed keys, e.g. for two option layers in one tensordict:

        >>> actor = OptionCriticActor(heads, low=-2.0, high=2.0).set_keys(
        ...     option=("high", "option"), prev_option=("high", "prev_option"), is_init="first_step")
        >>> env = TransformedEnv(GymEnv("Pendulum-v1"), Compose(*actor.make_transforms()))
        >>> td = env.rollout(3, actor)
        >>> td["high", "option"].shape, bool(td["first_step"][0])
        (torch.Size([3]), True)
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read or written by the actor; change them with :meth:`OptionCriticActor.set_keys`.

        Attributes:
            observation: the state the heads read.
            action: the action written.
            prev_option: the option of the previous step (read; written under
                ``("next", prev_option)`` to carry it over).
            is_init: the episode-start flag (:class:`~torchrl.envs.InitTracker`).
            option: the option executed at this step.
            option_start: whether a new option was picked at this step.
            termination_prob: ``beta(s, prev_option)`` (1 at episode starts).
            option_log_probs: ``log pi_o(a|s)`` under every option, ``[*, n]``.
            assignment_log_prob: ``log P_t(o)``, ``[*, n]``.
            option_logits: the heads' ``pi_O`` logits, ``[*, n]``.
            option_loc, option_scale: the heads' pre-tanh Gaussians, ``[*, n, A]``.
            termination_probs: the heads' ``beta(s, o)`` for every option, ``[*, n]``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        prev_option: NestedKey = "prev_option"
        is_init: NestedKey = "is_init"
        option: NestedKey = "option"
        option_start: NestedKey = "option_start"
        termination_prob: NestedKey = "termination_prob"
        option_log_probs: NestedKey = "option_log_probs"
        assignment_log_prob: NestedKey = "option_assignment_log_prob"
        option_logits: NestedKey = "option_logits"
        option_loc: NestedKey = "option_loc"
        option_scale: NestedKey = "option_scale"
        termination_probs: NestedKey = "termination_probs"

    default_keys = _AcceptedKeys

    def __init__(
        self,
        heads: OptionHeads,
        low: float | torch.Tensor = -1.0,
        high: float | torch.Tensor = 1.0,
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
    ):
        super().__init__()
        self.heads = heads
        self.num_options = heads.num_options
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32).expand(heads.act_dim).clone())
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32).expand(heads.act_dim).clone())
        self._tensor_keys = self._AcceptedKeys()
        self.set_keys(observation=observation_key, action=action_key)

    # ------------------------------------------------------------------ keys
    @property
    def tensor_keys(self) -> _AcceptedKeys:
        """The configured keys (a dataclass; change them with :meth:`set_keys`)."""
        return self._tensor_keys

    @property
    def observation_key(self) -> NestedKey:
        return self._tensor_keys.observation

    @property
    def action_key(self) -> NestedKey:
        return self._tensor_keys.action

    def set_keys(self, **kwargs: NestedKey) -> OptionCriticActor:
        """Rename the tensordict entries the actor reads or writes; returns the actor.

        Names are the fields of :attr:`tensor_keys` (see the class docstring);
        ``None`` restores the default. Keys must be distinct.
        Call it before :meth:`make_transforms` and before building a loss on
        the actor (both read the keys when they are made).
        """
        names = {f.name for f in fields(self._AcceptedKeys)}
        conf = asdict(self._tensor_keys)
        for name, value in kwargs.items():
            if name not in names:
                raise ValueError(f"{name!r} is not a key of {type(self).__name__}; accepted: {sorted(names)}")
            if value is None:
                value = getattr(self.default_keys(), name)
            elif not isinstance(value, (str, tuple)):
                raise TypeError(f"key {name}={value!r} is not a NestedKey (a string or a tuple of strings)")
            conf[name] = unravel_key(value)
        clash = [v for v in conf.values() if list(conf.values()).count(v) > 1]
        if clash:
            raise ValueError(f"two entries share the key {clash[0]!r}: keys must be distinct ({conf})")
        self._tensor_keys = self._AcceptedKeys(**conf)
        k = self._tensor_keys
        self.in_keys = [k.observation, k.prev_option, k.is_init]
        self.out_keys = [
            k.option,
            k.option_start,
            k.termination_prob,
            k.option_log_probs,
            k.assignment_log_prob,
            k.action,
            unravel_key(("next", k.prev_option)),
        ]
        return self

    # ------------------------------------------------------- heads and dists
    def distribution(self, loc: torch.Tensor, scale: torch.Tensor):
        """The tanh-Gaussian of given pre-tanh ``loc``/``scale`` on this actor's box."""
        from torchrl.modules import TanhNormal

        return TanhNormal(loc, scale, low=self.low, high=self.high, safe_tanh=True)

    def get_option_heads(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Run the heads on ``observation`` and write their outputs into ``tensordict``; returns it.

        Writes ``option_logits`` ``[*, n]``, ``option_loc`` and
        ``option_scale`` ``[*, n, A]`` and ``termination_probs`` ``[*, n]``
        (under the configured keys), with gradients.
        """
        k = self._tensor_keys
        logits, loc, scale, beta = self.heads(tensordict.get(k.observation))
        tensordict.set(k.option_logits, logits)
        tensordict.set(k.option_loc, loc)
        tensordict.set(k.option_scale, scale)
        tensordict.set(k.termination_probs, beta)
        return tensordict

    def get_dist(self, tensordict: TensorDictBase):
        """The intra-option distributions of **all** options: batch shape ``[*, n]``, event ``[A]``.

        Built from the ``option_loc``/``option_scale`` entries of
        ``tensordict`` (:meth:`get_option_heads` is called first when they are
        absent; present entries are used as they are). ``log_prob(action.unsqueeze(-2))``
        gives ``log pi_o(a|s)`` for every option, ``[*, n]``.
        """
        k = self._tensor_keys
        if tensordict.get(k.option_loc, None) is None:
            self.get_option_heads(tensordict)
        return self.distribution(tensordict.get(k.option_loc), tensordict.get(k.option_scale))

    def make_transforms(self):
        """``[InitTracker(init_key=is_init), TensorDictPrimer(prev_option)]``: append them to the env."""
        from torchrl.data import Categorical
        from torchrl.envs import InitTracker, TensorDictPrimer

        k = self._tensor_keys
        if not isinstance(k.is_init, str):
            raise ValueError(
                f"is_init={k.is_init!r}: InitTracker writes its flag next to each done entry, so the key must be a "
                "string (set_keys(is_init='...'))"
            )
        return [
            InitTracker(init_key=k.is_init),
            TensorDictPrimer({k.prev_option: Categorical(self.num_options, shape=(), dtype=torch.int64)}, default_value=0, expand_specs=True),
        ]

    # --------------------------------------------------------------- rollout
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        k = self._tensor_keys
        obs = tensordict.get(k.observation)
        batch = obs.shape[:-1]
        is_init = tensordict.get(k.is_init, None)
        if is_init is None:
            raise KeyError(
                f"OptionCriticActor needs {k.is_init!r} to know where episodes start: append "
                "actor.make_transforms() (InitTracker + prev_option primer) to the env."
            )
        is_init = is_init.reshape(batch)
        prev = tensordict.get(k.prev_option, None)
        if prev is None:
            prev = torch.zeros(batch, dtype=torch.long, device=obs.device)
        prev = prev.reshape(batch).long()
        logits, loc, scale, beta = self.heads(obs)
        beta_prev = beta.gather(-1, prev.unsqueeze(-1)).squeeze(-1)
        beta_prev = torch.where(is_init, torch.ones_like(beta_prev), beta_prev)
        pi = torch.softmax(logits, -1)
        onehot = F.one_hot(prev, self.num_options).to(pi.dtype)
        assign = beta_prev.unsqueeze(-1) * pi + (1 - beta_prev.unsqueeze(-1)) * onehot
        det = _is_deterministic()
        if det:
            terminate = beta_prev > 0.5
            new = logits.argmax(-1)
        else:
            terminate = torch.rand_like(beta_prev) < beta_prev
            new = torch.distributions.Categorical(logits=logits).sample()
        terminate = terminate | is_init
        option = torch.where(terminate, new, prev)
        idx = option.reshape(*batch, 1, 1).expand(*batch, 1, loc.shape[-1])
        dist = self.distribution(loc.gather(-2, idx).squeeze(-2), scale.gather(-2, idx).squeeze(-2))
        action = dist.deterministic_sample if det else dist.sample()
        all_logp = self.distribution(loc, scale).log_prob(action.unsqueeze(-2))
        tensordict.set(k.option, option)
        tensordict.set(k.option_start, terminate)
        tensordict.set(k.termination_prob, beta_prev)
        tensordict.set(k.option_log_probs, all_logp)
        tensordict.set(k.assignment_log_prob, assign.clamp_min(1e-12).log())
        tensordict.set(k.action, action)
        tensordict.set(unravel_key(("next", k.prev_option)), option)
        return tensordict
