"""Fitting the learned models: one supervised trainer for every model (ensembles, the CVAE, the percentile BC), and the
``fit`` / ``save`` / ``load`` every model built from a config dict shares (:class:`FitMixin`)."""
from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import time
import warnings
from pathlib import Path
from typing import Any, Protocol, Sequence

import torch
from tensordict import TensorDictBase
from torch import nn

from ..utils import CorruptFileError, checksum_path, load_torch_file, save_torch_file

__all__ = ["atomic_torch_save", "FitMixin", "make_adam", "SupervisedTrainer", "TrainableModel"]

#: seconds between two writes of a fit's checkpoint when :class:`SupervisedTrainer` is not given ``checkpoint_every_s``
CHECKPOINT_EVERY_S = 120.0


def make_adam(params, **kwargs) -> torch.optim.Adam:
    """Adam with the fused kernel where the device supports it (10x faster step on CPU)."""
    params = list(params)
    try:
        return torch.optim.Adam(params, fused=True, **kwargs)
    except (RuntimeError, TypeError):  # older torch or an unsupported device/dtype
        return torch.optim.Adam(params, **kwargs)


class TrainableModel(Protocol):
    """What :class:`SupervisedTrainer` needs from a model.

    * ``num_members``: ``K``; every trainable parameter has a leading
      dimension ``K`` when ``K > 1`` (batched-weight ensembles);
    * ``train_keys``: the dataset keys the loss reads;
    * ``loss(batch)``: for a batch of shape ``[K, B]`` (member ``k`` gets
      ``batch[k]``) or ``[B]`` (the same batch for every member), returns the
      per-member mean loss, shape ``[K]``.
    """

    num_members: int
    train_keys: Sequence

    def loss(self, batch: TensorDictBase) -> torch.Tensor: ...

    def parameters(self): ...


@dataclasses.dataclass
class SupervisedTrainer:
    """Adam, bootstrap minibatches per member, validation, early stopping.

    Each optimisation step draws an independent minibatch (with replacement:
    a bootstrap) for every member and sums the members' losses; since members
    share no parameter, each member's gradient is that of its own loss. After
    every epoch the validation loss of each member is measured; a member's
    best weights are kept, training stops once no member has improved for
    ``patience`` epochs, and every member gets its best weights back.

    Args:
        lr: Adam learning rate (paper: 1e-4).
        batch_size: minibatch per member (paper: 256).
        max_epochs: upper bound on epochs.
        steps_per_epoch: optimisation steps between validations; default one
            pass over the training set (``len(train) // batch_size``).
        max_steps: optional bound on the total number of steps.
        patience: epochs without improvement before stopping.
        min_delta: improvement smaller than this does not count.
        rel_tol: an improvement also has to be larger than this fraction of
            the member's best loss so far to count (0: any improvement).
            Together with ``patience`` this is the fit's convergence rule:
            a fit stops once no member's held-out loss has improved by more
            than ``rel_tol`` (relative) for ``patience`` epochs, instead of
            after a fixed step budget. Without it, noise-sized improvements
            of one member (a few 1e-4 relative, measured on the demo's
            ensemble) keep a fit going to ``max_epochs``.
        val_max_samples: validation subset size (fixed, drawn once).
        seed: seeds the minibatch sampling.
        progress: show a tqdm bar with the losses.
        desc: label of the progress bar.
        checkpoint: a file where the fit keeps its whole state while it runs
            (weights, Adam's moments, the best weights so far, the sampler's
            random state, the history), written atomically at most every
            ``checkpoint_every_s`` seconds at the end of an epoch and deleted
            when the fit ends. A fit started again with the same checkpoint
            (after a kill, a crash or the end of a session) goes on from the
            last epoch written and ends with the weights an uninterrupted fit
            would have had; a checkpoint left by another fit (other data
            size, settings or shapes) is set aside with a warning. None: no
            checkpoint (a fit of hours that is killed starts again).
        checkpoint_every_s: seconds between two checkpoint writes (0: every
            epoch; None: :data:`CHECKPOINT_EVERY_S`, two minutes).
    """

    lr: float = 1e-4
    batch_size: int = 256
    max_epochs: int = 200
    steps_per_epoch: int | None = None
    max_steps: int | None = None
    patience: int = 5
    min_delta: float = 0.0
    rel_tol: float = 0.0
    val_max_samples: int = 50_000
    weight_decay: float = 0.0
    seed: int = 0
    progress: bool = True
    desc: str = "fit"
    checkpoint: str | os.PathLike | None = None
    checkpoint_every_s: float | None = None

    def _fingerprint(self, train: TensorDictBase, n_val: int, k: int, params) -> dict:
        """What a checkpoint must match to be resumed: the data (its sizes, each key's sum and a digest of its bytes), the
        members, the step settings, the shapes. The stopping rules (patience, rel_tol, max_epochs) may change between the
        two runs (:func:`_same_fit` compares them)."""
        items = sorted(train.items(True, True), key=lambda kv: str(kv[0]))
        sums = [float(value.double().sum()) for _, value in items]
        digest = hashlib.sha256()
        for _, value in items:
            digest.update(value.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
        return {"n": train.shape[0], "n_val": n_val, "data_sums": sums, "data_digest": digest.hexdigest(), "k": k, "lr": self.lr, "batch_size": self.batch_size,
                "steps_per_epoch": self.steps_per_epoch, "max_steps": self.max_steps, "weight_decay": self.weight_decay,
                "seed": self.seed, "shapes": [list(p.shape) for p in params]}

    def _resume(self, fingerprint: dict) -> dict | None:
        """The state in :attr:`checkpoint` when it belongs to this fit, else None (a foreign or damaged one is renamed
        ``<name>.stale`` with a warning, never deleted: it may be another run's)."""
        path = Path(self.checkpoint)
        if not path.is_file():
            return None
        try:
            state = load_torch_file(path, "fit checkpoint", "it is set aside and the fit starts again")
            found = state.get("fingerprint") if isinstance(state, dict) else None
            reason = None if _same_fit(found, fingerprint) else f"it was written by another fit ({_difference(found, fingerprint)})"
        except CorruptFileError as err:
            state, reason = None, str(err)
        if reason is None:
            return state
        stale = path.with_name(path.name + ".stale")
        os.replace(path, stale)
        checksum_path(path).unlink(missing_ok=True)
        warnings.warn(f"{path}: not resumed, {reason}; moved to {stale.name}, the fit starts from scratch", stacklevel=3)
        return None

    def fit(self, model: TrainableModel, train: TensorDictBase, val: TensorDictBase | None = None) -> list[dict]:
        """Train ``model`` in place; returns the per-epoch history."""
        from tqdm.auto import tqdm

        device = next(model.parameters()).device
        keys = list(model.train_keys)
        train = train.select(*keys).to(device)
        n = train.shape[0]
        if n == 0:
            raise ValueError("SupervisedTrainer.fit: the training set is empty.")
        k = model.num_members
        gen = torch.Generator(device=device).manual_seed(self.seed)
        if val is not None and val.shape[0] > 0:
            val = val.select(*keys).to(device)
            if val.shape[0] > self.val_max_samples:
                sel = torch.randperm(val.shape[0], generator=torch.Generator().manual_seed(self.seed))
                val = val[sel[: self.val_max_samples].to(device)]
        else:
            val = None
        params = [p for p in model.parameters() if p.requires_grad]
        if k > 1:
            for p in params:
                if p.shape[0] != k:
                    raise ValueError(
                        f"every trainable parameter of a {k}-member model must have a leading "
                        f"dimension {k}; found shape {tuple(p.shape)}."
                    )
        opt = make_adam(params, lr=self.lr, weight_decay=self.weight_decay)
        steps_per_epoch = self.steps_per_epoch or max(1, n // self.batch_size)
        max_epochs = self.max_epochs
        if self.max_steps is not None:
            max_epochs = min(max_epochs, math.ceil(self.max_steps / steps_per_epoch))
        best = torch.full((k,), float("inf"), device=device)
        best_params = [p.detach().clone() for p in params]
        bad_epochs = 0
        history: list[dict] = []
        total_steps = 0
        start_epoch = 0
        # what a checkpoint must match (a digest of the whole training set: only for a fit that keeps one)
        fingerprint = self._fingerprint(train, 0 if val is None else val.shape[0], k, params) if self.checkpoint is not None else None
        state = self._resume(fingerprint) if self.checkpoint is not None else None
        if state is not None:
            with torch.no_grad():
                model.load_state_dict(state["model"])
                for b, saved in zip(best_params, state["best_params"]):
                    b.copy_(saved)
            opt.load_state_dict(state["optimizer"])
            best = state["best"].to(device)
            bad_epochs, total_steps, history = state["bad_epochs"], state["total_steps"], state["history"]
            gen.set_state(state["generator"])
            start_epoch = len(history)
            if self.progress:
                print(f"{self.desc}: resuming from {self.checkpoint} after epoch {start_epoch} ({total_steps} steps)")
        last_write = time.monotonic()
        bar = tqdm(range(start_epoch, max_epochs), desc=self.desc, disable=not self.progress, leave=False,
                   initial=start_epoch, total=max_epochs)
        done = start_epoch >= max_epochs or bad_epochs >= self.patience or (self.max_steps is not None and total_steps >= self.max_steps)
        for epoch in ([] if done else bar):
            model.train()
            running = torch.zeros(k, device=device)
            steps = steps_per_epoch
            if self.max_steps is not None:
                steps = min(steps, self.max_steps - total_steps)
            for _ in range(steps):
                idx = torch.randint(0, n, (k, self.batch_size), generator=gen, device=device)
                per_member = model.loss(train[idx])
                opt.zero_grad(set_to_none=True)
                per_member.sum().backward()
                opt.step()
                running += per_member.detach()
            total_steps += steps
            train_loss = running / max(steps, 1)
            record = {"epoch": epoch, "steps": total_steps, "train_loss": train_loss.cpu().tolist()}
            if val is not None:
                val_loss = self.evaluate(model, val)
                record["val_loss"] = val_loss.cpu().tolist()
                improved = val_loss < best - self.min_delta - self.rel_tol * best.abs().nan_to_num(posinf=0.0)
            else:
                val_loss = train_loss
                improved = train_loss < best - self.min_delta - self.rel_tol * best.abs().nan_to_num(posinf=0.0)
            if improved.any():
                best = torch.where(improved, val_loss, best)
                with torch.no_grad():
                    for p, b in zip(params, best_params):
                        if k > 1:
                            b[improved] = p[improved]
                        else:
                            b.copy_(p)
                bad_epochs = 0
            else:
                bad_epochs += 1
            history.append(record)
            bar.set_postfix(
                train=f"{train_loss.mean().item():.4f}",
                **({"val": f"{val_loss.mean().item():.4f}"} if val is not None else {}),
            )
            if bad_epochs >= self.patience:
                break
            if self.max_steps is not None and total_steps >= self.max_steps:
                break
            every = CHECKPOINT_EVERY_S if self.checkpoint_every_s is None else self.checkpoint_every_s
            if self.checkpoint is not None and time.monotonic() - last_write >= every:
                self._write(model, opt, best, best_params, bad_epochs, total_steps, history, gen, fingerprint)
                last_write = time.monotonic()
        bar.close()
        if self.checkpoint is not None:  # the fit is over: its state is in the model now
            Path(self.checkpoint).unlink(missing_ok=True)
            checksum_path(self.checkpoint).unlink(missing_ok=True)
        with torch.no_grad():
            for p, b in zip(params, best_params):
                p.copy_(b)
        model.eval()
        return history

    def _write(self, model, opt, best, best_params, bad_epochs, total_steps, history, gen, fingerprint) -> None:
        Path(self.checkpoint).parent.mkdir(parents=True, exist_ok=True)
        save_torch_file({"fingerprint": fingerprint, "model": model.state_dict(), "optimizer": opt.state_dict(),
                         "best": best.cpu(), "best_params": [b.cpu() for b in best_params], "bad_epochs": bad_epochs,
                         "total_steps": total_steps, "history": history, "generator": gen.get_state()}, self.checkpoint)

    @torch.no_grad()
    def evaluate(self, model: TrainableModel, data: TensorDictBase, chunk: int = 8192) -> torch.Tensor:
        """Mean held-out loss of every member on ``data`` (the same samples for all), shape ``[K]``: the model's ``val_loss``
        where it has one (e.g. the mean's error of a Gaussian ensemble), else its training ``loss``."""
        was_training = model.training
        model.eval()
        total = None
        n = data.shape[0]
        for start in range(0, n, chunk):
            part = data[start : start + chunk]
            loss = getattr(model, "val_loss", model.loss)(part) * part.shape[0]
            total = loss if total is None else total + loss
        model.train(was_training)
        return total / n


def _same_fit(found, expected: dict) -> bool:
    """Whether a checkpoint's fingerprint ``found`` is this fit's ``expected`` one.

    The data are compared by their bytes' digest (exact); the per-key sums only to a relative 1e-9, because a float64 sum
    over a million values depends on the order of its additions, which changes with the number of threads: a fit
    interrupted under ``OMP_NUM_THREADS=1`` and resumed under two threads read sums that differ in the last bit, and was
    thrown away. A checkpoint written before the digest existed is judged on its sums alone.
    """
    if not isinstance(found, dict) or set(found) - {"data_digest"} != set(expected) - {"data_digest"}:
        return False
    if any(found[key] != expected[key] for key in expected if key not in ("data_sums", "data_digest")):
        return False
    if "data_digest" in found and found["data_digest"] != expected["data_digest"]:
        return False
    a, b = found["data_sums"], expected["data_sums"]
    return len(a) == len(b) and all(math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-9) for x, y in zip(a, b))


def _difference(found, expected: dict) -> str:
    """The first settings in which a checkpoint's fingerprint ``found`` differs from ``expected``, for a warning."""
    if not isinstance(found, dict):
        return "no fingerprint"
    keys = [key for key in expected if found.get(key) != expected[key]]
    return ", ".join(f"{key} {found.get(key)!r} there, {expected[key]!r} here" for key in keys[:3]) or "another format"


# ---- fitting and saving a model built from a config (FitMixin), and its checkpoint files ---------------------------------

def atomic_torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save`` to a temporary file in the same folder, then rename; with its checksum (:func:`~torchrl_offhrl.utils.save_torch_file`)."""
    return save_torch_file(obj, path)


class FitMixin:
    """``fit``, ``save`` and ``load`` for models built from a config dict.

    Subclasses set ``self.config`` (plain Python values only) in ``__init__``
    so that ``type(model)(**config)`` rebuilds the same architecture.
    """

    config: dict
    training_history: list

    def fit(self, data, val_ratio: float = 0.1, split_seed: int = 0, **trainer_kwargs):
        """Fit on an :class:`~torchrl_offhrl.data.OfflineDataset` and return ``self``.

        The data is split by episode (``val_ratio`` held out, 90:10 by
        default); ``trainer_kwargs`` go to
        :class:`~torchrl_offhrl.models.SupervisedTrainer` (``lr``,
        ``batch_size``, ``max_epochs``, ``max_steps``, ``patience``,
        ``progress``, ...). Defaults come from the model's ``default_fit``.
        """
        kwargs = {**getattr(self, "default_fit", {}), "desc": f"fit {type(self).__name__}", **trainer_kwargs}
        if val_ratio and data.num_episodes >= 2:
            train, val = data.split(val_ratio, seed=split_seed)
            val_td = val.data
        else:
            train, val_td = data, None
        self.training_history = SupervisedTrainer(**kwargs).fit(self, train.data, val_td)
        return self

    def save(self, path: str | os.PathLike) -> Path:
        """Write ``{"config", "state_dict"}`` atomically; load with :meth:`load`."""
        assert isinstance(self, nn.Module)
        state = {k: v.detach().cpu() for k, v in self.state_dict().items()}
        return atomic_torch_save({"class": type(self).__name__, "config": self.config, "state_dict": state}, path)

    @classmethod
    def load(cls, path: str | os.PathLike, map_location="cpu"):
        """Rebuild a model saved with :meth:`save` (``torch.load(weights_only=True)``)."""
        path = Path(path).expanduser()
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no checkpoint there; write one with {cls.__name__}.save(path).")
        blob = load_torch_file(path, f"{cls.__name__} checkpoint", f"fit the model again and save it with {cls.__name__}.save(path)",
                               map_location=map_location)
        if not isinstance(blob, dict) or blob.get("class") != cls.__name__:
            found = blob.get("class") if isinstance(blob, dict) else type(blob).__name__
            raise ValueError(f"{path}: holds a {found!r} checkpoint, not a {cls.__name__} one.")
        model = cls(**blob["config"])
        model.load_state_dict(blob["state_dict"])
        model.eval()
        return model


def buffer(module: nn.Module, name: str, value, size: int) -> None:
    """Register a float buffer of length ``size`` (zeros/ones when ``value`` is None)."""
    if value is None:
        value = torch.ones(size) if name.endswith(("std", "high")) else torch.zeros(size)
        if name.endswith("low"):
            value = -torch.ones(size)
    module.register_buffer(name, torch.as_tensor(value, dtype=torch.float32).reshape(size).clone())
