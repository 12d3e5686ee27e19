"""What every agent gives the training loop, and the update rules shared by families of algorithms.

The loop (:func:`torchrl_offhrl.recipes.train`) knows nothing of any
algorithm: it builds an agent with :func:`~torchrl_offhrl.agents.make_agent`,
appends :meth:`Agent.env_transforms` to the envs the policy acts in, collects
batches with :attr:`Agent.policy`, calls :meth:`Agent.update` on each and
checkpoints :meth:`Agent.state_dict` (and :attr:`Agent.replay_buffer`, if
any). At each real-env evaluation it merges :meth:`Agent.evaluation_metrics`
into the record; at the last one it calls :meth:`Agent.save_evaluation`.

The networks the agents share are in :mod:`~torchrl_offhrl.agents.networks`
(re-exported here); the optimiser and compilation helpers (fused Adam,
CUDA-graph capture, ``torch.compile`` settings) at the end of this module.
"""
from __future__ import annotations

from collections.abc import Hashable, Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

from .networks import action_box, deterministic_actor, gaussian_actor, q_network, tanh_mean_gaussian_actor

__all__ = [
    "action_box", "adam", "Agent", "backward", "COMPILE_MODES", "compile_setting", "DatasetAgent", "deterministic_actor", "gaussian_actor",
    "make_capturable", "MetricMeans", "OnPolicyAgent", "q_network", "scalar_metrics", "sum_losses", "tanh_mean_gaussian_actor",
]


def sum_losses(out: Mapping) -> torch.Tensor:
    """The sum of a loss module's ``loss_*`` entries."""
    return sum(v for k, v in out.items() if k.startswith("loss_"))


def scalar_metrics(out) -> TensorDictBase:
    """The one-element entries of a loss's output TensorDict, detached and 0-dim (what :meth:`DatasetAgent.step` returns).

    Under :class:`~torchrl_offhrl.agents.seeds.SeedBatch` the output has a
    leading seed dimension (``batch_size [N]``): one element per seed, kept as ``[N]``.
    """
    shape = out.batch_size
    return out.select(*(k for k, v in out.items() if isinstance(v, torch.Tensor) and v.numel() == shape.numel())).detach().apply(
        lambda v: v.reshape(shape))


def backward(loss: torch.Tensor) -> None:
    """``loss.backward()``; a per-seed loss (``[N]``, :class:`~torchrl_offhrl.agents.seeds.SeedBatch`) is summed first, so that each
    seed's gradient is its own loss's (the seeds share no tensor). A scalar loss is unchanged."""
    (loss if loss.dim() == 0 else loss.sum()).backward()


class MetricMeans:
    """Means, over the steps of an update, of every one-element tensor of the loss outputs (named ``prefix + key``).

    Summed on their device and read once by :meth:`means` (no device sync
    per gradient step); :attr:`count` is the number of outputs added. With
    ``width`` N (a seeds' batch, :mod:`torchrl_offhrl.agents.seeds`) it keeps
    the outputs of ``N`` elements instead, one per seed, and :meth:`means`
    gives each key's N means as a list.

    Examples:
        >>> import torch
        >>> m = MetricMeans()
        >>> m.add({"loss_a": torch.tensor(1.0), "usage": torch.zeros(3)})
        >>> m.add({"loss_a": torch.tensor(2.0)})
        >>> m.means(), m.count
        ({'train/loss_a': 1.5}, 2)
        >>> m = MetricMeans(width=2)
        >>> m.add({"loss_a": torch.tensor([1.0, 3.0]), "alpha": torch.tensor(1.0)})
        >>> m.means()
        {'train/loss_a': [1.0, 3.0]}
    """

    def __init__(self, prefix: str = "train/", width: int = 1):
        self.prefix = prefix
        self.width = int(width)
        self.count = 0
        self._sums: dict[str, torch.Tensor] = {}

    def add(self, out: Mapping) -> None:
        for k, v in out.items():
            if isinstance(v, torch.Tensor) and v.numel() == self.width and (self.width == 1 or v.shape[:1] == (self.width,)):
                v = v.detach().reshape(self.width if self.width > 1 else ()).double()
                self._sums[k] = self._sums[k] + v if k in self._sums else v
        self.count += 1

    def means(self) -> dict:
        if self.width == 1:
            return {self.prefix + k: float(v) / max(self.count, 1) for k, v in self._sums.items()}
        return {self.prefix + k: (v / max(self.count, 1)).tolist() for k, v in self._sums.items()}


class Agent:
    """Base class of the agents: a policy, a loss, its optimisers and how they learn from a batch.

    A subclass sets, in its ``__init__``:

    * ``policy``: the exploration policy the collector runs (it writes
      :attr:`action_key`); under ``ExplorationType.DETERMINISTIC`` it is the
      evaluation policy;
    * ``loss``: a TorchRL :class:`~torchrl.objectives.LossModule` (its
      ``state_dict`` holds every network);
    * ``optimizer``: one optimiser over every trained parameter (several
      built per network are merged with TorchRL's ``group_optimizers``:
      Adam steps each parameter on its own, so this changes nothing);

    and implements :meth:`update`. Optional: :meth:`new_task` (the transfer
    setting's switch), :meth:`env_transforms`
    (transforms the policy needs on every env it acts in, e.g. an
    ``InitTracker``), :meth:`evaluation_metrics` / :meth:`save_evaluation`
    (extra numbers and files of a real-env evaluation), ``replay_buffer``
    (off-policy agents: the loop checkpoints it), ``init_random_frames``
    (frames the collector fills with uniformly random actions first),
    ``frames_per_batch`` (the collector's batch), :meth:`pretrain` (a start
    from the dataset before training, e.g. MOReL's behaviour-cloned policy),
    :meth:`use_dataset` (the dataset beside the model env, e.g. MOPO's mixed
    minibatches).

    ``update(batch)`` returns a dict of float metrics (logged under their
    names) that includes ``"updates"``: the number of gradient steps taken.
    The training loop calls :meth:`set_progress` before each update with the
    fraction of the frame budget already collected (schedules such as
    ``anneal_lr`` use it; it derives from the frame count, so a resumed run
    continues the same schedule).
    """

    name: str = ""
    #: where the loop takes training batches from: ``"model_env"`` (collected on the composed model env: the
    #: budget is ``train.total_frames``) or ``"dataset"`` (minibatches of the dataset itself: the budget is
    #: ``train.total_updates``; no models are fitted, the agent acts in real actions)
    data_source: str = "model_env"
    policy: nn.Module
    loss: nn.Module
    optimizer: torch.optim.Optimizer
    action_key: str = "action"
    frames_per_batch: int = 1
    init_random_frames: int = 0
    replay_buffer: Any = None
    #: files :meth:`save_evaluation` writes into the run directory (the loop re-evaluates when one is missing)
    evaluation_files: tuple[str, ...] = ()
    #: config keys that only shape how the agent collects and trains on its env (a rollout schedule tied to the model
    #: env's size): left out when a finished run's agent is rebuilt to act in the real env
    #: (:func:`~torchrl_offhrl.recipes.evaluation.load_run_agent`); its policy and state load the same
    training_only_keys: tuple[str, ...] = ()
    #: run the loss through ``torch.compile`` (:meth:`loss_fn`): a speed switch, the same computation. ``False``
    #: or a ``torch.compile`` mode (``True`` is ``"default"``; ``"reduce-overhead"`` adds CUDA graphs on a GPU)
    compile: bool | str = False

    def loss_fn(self, method: str | None = None):
        """:attr:`loss` (or its bound ``method``, e.g. ``"qvalue_loss"``), through ``torch.compile`` when :attr:`compile` is set.

        Each callable is compiled once, on its first call (tens of seconds on
        CPU). The compiled callable wraps the loss without replacing it, so
        checkpoints keep the same keys either way and ``compile`` can change
        between a run and its resumption.
        """
        fn = self.loss if method is None else getattr(self.loss, method)
        if not self.compile:
            return fn
        compiled = self.__dict__.setdefault("_compiled", {})
        if method not in compiled:
            compiled[method] = torch.compile(fn, mode=self.compile)
        return compiled[method]

    def batch_loss(self, td: TensorDictBase):
        """:attr:`loss` on a whole batch, never compiled (steps taken once per batch, whose shapes differ from the minibatches').
        Under a seeds' batch the worker answers it with the seeds' vmapped loss."""
        return self.loss(td)

    def optimizers(self) -> list[torch.optim.Optimizer]:
        """Every optimiser the agent owns (its attributes that are optimisers, :attr:`optimizer` first)."""
        found = [self.optimizer] + [v for k, v in vars(self).items() if isinstance(v, torch.optim.Optimizer) and k != "optimizer"]
        return list(dict.fromkeys(found))

    def set_progress(self, fraction: float) -> None:
        """Called before each update with the fraction of the frame budget done (``[0, 1]``); default: nothing."""

    def use_dataset(self, data, reward_scale: float = 1.0) -> None:
        """Called when a model-env run is built (fresh or resumed), with the offline dataset and the reward scale of the env's
        rewards; default: nothing (MOPO mixes the dataset's transitions into its minibatches)."""

    def pretrain(self, data, progress: bool = False) -> dict:
        """Called once, with the offline dataset, when a run starts from scratch (not when it resumes); default: nothing.

        ``progress``: show a progress bar over the pretraining steps. Returns metrics to record in the run's summary
        (``{}``: none).
        """
        return {}

    def new_task(self) -> None:
        """Called once when the task changes (the transfer setting's switch to online fine-tuning); default: nothing.

        Off-policy agents start a fresh replay buffer here: the transitions
        collected before were rewarded for the old task (and came from the model).
        """

    def env_transforms(self) -> list:
        """Transforms to append to every env the policy acts in (collection and evaluation)."""
        return []

    def attach(self, env):
        """Append a fresh set of :meth:`env_transforms` to ``env`` (a ``TransformedEnv``) and return it."""
        for t in self.env_transforms():
            env.append_transform(t)
        return env

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        raise NotImplementedError

    @property
    def eval_policy(self) -> nn.Module:
        """The policy evaluations, offline policy selection and ``offhrl evaluate`` act with: :attr:`policy`, unless the agent
        keeps another for that (e.g. MOC's ``policy_ema``: a Polyak average of the policy's weights)."""
        averaged = self.__dict__.get("averaged_policy")
        return self.policy if averaged is None else averaged

    def evaluation_metrics(self, rollout: TensorDictBase, alive: torch.Tensor) -> dict[str, Any]:
        """Extra JSON-able numbers of a real-env evaluation (``rollout`` is ``[E, T]``, ``alive`` marks each env's first episode)."""
        return {}

    def save_evaluation(self, rollout: TensorDictBase, alive: torch.Tensor, run_dir: Path, title: str) -> None:
        """Write :attr:`evaluation_files` for the final evaluation (plots, tensors)."""

    def to(self, device) -> Agent:
        """Move the loss and every other module the agent holds (the acting policy above all) to ``device``.

        Moving the loss alone is not enough: TorchRL's losses keep the
        networks' parameters and buffers in their own ``TensorDictParams``;
        ``loss.to`` moves the parameters in place (the policy shares them)
        but gives the loss new buffer tensors, so the policy's buffers (the
        dataset's observation statistics) would stay behind on the CPU. The
        tensors among the distributions' keyword arguments (the tanh-Gaussian's
        action box) are no buffers either: they move too (else every
        distribution built on the GPU copies them from the host, which a CUDA
        graph cannot capture).
        """
        for module in vars(self).values():
            if isinstance(module, torch.nn.Module):
                module.to(device)
                for m in module.modules():
                    kwargs = getattr(m, "distribution_kwargs", None)
                    if isinstance(kwargs, dict):
                        kwargs.update({k: v.to(device) for k, v in kwargs.items() if isinstance(v, torch.Tensor)})
        return self

    def state_dict(self) -> dict:
        return {"loss": self.loss.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: Mapping) -> None:
        self.loss.load_state_dict(state["loss"])
        self.optimizer.load_state_dict(state["optimizer"])


class OnPolicyAgent(Agent):
    """On-policy update shared by PPO-style agents: GAE over the batch, then epochs of shuffled minibatches.

    Every ``loss_*`` term is summed and stepped with :attr:`optimizer` in
    each minibatch; gradients are clipped to ``max_grad_norm`` (``None``: no
    clipping). The batch's last dimension is time (``[envs, steps]``).
    ``compile=True`` runs the minibatch loss through ``torch.compile`` (a
    speed switch: the same computation). ``anneal_lr=True`` decays every
    step size linearly to 0 over the frame budget (:meth:`set_progress`).
    """

    def __init__(self, *, frames_per_batch: int, epochs: int, minibatch_size: int, max_grad_norm: float | None, compile: bool | str = False,
                 anneal_lr: bool = False):
        self.frames_per_batch = int(frames_per_batch)
        self.epochs = int(epochs)
        self.minibatch_size = int(minibatch_size)
        self.max_grad_norm = max_grad_norm
        self.compile = compile_setting(compile)
        self.anneal_lr = bool(anneal_lr)

    def set_progress(self, fraction: float) -> None:
        """With ``anneal_lr``, every optimiser's step size is its initial one times ``1 - fraction`` (linear to 0).

        As TorchRL's PPO scripts (``anneal_lr``) and the ``linear`` schedule of
        the baselines PPO that the official MOC code builds on.
        """
        if not self.anneal_lr:
            return
        mult = min(max(1.0 - float(fraction), 0.0), 1.0)
        for opt in self.optimizers():
            for group in opt.param_groups:
                group.setdefault("initial_lr", group["lr"])
                group["lr"] = group["initial_lr"] * mult

    def minibatch_loss(self, minibatch: TensorDictBase):
        """``loss(minibatch)``; with ``compile=True`` through ``torch.compile`` (:meth:`Agent.loss_fn`).

        Measured on CPU (``benchmarks/recipe_throughput.py``): PPO's update
        about 2.5x faster once compiled, so it pays off for runs longer than a
        few minutes.
        """
        return self.loss_fn()(minibatch)

    def prepare(self, batch: TensorDictBase) -> None:
        """Annotate the ``[envs, time]`` batch before it is shuffled (default: the loss's value estimator writes the advantage)."""
        self.loss.value_estimator(batch)

    #: where the minibatches' shuffles are drawn from (None: torch's global RNG); a seeds' batch gives each seed its own
    generator: torch.Generator | None = None

    def minibatch_objective(self, out: TensorDictBase) -> torch.Tensor:
        """What each minibatch step of :attr:`optimizer` minimises, from the loss's output (default: every ``loss_*`` term)."""
        return sum_losses(out)

    def observe_minibatch(self, out: TensorDictBase) -> None:
        """Called with each minibatch's loss outputs before its gradient step (under a seeds' batch, every entry has a
        leading seed dimension): state a loss adapts between steps (PPO's KL coefficient). Default: nothing."""

    def finish_update(self, flat: TensorDictBase) -> None:
        """Called after the minibatch epochs with the whole prepared batch, flattened (``[envs * time]``; under a seeds' batch
        ``[N, envs * time]``): steps taken once per batch (MOC's termination and pi_O). Default: nothing."""

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        metrics = self.minibatch_epochs(batch, self.optimizer, self.minibatch_objective)
        self.finish_update(batch.reshape(-1))
        return metrics

    def minibatch_epochs(self, batch: TensorDictBase, optim: torch.optim.Optimizer, objective) -> dict[str, float]:
        """:meth:`prepare` the batch, then ``epochs`` passes of shuffled minibatches, each one step of ``optim`` on ``objective(loss(minibatch))``.

        Returns the loss outputs' scalar metrics averaged over minibatches and ``"updates"``.
        """
        params = [p for grp in optim.param_groups for p in grp["params"]]
        with torch.no_grad():
            self.prepare(batch)
        flat = batch.reshape(-1)
        metrics = MetricMeans()
        for _ in range(self.epochs):
            perm = (torch.randperm(flat.numel(), device=flat.device) if self.generator is None
                    else torch.randperm(flat.numel(), generator=self.generator).to(flat.device))
            for idx in perm.split(self.minibatch_size):
                out = self.minibatch_loss(flat[idx])
                self.observe_minibatch(out)
                optim.zero_grad()
                objective(out).backward()
                if self.max_grad_norm:
                    torch.nn.utils.clip_grad_norm_(params, float(self.max_grad_norm))
                optim.step()
                metrics.add(out)
        return {**metrics.means(), "updates": metrics.count}


class DatasetAgent(Agent):
    """Model-free offline agents: every update is gradient steps on minibatches drawn from the dataset itself.

    The loop gives :meth:`update` a batch of :attr:`batch_size` transitions
    sampled uniformly from the dataset (TorchRL's offline layout: ``observation``,
    ``action``, ``("next", "observation" | "reward" | "done" | "terminated")``);
    no model is fitted and the agent acts in the real action space. The
    rewards the agent learns from are multiplied by :attr:`reward_scale`
    (resolved by the loop from the algorithm's config: a number, ``"auto"``
    or ``"return_range"``, see
    :func:`torchrl_offhrl.recipes.config.resolve_reward_scale`). Target
    networks' updaters go in :attr:`target_updater` so that checkpoints keep
    them.
    """

    data_source = "dataset"
    batch_size: int = 256
    reward_scale: float = 1.0
    target_updater: Any = None
    #: updates taken (checkpointed): schedules such as CQL's behaviour-cloning phase or TD3+BC's delayed actor read it
    steps: int = 0
    #: capture each form of the whole update (losses, backward, optimiser and target steps) as a CUDA graph and replay it
    #: on every later update (TensorDict's ``CudaGraphModule``, as TorchRL's sota scripts): on a GPU the update's
    #: hundreds of small kernels then launch at once instead of one by one from Python. A speed switch, the same
    #: computation; on a CPU it changes nothing
    cudagraphs: bool = False

    def step_variant(self) -> Hashable:
        """Which form the next update takes (default: always the same); one CUDA graph is captured per form.

        Python branches of an update (CQL's behaviour-cloning phase, TD3+BC's
        delayed actor step) cannot live inside one captured graph, so each
        branch is its own :meth:`step` form, chosen here from :attr:`steps`.
        """
        return None

    def step(self, batch: TensorDictBase, variant: Hashable) -> TensorDictBase:
        """One whole update on ``batch`` (rewards already scaled) in form ``variant``: losses, backward, optimiser and target steps.

        Returns the update's scalar metrics, detached, as a TensorDict (keys
        without the ``train/`` prefix). It must not branch on tensor values
        nor read them on the host, so that it can be captured as a CUDA graph.
        """
        raise NotImplementedError

    def update(self, batch: TensorDictBase) -> dict:
        """:meth:`step` on ``batch``, through its CUDA graph when :attr:`cudagraphs` is on and the agent is on a GPU.

        The metrics come back as 0-dim tensors on the agent's device (reading
        them would wait for the GPU at every update): the loop sums them and
        reads them when it logs. ``"updates"`` is 1.
        """
        out = self._step_fn(self.step_variant())(self.scaled(batch))
        self.steps += 1
        return {**{f"train/{k}": v for k, v in out.items()}, "updates": 1}

    def _step_fn(self, variant: Hashable):
        fns = self.__dict__.setdefault("_step_fns", {})
        if variant not in fns:
            def fn(batch, variant=variant):
                return self.step(batch, variant)
            if self.cudagraphs and next(self.loss.parameters()).is_cuda:
                from tensordict.nn import CudaGraphModule

                for opt in self.optimizers():
                    make_capturable(opt)
                # the warm-up runs (eager, on a side stream) create the optimisers' states and, when compiled, build the code
                fn = CudaGraphModule(fn, in_keys=[], out_keys=[], warmup=20 if self.compile else 3)
            fns[variant] = fn
        return fns[variant]

    def set_sampling(self, batch_size: int, reward_scale: float) -> None:
        """Set :attr:`batch_size` and :attr:`reward_scale` (a positive number: names such as ``"return_range"`` are resolved by the loop)."""
        if isinstance(reward_scale, str) or isinstance(reward_scale, bool) or not float(reward_scale) > 0:
            raise ValueError(f"{type(self).__name__}: reward_scale must be a positive number, got {reward_scale!r}; the names 'auto' and "
                             "'return_range' of the configs are resolved from the data by torchrl_offhrl.recipes.config.resolve_reward_scale")
        if int(batch_size) < 1:
            raise ValueError(f"{type(self).__name__}: batch_size must be >= 1, got {batch_size}")
        self.batch_size, self.reward_scale = int(batch_size), float(reward_scale)

    def scaled(self, batch: TensorDictBase) -> TensorDictBase:
        """``batch`` with its rewards multiplied by :attr:`reward_scale` (a new tensordict: ``batch`` is untouched)."""
        if self.reward_scale == 1.0:
            return batch
        out = batch.exclude(("next", "reward"))
        out.set(("next", "reward"), batch.get(("next", "reward")) * self.reward_scale)
        return out

    def state_dict(self) -> dict:
        out = super().state_dict()
        if self.target_updater is not None:
            out["target_updater"] = self.target_updater.state_dict()
        out["steps"] = self.steps
        return out

    def load_state_dict(self, state: Mapping) -> None:
        super().load_state_dict(state)
        if self.target_updater is not None and "target_updater" in state:
            self.target_updater.load_state_dict(state["target_updater"])
        self.steps = int(state.get("steps", 0))
        for opt in self.optimizers():  # a run captured on a GPU may resume anywhere: its graphs are made again, capturable then
            for group in opt.param_groups:
                group["capturable"] = False
        self.__dict__.pop("_step_fns", None)


# ---- optimiser and compilation helpers the agents share: fused Adam, CUDA-graph capture, torch.compile settings ----------

def adam(params, lr: float, eps: float = 1e-8, fused: bool = True) -> torch.optim.Adam:
    """Adam; ``fused`` (default) runs one fused kernel over every parameter instead of a Python loop of small ops.

    The same update rule: on the agents' small networks torch's default
    per-tensor Adam costs ~1 ms per step on CPU, the fused one ~0.1 ms
    (``benchmarks/recipe_throughput.py``). ``fused=False`` is torch's default
    implementation (results then match older runs bit for bit).
    """
    params = list(params)
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True) if fused else torch.optim.Adam(params, lr=lr, eps=eps, foreach=False)


COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def compile_setting(value) -> bool | str:
    """An algorithm config's ``compile`` value as :attr:`Agent.compile`: ``False``, or a ``torch.compile`` mode (``True``: ``"default"``)."""
    if value is None or value is False:
        return False
    if value is True:
        return "default"
    if isinstance(value, str) and value in COMPILE_MODES:
        return value
    raise ValueError(f"compile must be true, false or a torch.compile mode ({', '.join(COMPILE_MODES)}), got {value!r}: "
                     "e.g. algo.compile=true, or algo.compile=reduce-overhead for CUDA graphs on a GPU")


def make_capturable(opt: torch.optim.Optimizer) -> None:
    """Let ``opt`` (an Adam) be captured in a CUDA graph: ``capturable`` groups, step counts on the parameters' device."""
    for group in opt.param_groups:
        group["capturable"] = True
        for p in group["params"]:
            state = opt.state.get(p, {})
            if torch.is_tensor(state.get("step")) and state["step"].device != p.device:
                state["step"] = state["step"].to(p.device, torch.float32)
