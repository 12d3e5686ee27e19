"""Seeds as a batch dimension: N copies of one dataset agent (one per seed) trained as one computation.

:class:`SeedBatch` takes N agents of the same class and config, each built
under its own seed (so each starts with the weights its own run would have),
and trains them side by side: every tensor of their losses (parameters,
target networks, normalisation buffers) is stacked along a new leading seed
dimension in one *worker* agent, its optimisers step all seeds at once (Adam
is elementwise: each seed's slice follows its own update), and each loss is
evaluated for all seeds in one ``torch.vmap`` call over the stacked tensors
(TensorDict's ``to_module`` swaps each seed's slice into the module, as in
TensorDict's model-ensembling recipe). The agents' own ``step`` code runs
unchanged: it reaches its losses through :meth:`~torchrl_offhrl.agents.base.Agent.loss_fn`,
which the worker answers with the vmapped loss, and steps its gradients with
:func:`~torchrl_offhrl.agents.base.backward` (the sum over seeds: each
seed's gradient is its own loss's).

A batch is ``[N, batch_size]``: each seed's own minibatch (sampled from its
own RNG stream, :meth:`SeedBatch.sample`). :meth:`SeedBatch.sync` writes each
seed's slice (weights, optimiser states, step count) back into its own agent,
which is what evaluations act with and checkpoints save, so every seed is
still a run of its own.

Batched: BC, TD3+BC, IQL and CQL (:class:`SeedBatch`); PPO and MOC
(:class:`OnPolicySeedBatch`: their policies act as one
:class:`SeedBatchedPolicy` on an env of ``N * E`` envs, their updates
vmapped as above, minibatches shuffled per seed, gradients clipped per
seed); SAC and MOPO (:class:`OffPolicySeedBatch`: the same acting policy,
each seed's own replay buffer, its SAC steps vmapped). Constants every seed holds alike (buffers such as an action box or
the data's observation statistics) stay one unstacked tensor. TorchRL's own ``CQLLoss`` is refused: it
reads its parameters' ``.data`` inside the loss, which ``vmap`` forbids; the
CQL agent's :class:`~torchrl_offhrl.agents.cql.BatchableCQLLoss` is the same
loss with ``.detach()`` there (``tests/test_seed_batch.py`` checks that it
computes what ``CQLLoss`` computes).

What is identical to N separate runs: a deterministic update rule (BC,
IQL, TD3+BC without target-policy noise) gives each seed the same weights as
its own run up to floating-point rounding of the batched matrix products
(``tests/test_seed_batch.py``). Randomness inside a loss (TD3+BC's
target-policy noise, CQL's random actions and policy samples) is drawn per
seed (``randomness="different"``), from other draws than a separate run's:
the same distribution, not the same numbers. With ``randomness="same"`` the
draws are shared by the seeds and equal a separate run's from the same RNG
state: CQL's seeds then match separate agents update for update (the test).
"""
from __future__ import annotations

import contextlib
import copy
from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase

from tensordict.nn import TensorDictModuleBase
from torchrl.objectives import SoftUpdate

from .base import DatasetAgent, MetricMeans, OnPolicyAgent, backward
from .sac import SACAgent

__all__ = ["OffPolicySeedBatch", "OnPolicySeedBatch", "SeedBatch", "SeedBatchedPolicy", "clip_grad_norm_per_seed_", "stacked_module_params"]


#: TorchRL losses that cannot run under ``torch.vmap``, and why
_NOT_VMAPPABLE = {"CQLLoss": "reads its parameters' .data inside the loss (log_alpha, the actor's and critics' weights for its "
                             "sampled actions), which torch.vmap forbids (torchrl_offhrl.agents.cql.BatchableCQLLoss is the same "
                             "loss without it: the CQL agent's)",
                 "KLPENPPOLoss": "adapts its KL coefficient with data-dependent control flow (if kl > 1.5 x target: beta *= 2), which "
                                 "torch.vmap refuses (torchrl_offhrl.agents.ppo.BatchableKLPENPPOLoss is the same loss with the "
                                 "adaptation outside it: the PPO agent's with loss_type=kl)"}

#: leaf names of buffers that are constants of a run, kept unstacked when every seed holds the same values (an action
#: box, the data's observation statistics); any other tensor is stacked per seed, even when the seeds hold it alike
_CONSTANT_LEAVES = ("low", "high", "loc", "scale")


def stacked_module_params(modules) -> TensorDict:
    """N modules of one architecture (e.g. N seeds' policies) as one parameter set for ``torch.vmap``: their tensors
    stacked along a leading seed dimension (batch size ``[N]``, copies, detached), except the constants every module
    holds alike (buffers named as :data:`_CONSTANT_LEAVES`, e.g. the action box or the data's statistics, equal in
    all): those stay the module's own, so that checks such as a distribution's ``(high > low).all()`` see one plain
    tensor, not a batched one. ``params.to_module(modules[0])`` puts one seed's tensors in place (under ``vmap``).
    """
    tds = [TensorDict.from_module(m, as_module=False) for m in modules]
    out = TensorDict(batch_size=[len(tds)])
    for k in tds[0].keys(True, True):
        ts = [td.get(k) for td in tds]
        leaf = k[-1] if isinstance(k, tuple) else k
        if (leaf in _CONSTANT_LEAVES and not isinstance(ts[0], torch.nn.Parameter)
                and all(t.shape == ts[0].shape and torch.equal(t, ts[0]) for t in ts[1:])):
            continue
        out.set(k, torch.stack([t.detach() for t in ts]))
    return out


def _flat_params(opt: torch.optim.Optimizer) -> list:
    """The tensors an optimiser steps, in its groups' order (how a worker's and an agent's optimisers are matched)."""
    return [p for g in opt.param_groups for p in g["params"]]


def _is_constant(key, t: torch.Tensor, others: Sequence[torch.Tensor]) -> bool:
    """Whether a module's tensor is a run constant (:data:`_CONSTANT_LEAVES`, no parameter) every seed holds alike."""
    leaf = key if isinstance(key, str) else key[-1]
    return (leaf in _CONSTANT_LEAVES and not isinstance(t, torch.nn.Parameter)
            and all(o.shape == t.shape and torch.equal(o.to(t.device), t) for o in others))


def _per_element(name: str, value, param: torch.Tensor) -> bool:
    """Whether an optimiser's state entry holds one value per element of its parameter (Adam's moments: stacked and
    sliced per seed) rather than a counter (``step``). By shape, not by dimension: the moments of a scalar parameter (a
    SAC or CQL temperature, ``log_alpha``) are 0-dim too, and each seed has its own."""
    return name != "step" and torch.is_tensor(value) and value.shape == param.shape


def _leaves(loss) -> list[tuple]:
    """The key paths of the loss's tensors (``TensorDict.from_module``), each tensor once (a network shared by two
    parts of a loss, e.g. a value estimator, appears under several keys)."""
    td = TensorDict.from_module(loss, as_module=False)
    seen, keys = set(), []
    for k in td.keys(True, True):
        t = td.get(k)
        if id(t) not in seen:
            seen.add(id(t))
            keys.append(k)
    return keys


def _with_seed_dim(td: TensorDict, n: int | None, loss) -> TensorDict:
    """The same tensors (not copies) under a tree whose batch sizes gain the leading seed dimension ``n`` (None: none).

    ``TensorDict.from_module`` gives every sub-tree batch size ``[]``; a
    loss's parameter sets may have their own (TorchRL's expanded Q-networks:
    ``[2]``), which its own ``vmap`` over them needs: those become ``[n, 2]``,
    so that inside the seeds' ``vmap`` each seed's slice is what the loss expects.
    """
    def tree(sub, batch):
        out = TensorDict(batch_size=batch)
        for k, v in sub.items():
            out.set(k, tree(v, batch) if isinstance(v, TensorDictBase) else v)
        return out

    lead = [] if n is None else [n]
    out = TensorDict(batch_size=lead)
    for k, v in td.items():
        own = getattr(loss, k, None)
        extra = own.batch_size if isinstance(own, TensorDictBase) else torch.Size([])
        out.set(k, tree(v, torch.Size([*lead, *extra])) if isinstance(v, TensorDictBase) else v)
    return out


@contextlib.contextmanager
def _batched_normal_draws(active: bool):
    """Within the seeds' ``vmap``, ``Normal.rsample`` draws its noise with ``torch.randn(shape)``, not ``torch.empty(shape).normal_()``.

    The in-place draw on a fresh (unbatched) tensor is refused by ``vmap``
    under ``randomness="different"``; the out-of-place one is batched, so each
    seed draws its own noise (a policy's reparameterised samples: CQL's
    actions for its penalty and its TD target). The same distribution;
    nothing changes outside the seeds' vmapped loss.
    """
    import torch.distributions.normal as normal_mod

    if not active:
        yield
        return
    own = normal_mod._standard_normal
    normal_mod._standard_normal = lambda shape, dtype=None, device=None: torch.randn(shape, dtype=dtype, device=device)
    try:
        yield
    finally:
        normal_mod._standard_normal = own


@contextlib.contextmanager
def _vmap_safe_reduction(loss):
    """TorchRL's PPO and A2C losses reduce each ``loss_*`` term and then ``.squeeze(-1)`` it: on a 0-dim tensor a no-op,
    but refused inside ``torch.vmap`` (PyTorch 2.13: "Dimension is out of range"). Within the seeds' vmap their
    reduction returns ``[1]`` instead, which the squeeze makes 0-dim again: the same values, per seed."""
    from torchrl.objectives import A2CLoss, PPOLoss

    if not isinstance(loss, (PPOLoss, A2CLoss)):
        yield
        return

    own = type(loss)._reduce_loss

    def reduce(*args, **kwargs):
        out = own(loss, *args, **kwargs)
        return out.unsqueeze(-1) if out.dim() == 0 else out

    loss.__dict__["_reduce_loss"] = reduce
    try:
        yield
    finally:
        loss.__dict__.pop("_reduce_loss", None)


class SeedBatch:
    """N dataset agents of one config, one per seed, trained as one vmapped computation (see the module's docstring).

    Args:
        agents: N :class:`~torchrl_offhrl.agents.base.DatasetAgent` of the
            same class and hyper-parameters, each built under its own seed.
        randomness: ``torch.vmap``'s randomness for draws inside a loss
            (``"different"``: each seed its own draws).
        generators: one ``torch.Generator`` per seed for :meth:`sample`
            (default: seeded with ``0 .. N-1``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict, TensorDictBase
        >>> from torchrl_offhrl.data import make_gym_env
        >>> from torchrl_offhrl.agents.bc import BCAgent
        >>> env = make_gym_env("Pendulum-v1")
        >>> agents = []
        >>> for seed in (4, 5, 6):
        ...     _ = torch.manual_seed(seed)
        ...     agents.append(BCAgent(env, hidden_sizes=(16,), batch_size=4))
        >>> batch = SeedBatch(agents)
        >>> m = batch.update(TensorDict(observation=torch.zeros(3, 4, 3), action=torch.full((3, 4, 1), 0.5), batch_size=[3, 4]))
        >>> [sorted(x) for x in m][0], len(m)
        (['train/loss_bc', 'updates'], 3)
    """

    #: the agents it batches (and how its errors name them)
    agent_base: type = DatasetAgent
    agent_kinds: str = "dataset agents (BC, TD3+BC, IQL, CQL)"

    def __init__(self, agents: Sequence[DatasetAgent], randomness: str = "different", generators: Sequence[torch.Generator] | None = None):
        agents = list(agents)
        if len(agents) < 1:
            raise ValueError("SeedBatch needs at least one agent")
        kinds = {type(a) for a in agents}
        if len(kinds) != 1 or not isinstance(agents[0], self.agent_base):
            raise TypeError(f"{type(self).__name__} batches {self.agent_kinds} of one class, got {sorted(k.__name__ for k in kinds)}")
        if type(agents[0].loss).__name__ in _NOT_VMAPPABLE:
            raise NotImplementedError(f"SeedBatch: {type(agents[0]).__name__}'s loss ({type(agents[0].loss).__name__}) "
                                      f"{_NOT_VMAPPABLE[type(agents[0].loss).__name__]}; train its seeds as separate runs")
        if any(getattr(a, "compile", False) for a in agents):
            raise ValueError(f"{type(self).__name__}: build the agents with compile=False (the vmapped update is not compiled "
                             "yet; cudagraphs=True captures it as CUDA graphs on a GPU)")
        if len({bool(getattr(a, "cudagraphs", False)) for a in agents}) > 1:
            raise ValueError(f"{type(self).__name__}: the agents must agree on cudagraphs (one worker steps them all)")
        self.agents, self.n = agents, len(agents)
        self.randomness = randomness
        self.generators = list(generators) if generators is not None else [torch.Generator().manual_seed(i) for i in range(self.n)]
        if len(self.generators) != self.n:
            raise ValueError(f"SeedBatch: one generator per agent ({self.n}), got {len(self.generators)}")
        # agent 0's captured updates (CUDA graphs, streams: not copyable) stay its own; the worker captures its own
        fns = agents[0].__dict__.get("_step_fns")
        self.worker = copy.deepcopy(agents[0], memo={} if fns is None else {id(fns): {}})
        self._keys = _leaves(self.worker.loss)
        self._check_same_shapes()
        self._rebind_optimizers()
        self._rebind_target_updater()
        self.worker.loss_fn = self._vmapped_loss_fn  # the agent's step code reaches its losses here
        self._policy = None
        self.stack()

    # -------------------------------------------------------------- stacking
    def _check_same_shapes(self) -> None:
        ref = TensorDict.from_module(self.agents[0].loss, as_module=False)
        for i, a in enumerate(self.agents[1:], 1):
            td = TensorDict.from_module(a.loss, as_module=False)
            for k in self._keys:
                if td.get(k).shape != ref.get(k).shape:
                    raise ValueError(f"SeedBatch: agent {i}'s {'.'.join(k)} has shape {tuple(td.get(k).shape)}, agent 0's "
                                     f"{tuple(ref.get(k).shape)}: the agents must share one config")

    def _rebind_optimizers(self) -> None:
        """Point the worker's optimisers at the worker's own loss tensors (a deep copy does not keep a loss's parameters and
        its optimiser's the same objects), matched to agent 0's by their key in the loss."""
        a0 = TensorDict.from_module(self.agents[0].loss, as_module=False)
        key_of = {}
        for k in a0.keys(True, True):
            key_of.setdefault(id(a0.get(k)), k)
        w = TensorDict.from_module(self.worker.loss, as_module=False)
        for w_opt, opt in zip(self.worker.optimizers(), self.agents[0].optimizers()):
            for w_group, group in zip(w_opt.param_groups, opt.param_groups):
                missing = [i for i, q in enumerate(group["params"]) if id(q) not in key_of]
                if missing:
                    raise ValueError(f"SeedBatch: {type(self.agents[0]).__name__}'s optimiser steps tensors outside its loss; it cannot be batched")
                w_group["params"] = [w.get(key_of[id(q)]) for q in group["params"]]
            w_opt.state.clear()

    def _rebind_target_updater(self) -> None:
        """Give the worker a target updater of its own loss: a new one of agent 0's updater's kind and rate, built on the
        worker's loss through TorchRL's public API (an updater caches the tensors it steps when first used, so the deep
        copy's would step agent 0's). ``init_`` copies each source into its target; the targets are put back after, so
        the worker keeps the targets it holds (agent 0's, then the seeds' stacked ones)."""
        u = getattr(self.worker, "target_updater", None)
        if u is None:
            return
        if not isinstance(u, SoftUpdate):
            raise ValueError(f"SeedBatch: {type(self.agents[0]).__name__}'s target updater is a {type(u).__name__}; only "
                             "TorchRL's SoftUpdate is rebuilt for a seeds' batch")
        fresh = SoftUpdate(self.worker.loss, eps=u.eps)
        if u.initialized:
            params = TensorDict.from_module(self.worker.loss, as_module=False)
            targets = params.select(*(k for k in params.keys(True, True) if (k if isinstance(k, str) else k[0]).startswith("target_")))
            kept = targets.clone()
            with torch.no_grad():
                fresh.init_()
                targets.update_(kept)
        self.worker.target_updater = fresh

    def stack(self) -> None:
        """Stack the agents' tensors, optimiser states and step counts into the worker (at the start, and after loading checkpoints).

        With ``cudagraphs`` on a GPU, the worker's captured updates are dropped: stacking gives its tensors new storage, which
        a graph captured before would not see; the next update captures them again.
        """
        self.worker.__dict__.pop("_step_fns", None)
        w = TensorDict.from_module(self.worker.loss, as_module=False)
        per = [TensorDict.from_module(a.loss, as_module=False) for a in self.agents]
        # constants every seed holds alike (an action box, the data's observation statistics: buffers, no target network)
        # stay one unstacked tensor, outside the vmapped tree: the same values, and checks such as TorchRL's
        # ``(high > low).all()`` in a distribution stay plain Python control flow inside the vmap
        self._shared = set()
        with torch.no_grad():
            for k in self._keys:
                ts = [p.get(k).detach() for p in per]
                name = k if isinstance(k, str) else ".".join(k)
                if "target_" not in name and _is_constant(k, per[0].get(k), ts[1:]):
                    self._shared.add(k)
                    w.get(k).data = ts[0].clone()
                else:
                    w.get(k).data = torch.stack(ts)
        # agent 0's batch sizes: the worker's hold stacked tensors
        self._params = _with_seed_dim(w.exclude(*self._shared) if self._shared else w, self.n, self.agents[0].loss)
        # ... and are swapped into the loss with the seeds' slices (_with_shared)
        self._shared_params = _with_seed_dim(w.select(*self._shared), None, self.agents[0].loss) if self._shared else None
        for w_opt, opts in zip(self.worker.optimizers(), zip(*(a.optimizers() for a in self.agents))):
            own = [_flat_params(o) for o in opts]
            w_opt.state.clear()
            for j, wp in enumerate(_flat_params(w_opt)):
                states = [o.state.get(params[j]) for o, params in zip(opts, own)]
                if any(s is None for s in states):
                    continue
                w_opt.state[wp] = {name: (torch.stack([s[name] for s in states]) if _per_element(name, v, own[0][j]) else
                                          v.clone() if torch.is_tensor(v) else v)
                                   for name, v in states[0].items()}
        if hasattr(self.agents[0], "steps"):
            self.worker.steps = self.agents[0].steps
            if any(a.steps != self.worker.steps for a in self.agents):
                raise ValueError(f"SeedBatch: the agents have taken different numbers of updates {[a.steps for a in self.agents]}")

    def sync(self) -> None:
        """Write each seed's slice (weights, target networks, optimiser states, step count) into its own agent."""
        w = TensorDict.from_module(self.worker.loss, as_module=False)
        with torch.no_grad():
            for i, a in enumerate(self.agents):
                mine = TensorDict.from_module(a.loss, as_module=False)
                for k in self._keys:
                    if k not in self._shared:
                        mine.get(k).data.copy_(w.get(k).data[i])
                for w_opt, opt in zip(self.worker.optimizers(), a.optimizers()):
                    own = _flat_params(opt)
                    for j, wp in enumerate(_flat_params(w_opt)):
                        if wp not in w_opt.state:
                            continue
                        opt.state[own[j]] = {name: (v[i].clone() if _per_element(name, v, wp) else v.clone() if torch.is_tensor(v) else v)
                                             for name, v in w_opt.state[wp].items()}
                if hasattr(a, "steps"):
                    a.steps = self.worker.steps

    @property
    def policy(self) -> SeedBatchedPolicy:
        """The seeds' policy for a collector on an env of ``N * E`` envs (built on first use)."""
        if self._policy is None:
            self._policy = SeedBatchedPolicy(self.worker.policy, self._module_params(self.worker.policy), randomness=self.randomness)
        return self._policy

    def _module_params(self, module) -> TensorDictBase:
        """The worker's stacked loss tensors in ``module``'s layout (batch size ``[N]``): each of agent 0's policy tensors is
        matched to the loss tensor that shares its memory (a functional TorchRL loss keeps its own tensor objects, e.g.
        buffers, over the policy's storage), and the worker's stacked tensor at that key stands in for it."""
        a0_loss = TensorDict.from_module(self.agents[0].loss, as_module=False)
        where = {}
        for k in a0_loss.keys(True, True):
            t = a0_loss.get(k)
            where.setdefault((t.data_ptr(), tuple(t.shape)), k)
        a0_policy = TensorDict.from_module(self.agents[0].policy, as_module=False)
        worker_loss = TensorDict.from_module(self.worker.loss, as_module=False)
        policies = [TensorDict.from_module(a.policy, as_module=False) for a in self.agents[1:]]
        out, foreign = TensorDict(), []
        for k in a0_policy.keys(True, True):
            t = a0_policy.get(k)
            lk = where.get((t.data_ptr(), tuple(t.shape)))
            if lk is None and _is_constant(k, t, [p.get(k) for p in policies]):
                # a buffer the loss holds a copy of, not the same memory (after ``Agent.to``, which moves the policy and
                # the loss apart): a constant every seed's policy holds alike stays the module's own, as shared ones do
                continue
            if lk is None:
                foreign.append(k if isinstance(k, str) else ".".join(k))
            elif lk not in self._shared:  # a constant of every seed stays the module's own
                out.set(k, worker_loss.get(lk))
        if foreign:
            raise ValueError(f"SeedBatch: the policy holds tensors outside its agent's loss ({foreign[:3]}): they would not be "
                             "stacked per seed")
        return _with_seed_dim(out, self.n, module)

    # -------------------------------------------------------------- updates
    def _with_shared(self, params: TensorDictBase) -> TensorDictBase:
        """One seed's tensors inside the vmap, with the constants every seed holds alike (one tensor, not vmapped) added:
        a TorchRL loss's networks keep buffers of their own beside the loss's copies, which ``loss.to(device)`` does not
        move, so a constant left out of a ``to_module`` swap would be read from the CPU on a GPU."""
        return params if self._shared_params is None else params.update(self._shared_params)

    def _vmapped_loss_fn(self, method: str | None = None):
        """The loss (or its ``method``) of every seed on ``[N, ...]`` data, in one vmap; extra arguments are passed as they are."""
        loss = self.worker.loss
        extra = ((), {})

        def one_seed(params, batch):
            with self._with_shared(params).to_module(loss), _vmap_safe_reduction(loss):
                # a loss without a target copy of a network reads its detached weights as the target (TorchRL's
                # LossModule.__getattr__ takes ``.data``, which vmap forbids): the same values, detached here instead
                aliases = [f"target_{name}" for name, m in loss._modules.items() if name.endswith("_params") and not name.startswith("target_")
                           and f"target_{name}" not in loss._modules and isinstance(m, TensorDictBase)]
                for a in aliases:
                    loss.__dict__[a] = loss._modules[a[len("target_"):]].detach()
                try:
                    return (loss if method is None else getattr(loss, method))(batch, *extra[0], **extra[1])
                finally:
                    for a in aliases:
                        loss.__dict__.pop(a, None)

        def call(batch, *args, **kwargs):
            nonlocal extra
            extra = (args, kwargs)
            with _batched_normal_draws(self.randomness == "different"):
                return torch.vmap(one_seed, (0, 0), randomness=self.randomness)(self._params, batch)

        return call

    def sample(self, replay_buffer) -> TensorDict:
        """``[N, batch_size]``: one minibatch per seed from ``replay_buffer``, each drawn from its seed's own generator."""
        return self._per_seed_draws([replay_buffer.sample] * self.n)

    def _per_seed_draws(self, draws) -> TensorDict:
        """``draws[i]()`` for every seed ``i`` with seed ``i``'s generator as the RNG state (the outer state untouched), stacked."""
        out = []
        for draw, g in zip(draws, self.generators):
            with torch.random.fork_rng(devices=[]):
                torch.set_rng_state(g.get_state())
                out.append(draw())
                g.set_state(torch.get_rng_state())
        return torch.stack(out)

    def _seeds_first(self, batch: TensorDictBase) -> TensorDictBase:
        """A batch of the seeds' envs as ``[N, E, ...]``: given so, or as the collector's ``[N * E, ...]`` (seed ``i``'s envs
        ``i * E .. (i + 1) * E - 1``)."""
        n = self.n
        if batch.batch_size[:1] == torch.Size([n]):
            return batch
        if not batch.batch_dims or batch.batch_size[0] % n:
            raise ValueError(f"{type(self).__name__}.update: a batch of the {n} seeds' envs ([N * E, T] or [N, E, T]), got {tuple(batch.batch_size)}")
        return batch.reshape(n, batch.batch_size[0] // n, *batch.batch_size[1:])

    def update(self, batch: TensorDict) -> list[dict]:
        """One update of every seed on ``batch`` (``[N, batch_size]``); each seed's metrics (``train/...`` and ``updates``)."""
        if batch.batch_size[:1] != torch.Size([self.n]):
            raise ValueError(f"SeedBatch.update: the batch's leading dimension must be the {self.n} seeds, got batch size {tuple(batch.batch_size)}")
        metrics = self.worker.update(batch)
        out = []
        for i in range(self.n):
            out.append({k: (v[i] if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in metrics.items()})
        return out


def clip_grad_norm_per_seed_(params: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """``torch.nn.utils.clip_grad_norm_`` for each seed of stacked parameters (leading dimension: the seeds).

    Each seed's gradients are scaled by ``min(1, max_norm / (norm + 1e-6))``
    with ``norm`` the 2-norm over all of *its* gradients, as its own run's
    ``clip_grad_norm_`` would; returns the norms (``[N]``, before clipping).

    Examples:
        >>> import torch
        >>> w = torch.zeros(2, 3, requires_grad=True)
        >>> w.grad = torch.tensor([[3.0, 4.0, 0.0], [0.3, 0.4, 0.0]])
        >>> clip_grad_norm_per_seed_([w], 1.0).tolist()
        [5.0, 0.5]
        >>> [round(x, 4) for x in w.grad.flatten().tolist()]
        [0.6, 0.8, 0.0, 0.3, 0.4, 0.0]
    """
    grads = [p.grad for p in params if p.grad is not None]
    if not grads:
        return torch.zeros(0)
    n = grads[0].shape[0]
    norms = torch.stack([g.reshape(n, -1).pow(2).sum(1) for g in grads]).sum(0).sqrt()
    coef = (float(max_norm) / (norms + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(coef.reshape(n, *([1] * (g.dim() - 1))))
    return norms


class SeedBatchedPolicy(TensorDictModuleBase):
    """The policy of N seeds acting in one batched env: env ``i * E .. (i + 1) * E - 1`` is seed ``i``'s.

    A TensorDict module for TorchRL's collectors: the input's leading batch
    dimension (``N * E`` envs) is split into ``[N, E]``, and the seeds'
    policy (one module whose weights are stacked along a leading seed
    dimension, e.g. an :class:`OnPolicySeedBatch`'s worker policy) runs once
    under ``torch.vmap``, each seed with its own weights and, with
    ``randomness="different"``, its own draws (actions, options). The
    exploration type is the caller's (``set_exploration_type``), as for
    any policy.

    Args:
        module: the policy module whose weights ``params`` holds.
        params: ``TensorDict.from_module(module)`` with batch size ``[N]``.
        randomness: ``torch.vmap``'s (``"different"``: each seed its own draws).
    """

    def __init__(self, module, params: TensorDictBase, randomness: str = "different"):
        super().__init__()
        self.module = module
        self.in_keys, self.out_keys = list(module.in_keys), list(module.out_keys)
        self.__dict__["params"] = params  # the worker's tensors, not registered again here
        self.n = params.batch_size[0]
        self.randomness = randomness

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.batch_size
        if not shape or shape[0] % self.n:
            raise ValueError(f"SeedBatchedPolicy: the envs' batch {tuple(shape)} must be the {self.n} seeds' envs, E each (N * E leading)")
        seeds = tensordict.reshape(self.n, shape[0] // self.n, *shape[1:])
        module = self.module

        def one_seed(params, td):
            with params.to_module(module):
                return module(td)

        with _batched_normal_draws(self.randomness == "different"):
            out = torch.vmap(one_seed, (0, 0), randomness=self.randomness)(self.params, seeds)
        return tensordict.update(out.reshape(shape))


class OnPolicySeedBatch(SeedBatch):
    """N on-policy agents of one config (PPO, MOC), one per seed, updated as one vmapped computation and acting as one policy.

    The collector runs :attr:`policy` (a :class:`SeedBatchedPolicy`) on
    an env of ``N * E`` envs, seed ``i`` owning envs ``i * E .. (i + 1) * E - 1``; :meth:`update`
    takes that ``[N * E, T]`` batch (or ``[N, E, T]``) and runs each seed's own
    update rule on its own ``[E, T]`` part: the advantage from its own critic
    (TorchRL's value estimators: the critic per seed under ``vmap``, the
    recursion on all seeds at once; other agents' :meth:`prepare` runs under
    ``vmap`` whole), then ``epochs`` passes of minibatches, each seed's
    shuffled by its own generator, one optimiser step for all seeds (Adam is
    elementwise), gradients clipped per seed
    (:func:`clip_grad_norm_per_seed_`), and the agent's once-per-batch steps
    (:meth:`~torchrl_offhrl.agents.base.OnPolicyAgent.finish_update`, MOC's
    termination and pi_O) on each seed's whole batch. Given the same batch and
    shuffles, each seed's weights follow its own agent's update up to
    floating-point rounding (``tests/test_seed_batch.py``); draws inside a
    loss (MOC's ``z``) are each seed's own under ``randomness="different"``.
    """

    agent_base = OnPolicyAgent
    agent_kinds = "on-policy agents (PPO, MOC)"

    def __init__(self, agents: Sequence[OnPolicyAgent], randomness: str = "different", generators: Sequence[torch.Generator] | None = None):
        if agents:
            why = self.refusal(agents[0])
            if why:
                raise NotImplementedError(f"OnPolicySeedBatch: {why}; train its seeds as separate runs")
        super().__init__(agents, randomness=randomness, generators=generators)
        w = self.worker
        w.batch_loss = self._vmapped_loss_fn()
        if w.epochs < 1 or w.minibatch_size < 1:
            raise ValueError("OnPolicySeedBatch: the agents need epochs >= 1 and minibatch_size >= 1")
        self._estimator = None
        if type(w).prepare is OnPolicyAgent.prepare:  # TorchRL's value estimator (PPO's GAE): an unstacked copy runs the recursion
            est = copy.deepcopy(self.agents[0].loss.value_estimator)
            est.value_network = None
            self._estimator = est

    @staticmethod
    def refusal(agent) -> str | None:
        """Why ``agent``'s seeds cannot batch here (None: they can): what this batch does not reproduce of its update."""
        from .moc import MOCAgent

        if not isinstance(agent, OnPolicyAgent):
            return None  # not this batch's kind at all: the class check says so
        # (a loss torch.vmap cannot run, and compiled agents, are refused by SeedBatch's own checks)
        loss = getattr(agent, "loss", None)
        if getattr(agent, "averaged_policy", None) is not None:
            return "MOC's policy_ema (an averaged copy of the policy) is not batched yet"
        if getattr(loss, "functional", False) and type(agent).prepare is OnPolicyAgent.prepare:
            return "a functional TorchRL loss (algo.functional=true) swaps its critic's weights in only inside its own call"
        if type(agent).update not in (OnPolicyAgent.update, MOCAgent.update):
            return f"{type(agent).__name__} overrides update(), which the batch would skip"
        if type(agent).prepare not in (OnPolicyAgent.prepare, MOCAgent.prepare):
            return f"{type(agent).__name__} overrides prepare(), which the batch would skip"
        return None

    def _prepare(self, batch: TensorDictBase) -> None:
        """Each seed's advantage (and whatever else its agent's :meth:`prepare` writes) into the ``[N, E, T]`` batch."""
        w = self.worker
        loss = w.loss
        est = loss.value_estimator
        if self._estimator is None:
            prepare = self._vmapped_loss_fn("prepare_batch")
            if hasattr(est, "gae_inputs"):  # an estimator split in two (OptionGAE): networks per seed, one recursion for all
                def inputs(params, td):
                    with self._with_shared(params).to_module(loss):
                        return est.gae_inputs(td)

                est.write(batch, *est.advantage_from_inputs(torch.vmap(inputs, (0, 0))(self._params, batch), time_dim=batch.ndim - 1))
                new = prepare(batch.copy(), False)
            else:
                new = prepare(batch.copy())
            batch.update(new)  # every entry the preparation wrote, nested ones included
            return
        critic, key = est.value_network, est.tensor_keys.value

        def values(params, td):
            with self._with_shared(params).to_module(loss):
                return (critic(td.select(*critic.in_keys).copy()).get(key),
                        critic(td.get("next").select(*critic.in_keys).copy()).get(key))

        value, next_value = torch.vmap(values, (0, 0))(self._params, batch)
        batch.set(key, value)
        batch.set(("next", key), next_value)
        self._estimator(batch)

    def update(self, batch: TensorDictBase) -> list[dict]:
        """One on-policy update of every seed on its part of ``batch``; each seed's metrics (``train/...`` means and ``updates``)."""
        n, w = self.n, self.worker
        batch = self._seeds_first(batch)
        with torch.no_grad():
            self._prepare(batch)
        flat = batch.reshape(n, -1)
        size = flat.batch_size[1]
        rows = torch.arange(n, device=flat.device).unsqueeze(1)
        params = [p for g in w.optimizer.param_groups for p in g["params"]]
        sums: dict[str, torch.Tensor] = {}
        count = 0
        for _ in range(w.epochs):
            perms = torch.stack([torch.randperm(size, generator=g) for g in self.generators]).to(flat.device)
            for idx in perms.split(w.minibatch_size, dim=1):
                out = w.minibatch_loss(flat[rows, idx])
                w.observe_minibatch(out)
                w.optimizer.zero_grad()
                backward(w.minibatch_objective(out))
                if w.max_grad_norm:
                    clip_grad_norm_per_seed_(params, w.max_grad_norm)
                w.optimizer.step()
                for k, v in out.items():  # one element per seed, as a single run's MetricMeans keeps one element
                    if isinstance(v, torch.Tensor) and v.numel() == n and v.shape[:1] == torch.Size([n]):
                        v = v.detach().reshape(n).double()
                        sums[k] = sums[k] + v if k in sums else v
                count += 1
        w.finish_update(flat)
        means = {k: (v / max(count, 1)).tolist() for k, v in sums.items()}
        return [{**{f"train/{k}": vals[i] for k, vals in means.items()}, "updates": count} for i in range(n)]



class OffPolicySeedBatch(SeedBatch):
    """N off-policy agents of one config on the model env (SAC, MOPO), one per seed, acting as one policy and updated as one.

    The collector runs :attr:`policy` (a :class:`SeedBatchedPolicy`) on an
    env of ``N * E`` envs, seed ``i`` owning envs ``i * E .. (i + 1) * E - 1``.
    :meth:`update` takes that batch (``[N * E, T]`` or ``[N, E, T]``), puts
    each seed's part into that seed's own replay buffer (each agent keeps its
    own, which its run's checkpoint saves), and takes the agents' gradient
    steps for all seeds at once: each seed's minibatch drawn from its own
    buffers with its own generator (MOPO's share of the dataset's transitions
    included, :meth:`~torchrl_offhrl.agents.sac.SACAgent.minibatch`), the
    SAC losses of all seeds in one ``torch.vmap``, one optimiser step (Adam is
    elementwise) and one Polyak step of the stacked target critics. Given the
    same minibatches and (``randomness="same"``) the same draws inside the loss
    (the actions SAC samples for its actor, temperature and TD target), each
    seed's weights follow its own agent's update up to floating-point rounding
    (``tests/test_seed_batch.py``).
    """

    agent_base = SACAgent
    agent_kinds = "off-policy agents on the model env (SAC, MOPO)"

    def __init__(self, agents, randomness: str = "different", generators: Sequence[torch.Generator] | None = None):
        agents = list(agents)
        # the worker is a copy of agent 0 without its buffers: each seed keeps and fills its own (and MOPO its dataset's)
        held = {}
        if agents:
            held = {k: agents[0].__dict__[k] for k in ("replay_buffer", "dataset_buffer") if k in agents[0].__dict__}
            agents[0].__dict__.update(dict.fromkeys(held))
        try:
            super().__init__(agents, randomness=randomness, generators=generators)
        finally:
            if agents:
                agents[0].__dict__.update(held)

    def stack(self) -> None:
        super().stack()
        frames = {a.frames for a in self.agents}
        if len(frames) != 1:
            raise ValueError(f"OffPolicySeedBatch: the agents have collected different numbers of frames {sorted(frames)}")
        self.worker.frames = frames.pop()

    def sync(self) -> None:
        super().sync()
        for a in self.agents:
            a.frames = self.worker.frames

    def minibatches(self) -> TensorDict:
        """``[N, batch_size]``: each seed's minibatch from its own agent's buffers (its ``minibatch()``), drawn from its own generator."""
        return self._per_seed_draws([a.minibatch for a in self.agents])

    def update(self, batch: TensorDictBase) -> list[dict]:
        """Store each seed's part of ``batch`` in its buffer, then the gradient steps of every seed; each seed's metrics."""
        n = self.n
        batch = self._seeds_first(batch)
        for a, part in zip(self.agents, batch.unbind(0)):
            a.store(part)
        metrics = self.worker.gradient_steps(batch[0].numel(), self.minibatches, MetricMeans(width=n))
        count = metrics.pop("updates")
        return [{**{k: (v[i] if isinstance(v, list) else v) for k, v in metrics.items()}, "updates": count} for i in range(n)]
