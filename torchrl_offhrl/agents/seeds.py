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

Batched: BC, TD3+BC, IQL and CQL. TorchRL's own ``CQLLoss`` is refused: it
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

from .base import DatasetAgent

__all__ = ["SeedBatch"]


#: TorchRL losses that cannot run under ``torch.vmap``, and why
_NOT_VMAPPABLE = {"CQLLoss": "reads its parameters' .data inside the loss (log_alpha, the actor's and critics' weights for its "
                             "sampled actions), which torch.vmap forbids (torchrl_offhrl.agents.cql.BatchableCQLLoss is the same "
                             "loss without it: the CQL agent's)"}


def _flat_params(opt: torch.optim.Optimizer) -> list:
    """The tensors an optimiser steps, in its groups' order (how a worker's and an agent's optimisers are matched)."""
    return [p for g in opt.param_groups for p in g["params"]]


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


def _with_seed_dim(td: TensorDict, n: int, loss) -> TensorDict:
    """The same tensors (not copies) under a tree whose batch sizes gain the leading seed dimension ``n``.

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

    out = TensorDict(batch_size=[n])
    for k, v in td.items():
        own = getattr(loss, k, None)
        extra = own.batch_size if isinstance(own, TensorDictBase) else torch.Size([])
        out.set(k, tree(v, torch.Size([n, *extra])) if isinstance(v, TensorDictBase) else v)
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

    def __init__(self, agents: Sequence[DatasetAgent], randomness: str = "different", generators: Sequence[torch.Generator] | None = None):
        agents = list(agents)
        if len(agents) < 1:
            raise ValueError("SeedBatch needs at least one agent")
        kinds = {type(a) for a in agents}
        if len(kinds) != 1 or not isinstance(agents[0], DatasetAgent):
            raise TypeError(f"SeedBatch batches dataset agents of one class (BC, TD3+BC, IQL, CQL), got {sorted(k.__name__ for k in kinds)}")
        if type(agents[0].loss).__name__ in _NOT_VMAPPABLE:
            raise NotImplementedError(f"SeedBatch: {type(agents[0]).__name__}'s loss ({type(agents[0].loss).__name__}) "
                                      f"{_NOT_VMAPPABLE[type(agents[0].loss).__name__]}; train its seeds as separate runs")
        if any(getattr(a, "compile", False) or getattr(a, "cudagraphs", False) for a in agents):
            raise ValueError("SeedBatch: build the agents with compile=False and cudagraphs=False (the vmapped update is not compiled yet)")
        self.agents, self.n = agents, len(agents)
        self.randomness = randomness
        self.generators = list(generators) if generators is not None else [torch.Generator().manual_seed(i) for i in range(self.n)]
        if len(self.generators) != self.n:
            raise ValueError(f"SeedBatch: one generator per agent ({self.n}), got {len(self.generators)}")
        self.worker = copy.deepcopy(agents[0])
        self._keys = _leaves(self.worker.loss)
        self._check_same_shapes()
        self._rebind_optimizers()
        self._rebind_target_updater()
        self.worker.__dict__.pop("_step_fns", None)
        self.worker.loss_fn = self._vmapped_loss_fn  # the agent's step code reaches its losses here
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
        """Point the worker's target updater (TorchRL's ``SoftUpdate``, which caches its source and target tensors) at the
        worker's own loss, with the same pairs agent 0's updater steps."""
        u = self.worker.target_updater
        if u is None:
            return
        u.loss_module = self.worker.loss
        for attr, names in (("_sources_val", u._source_names), ("_targets_val", u._target_names)):
            old = u.__dict__.pop(attr, None)
            fresh = TensorDict({name: getattr(self.worker.loss, name) for name in names}, [])
            if old is not None:
                fresh = fresh.select(*old.keys(True, True)).lock_()
            u.__dict__[attr] = fresh

    def stack(self) -> None:
        """Stack the agents' tensors, optimiser states and step counts into the worker (at the start, and after loading checkpoints)."""
        w = TensorDict.from_module(self.worker.loss, as_module=False)
        per = [TensorDict.from_module(a.loss, as_module=False) for a in self.agents]
        with torch.no_grad():
            for k in self._keys:
                w.get(k).data = torch.stack([p.get(k).detach() for p in per])
        self._params = _with_seed_dim(w, self.n, self.agents[0].loss)  # agent 0's batch sizes: the worker's hold stacked tensors
        for w_opt, opts in zip(self.worker.optimizers(), zip(*(a.optimizers() for a in self.agents))):
            own = [_flat_params(o) for o in opts]
            w_opt.state.clear()
            for j, wp in enumerate(_flat_params(w_opt)):
                states = [o.state.get(params[j]) for o, params in zip(opts, own)]
                if any(s is None for s in states):
                    continue
                w_opt.state[wp] = {name: (torch.stack([s[name] for s in states]) if torch.is_tensor(v) and v.dim() > 0 else v.clone() if torch.is_tensor(v) else v)
                                   for name, v in states[0].items()}
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
                    mine.get(k).data.copy_(w.get(k).data[i])
                for w_opt, opt in zip(self.worker.optimizers(), a.optimizers()):
                    own = _flat_params(opt)
                    for j, wp in enumerate(_flat_params(w_opt)):
                        if wp not in w_opt.state:
                            continue
                        opt.state[own[j]] = {name: (v[i].clone() if torch.is_tensor(v) and v.dim() > 0 else v.clone() if torch.is_tensor(v) else v)
                                             for name, v in w_opt.state[wp].items()}
                a.steps = self.worker.steps

    # -------------------------------------------------------------- updates
    def _vmapped_loss_fn(self, method: str | None = None):
        loss = self.worker.loss

        def one_seed(params, batch):
            with params.to_module(loss):
                # a loss without a target copy of a network reads its detached weights as the target (TorchRL's
                # LossModule.__getattr__ takes ``.data``, which vmap forbids): the same values, detached here instead
                aliases = [f"target_{name}" for name, m in loss._modules.items() if name.endswith("_params") and not name.startswith("target_")
                           and f"target_{name}" not in loss._modules and isinstance(m, TensorDictBase)]
                for a in aliases:
                    loss.__dict__[a] = loss._modules[a[len("target_"):]].detach()
                try:
                    return (loss if method is None else getattr(loss, method))(batch)
                finally:
                    for a in aliases:
                        loss.__dict__.pop(a, None)

        def call(batch):
            with _batched_normal_draws(self.randomness == "different"):
                return torch.vmap(one_seed, (0, 0), randomness=self.randomness)(self._params, batch)

        return call

    def sample(self, replay_buffer) -> TensorDict:
        """``[N, batch_size]``: one minibatch per seed from ``replay_buffer``, each drawn from its seed's own generator."""
        out = []
        for g in self.generators:
            with torch.random.fork_rng(devices=[]):
                torch.set_rng_state(g.get_state())
                out.append(replay_buffer.sample())
                g.set_state(torch.get_rng_state())
        return torch.stack(out)

    def update(self, batch: TensorDict) -> list[dict]:
        """One update of every seed on ``batch`` (``[N, batch_size]``); each seed's metrics (``train/...`` and ``updates``)."""
        if batch.batch_size[:1] != torch.Size([self.n]):
            raise ValueError(f"SeedBatch.update: the batch's leading dimension must be the {self.n} seeds, got batch size {tuple(batch.batch_size)}")
        metrics = self.worker.update(batch)
        out = []
        for i in range(self.n):
            out.append({k: (v[i] if torch.is_tensor(v) and v.dim() > 0 else v) for k, v in metrics.items()})
        return out
