"""What every agent gives the training loop, and the update rules shared by families of algorithms.

The loop (:func:`torchrl_offhrl.recipes.train`) knows nothing of any
algorithm: it builds an agent with :func:`~torchrl_offhrl.agents.make_agent`,
appends :meth:`Agent.env_transforms` to the envs the policy acts in, collects
batches with :attr:`Agent.policy`, calls :meth:`Agent.update` on each and
checkpoints :meth:`Agent.state_dict` (and :attr:`Agent.replay_buffer`, if
any). At each real-env evaluation it merges :meth:`Agent.evaluation_metrics`
into the record; at the last one it calls :meth:`Agent.save_evaluation`.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import nn

__all__ = ["Agent", "MetricMeans", "OnPolicyAgent", "action_box", "adam", "sum_losses"]


def sum_losses(out: Mapping) -> torch.Tensor:
    """The sum of a loss module's ``loss_*`` entries."""
    return sum(v for k, v in out.items() if k.startswith("loss_"))


class MetricMeans:
    """Means, over the steps of an update, of every one-element tensor of the loss outputs (named ``prefix + key``).

    Summed on their device and read once by :meth:`means` (no device sync
    per gradient step); :attr:`count` is the number of outputs added.

    Examples:
        >>> import torch
        >>> m = MetricMeans()
        >>> m.add({"loss_a": torch.tensor(1.0), "usage": torch.zeros(3)})
        >>> m.add({"loss_a": torch.tensor(2.0)})
        >>> m.means(), m.count
        ({'train/loss_a': 1.5}, 2)
    """

    def __init__(self, prefix: str = "train/"):
        self.prefix = prefix
        self.count = 0
        self._sums: dict[str, torch.Tensor] = {}

    def add(self, out: Mapping) -> None:
        for k, v in out.items():
            if isinstance(v, torch.Tensor) and v.numel() == 1:
                v = v.detach().reshape(()).double()
                self._sums[k] = self._sums[k] + v if k in self._sums else v
        self.count += 1

    def means(self) -> dict[str, float]:
        return {self.prefix + k: float(v) / max(self.count, 1) for k, v in self._sums.items()}


def adam(params, lr: float, eps: float = 1e-8, fused: bool = True) -> torch.optim.Adam:
    """Adam; ``fused`` (default) runs one fused kernel over every parameter instead of a Python loop of small ops.

    The same update rule: on the agents' small networks torch's default
    per-tensor Adam costs ~1 ms per step on CPU, the fused one ~0.1 ms
    (``benchmarks/recipe_throughput.py``). ``fused=False`` is torch's default
    implementation (results then match older runs bit for bit).
    """
    params = list(params)
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True) if fused else torch.optim.Adam(params, lr=lr, eps=eps, foreach=False)


def action_box(env, key: str) -> tuple[int, torch.Tensor, torch.Tensor]:
    """``(dim, low, high)`` of the action ``key`` of ``env`` (one env's box when the env is batched)."""
    spec = env.full_action_spec[key] if key in env.full_action_spec.keys(True, True) else env.action_spec
    dim = spec.shape[-1]
    low = spec.space.low.reshape(-1, dim)[0].float()
    high = spec.space.high.reshape(-1, dim)[0].float()
    return dim, low, high


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

    and implements :meth:`update`. Optional: :meth:`env_transforms`
    (transforms the policy needs on every env it acts in, e.g. an
    ``InitTracker``), :meth:`evaluation_metrics` / :meth:`save_evaluation`
    (extra numbers and files of a real-env evaluation), ``replay_buffer``
    (off-policy agents: the loop checkpoints it), ``init_random_frames``
    (frames the collector fills with uniformly random actions first),
    ``frames_per_batch`` (the collector's batch).

    ``update(batch)`` returns a dict of float metrics (logged under their
    names) that includes ``"updates"``: the number of gradient steps taken.
    The training loop calls :meth:`set_progress` before each update with the
    fraction of the frame budget already collected (schedules such as
    ``anneal_lr`` use it; it derives from the frame count, so a resumed run
    continues the same schedule).
    """

    name: str = ""
    policy: nn.Module
    loss: nn.Module
    optimizer: torch.optim.Optimizer
    action_key: str = "action"
    frames_per_batch: int = 1
    init_random_frames: int = 0
    replay_buffer: Any = None
    #: files :meth:`save_evaluation` writes into the run directory (the loop re-evaluates when one is missing)
    evaluation_files: tuple[str, ...] = ()

    def set_progress(self, fraction: float) -> None:
        """Called before each update with the fraction of the frame budget done (``[0, 1]``); default: nothing."""

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

    def evaluation_metrics(self, rollout: TensorDictBase, alive: torch.Tensor) -> dict[str, Any]:
        """Extra JSON-able numbers of a real-env evaluation (``rollout`` is ``[E, T]``, ``alive`` marks each env's first episode)."""
        return {}

    def save_evaluation(self, rollout: TensorDictBase, alive: torch.Tensor, run_dir: Path, title: str) -> None:
        """Write :attr:`evaluation_files` for the final evaluation (plots, tensors)."""

    def to(self, device) -> Agent:
        self.loss.to(device)
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

    def __init__(self, *, frames_per_batch: int, epochs: int, minibatch_size: int, max_grad_norm: float | None, compile: bool = False,
                 anneal_lr: bool = False):
        self.frames_per_batch = int(frames_per_batch)
        self.epochs = int(epochs)
        self.minibatch_size = int(minibatch_size)
        self.max_grad_norm = max_grad_norm
        self.compile = bool(compile)
        self.anneal_lr = bool(anneal_lr)
        self._compiled_loss = None

    def optimizers(self) -> list[torch.optim.Optimizer]:
        """Every optimiser the agent owns (its attributes that are optimisers, :attr:`optimizer` first)."""
        found = [self.optimizer] + [v for k, v in vars(self).items() if isinstance(v, torch.optim.Optimizer) and k != "optimizer"]
        return list(dict.fromkeys(found))

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
        """``loss(minibatch)``; with ``compile=True`` through ``torch.compile`` (built on first use, ~40 s on CPU).

        The compiled callable wraps :attr:`loss` without replacing it, so
        checkpoints keep the same keys either way. Measured on CPU
        (``benchmarks/recipe_throughput.py``): PPO's update about 2.5x faster
        once compiled, so it pays off for runs longer than a few minutes.
        """
        if not self.compile:
            return self.loss(minibatch)
        if self._compiled_loss is None:
            self._compiled_loss = torch.compile(self.loss)
        return self._compiled_loss(minibatch)

    def prepare(self, batch: TensorDictBase) -> None:
        """Annotate the ``[envs, time]`` batch before it is shuffled (default: the loss's value estimator writes the advantage)."""
        self.loss.value_estimator(batch)

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        return self.minibatch_epochs(batch, self.optimizer, sum_losses)

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
            for idx in torch.randperm(flat.numel(), device=flat.device).split(self.minibatch_size):
                out = self.minibatch_loss(flat[idx])
                optim.zero_grad()
                objective(out).backward()
                if self.max_grad_norm:
                    torch.nn.utils.clip_grad_norm_(params, float(self.max_grad_norm))
                optim.step()
                metrics.add(out)
        return {**metrics.means(), "updates": metrics.count}
