"""Up-front validation of a resolved recipe config: every bad value, with its key, before any data or model work.

A wrong value should cost a second, not the nine minutes of generating a
dataset before the first use of the value fails (or, for a negative frame
budget, silently trains nothing). :func:`validate_config` checks the keys
every command reads against their allowed ranges and raises one
``ValueError`` that lists each bad value as ``key: expected ..., got ...``.
Keys of an algorithm's config are checked by their name (``lr`` and
``*_lr`` positive, ``gamma`` in (0, 1], ...); the agent's constructor still
rejects keys it does not know.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import torch

from ..envs import TASKS
from .selection import CRITERIA

__all__ = ["validate_config"]

_MISSING = object()


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def _int(lo: int | None = None, *, optional: bool = False) -> tuple[str, Callable[[Any], bool]]:
    what = "an integer" + (f" >= {lo}" if lo is not None else "") + (" or null" if optional else "")
    return what, lambda v: (optional and v is None) or (_is_int(v) and (lo is None or v >= lo))


def _num(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
         optional: bool = False) -> tuple[str, Callable[[Any], bool]]:
    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {lo}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {hi}")
    what = "a number" + (" " + " and ".join(parts) if parts else "") + (" or null" if optional else "")

    def ok(v):
        if optional and v is None:
            return True
        if not _is_num(v):
            return False
        if lo is not None and (v <= lo if lo_open else v < lo):
            return False
        return hi is None or (v < hi if hi_open else v <= hi)

    return what, ok


def _choice(*options) -> tuple[str, Callable[[Any], bool]]:
    return f"one of {', '.join(map(repr, options))}", lambda v: v in options


def _sizes() -> tuple[str, Callable[[Any], bool]]:
    return "a non-empty list of positive integers", lambda v: isinstance(v, (list, tuple)) and len(v) > 0 and all(_is_int(x) and x > 0 for x in v)


_FIT = {"lr": _num(0, lo_open=True), "batch_size": _int(1), "max_epochs": _int(1), "max_steps": _int(1, optional=True), "patience": _int(0)}

#: key path -> (what is allowed, check); absent keys are left to their defaults
RULES: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "seed": _int(0),
    "dataset_seed": _int(0),
    "num_transitions": _int(1, optional=True),
    "dataset_num_envs": _int(1),
    "val_ratio": _num(0, 1, lo_open=True, hi_open=True),
    "ensemble.num_models": _int(1),
    "ensemble.hidden_sizes": _sizes(),
    "ensemble.reward_hidden_sizes": ("null or " + _sizes()[0], lambda v: v is None or _sizes()[1](v)),
    "cvae.hidden_sizes": _sizes(),
    "cvae.kl_weight": _num(0),
    **{f"{m}.fit.{k}": rule for m in ("ensemble", "cvae") for k, rule in _FIT.items()},
    "model_env.horizon": _int(1),
    "model_env.member_mode": _choice("episode", "step", "mean"),
    "model_env.reset_states": _choice("initial", "any"),
    "model_env.latent_bound": _num(0, lo_open=True),
    "model_env.reward_penalty": _num(0),
    "model_env.reward_scale": ("a positive number or 'auto'", lambda v: v == "auto" or (_is_num(v) and v > 0)),
    "collector.num_envs": _int(1),
    "torch_threads": _int(1, optional=True),
    "train.total_frames": _int(1),
    "train.total_updates": _int(1),
    "train.online": ("true or false", lambda v: isinstance(v, bool)),
    "train.snapshot_frames": ("a list of positive integers (frames)", lambda v: isinstance(v, (list, tuple)) and all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in v)),
    "eval.every_frames": _int(1),
    "eval.every_updates": _int(1),
    "eval.episodes": _int(1),
    "eval.model_episodes": _int(1, optional=True),
    "eval.sampled": ("true or false", lambda v: isinstance(v, bool)),
    "selection.criterion": _choice(*CRITERIA),
    "selection.include_start": ("true or false", lambda v: isinstance(v, bool)),
    "eval.max_steps": _int(1),
    "transfer.task": (f"null or a task of torchrl_offhrl.envs.TASKS ({', '.join(map(repr, TASKS))})", lambda v: v is None or v in TASKS),
    "transfer.online_frames": _int(1),
    "transfer.num_envs": _int(1),
    "transfer.decoder": _choice("discard", "keep"),
    "transfer.from_scratch": ("true or false", lambda v: isinstance(v, bool)),
    "transfer.eval_every_frames": _int(1),
    "logger.backend": _choice("csv", "tensorboard", "wandb", "mlflow", None),
}

#: rules for an algorithm's keys, by name (whatever the algorithm)
ALGO_RULES: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "gamma": _num(0, 1, lo_open=True),
    "lmbda": _num(0, 1),
    "num_options": _int(1),
    "frames_per_batch": _int(1),
    "minibatch_size": _int(1),
    "batch_size": _int(1),
    "epochs": _int(1),
    "clip_epsilon": _num(0, lo_open=True),
    "max_grad_norm": _num(0, lo_open=True, optional=True),
    "hidden_sizes": _sizes(),
    "adam_eps": _num(0, lo_open=True),
    "lr": _num(0, lo_open=True),
    "actor_lr": _num(0, lo_open=True),
    "critic_lr": _num(0, lo_open=True),
    "tau": _num(0, 1, lo_open=True),
    "expectile": _num(0, 1, lo_open=True, hi_open=True),
    "policy_ema": ("null or a number in (0, 1]", lambda v: v is None or (_is_num(v) and 0 < v <= 1)),
    "reward_scale": ("a positive number, 'auto' or 'return_range'", lambda v: v in ("auto", "return_range") or (_is_num(v) and v > 0)),
    "anneal_lr": ("true or false", lambda v: isinstance(v, bool)),
}


def _get(cfg: Mapping, path: str):
    node: Any = cfg
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return _MISSING
        node = node[part]
    return node


def _device_problem(value) -> str | None:
    try:
        dev = torch.device(str(value))
    except (RuntimeError, ValueError):
        return "a torch device such as 'cpu' or 'cuda'"
    if dev.type == "cuda" and not torch.cuda.is_available():
        return (f"a device this machine has (this torch build {torch.__version__} sees no CUDA GPU: install a CUDA build "
                "of torch, or use device=cpu)")
    return None


def validate_config(cfg: Mapping) -> None:
    """Raise ``ValueError`` listing every out-of-range value of a resolved recipe config (nothing when all are fine).

    Example:
        >>> validate_config({"train": {"total_frames": 1000}, "eval": {"episodes": 10}})
        >>> validate_config({"train": {"total_frames": -5}, "algo": {"lr": -1}})
        Traceback (most recent call last):
        ...
        ValueError: invalid config values (nothing was run):
          train.total_frames: expected an integer >= 1, got -5
          algo.lr: expected a number > 0, got -1
    """
    problems = []
    for key, (what, ok) in RULES.items():
        value = _get(cfg, key)
        if value is not _MISSING and not ok(value):
            problems.append(f"{key}: expected {what}, got {value!r}")
    if "device" in cfg:
        what = _device_problem(cfg["device"])
        if what:
            problems.append(f"device: expected {what}, got {cfg['device']!r}")
    for key, value in (cfg.get("algo") or {}).items():
        rule = ALGO_RULES.get(key)
        if rule is None and key.endswith("_lr"):  # a head's own step size (null: the agent's lr)
            rule = _num(0, lo_open=True, optional=True)
        if rule is None and key.endswith("_coef"):
            rule = _num(0)
        if rule is not None and not rule[1](value):
            problems.append(f"algo.{key}: expected {rule[0]}, got {value!r}")
    if problems:
        raise ValueError("invalid config values (nothing was run):\n  " + "\n  ".join(problems))
