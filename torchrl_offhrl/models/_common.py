"""Pieces shared by the learned models: fitting on a dataset, checkpoints."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..utils import load_torch_file, save_torch_file
from .trainer import SupervisedTrainer

__all__ = ["FitMixin", "atomic_torch_save"]


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
