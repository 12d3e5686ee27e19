"""The recipe config's schema: every section typed, with its defaults and allowed values, and up-front validation.

Every section of ``configs/offline_train.yaml`` is a dataclass here, each
field holding its type, its default and its allowed values (``_setting``):
the loop's (:class:`TrainConfig`, :class:`EvalConfig`,
:class:`SelectionConfig`, :class:`CollectorConfig`, :class:`TransferConfig`,
:class:`LoggerConfig`, gathered in :class:`RunConfig` by
:meth:`RunConfig.parse`) and the models' and the P-MDP's
(:class:`EnsembleConfig` and :class:`CVAEConfig` with their
:class:`FitConfig`, :class:`ModelEnvConfig`, :class:`AblationConfig`); the
top level's own keys are :data:`TOP_LEVEL`. The shipped YAML is checked
against these defaults key for key by the tests, so a default has one value
in two readable places (the YAML carries each key's reasons). The
algorithm's section is typed by its agent's signature (``agent_defaults``:
unknown keys are refused), its values checked by name (:data:`ALGO_RULES`).

A wrong value should cost a second, not the nine minutes of generating a
dataset before the first use of the value fails (or, for a negative frame
budget, silently trains nothing). :func:`validate_config` checks every key
against its field's allowed values (:data:`RULES` is read off the fields),
refuses keys a typed section does not have (a typo such as
``train.total_frame`` would otherwise be ignored), and raises one
``ValueError`` that lists each problem as ``key: expected ..., got ...``.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import Any

import torch

from ..envs import TASKS
from ..models import DISCREPANCIES
from .selection import CRITERIA

__all__ = ["AblationConfig", "CVAEConfig", "CollectorConfig", "EnsembleConfig", "EvalConfig", "FitConfig", "LoggerConfig", "ModelEnvConfig",
           "RENAMED_KEYS", "RunConfig", "SECTIONS", "parse_section", "renamed_key", "SelectionConfig", "TrainConfig", "TransferConfig", "UNITS", "section_defaults",
           "validate_config"]

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


def _bool() -> tuple[str, Callable[[Any], bool]]:
    return "true or false", lambda v: isinstance(v, bool)


def _setting(rule: tuple[str, Callable[[Any], bool]], default=MISSING, *, default_factory=MISSING):
    """A typed section's field: its default and its allowed values (``rule``: what is allowed, check)."""
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata={"rule": rule})
    return field(default=default, metadata={"rule": rule})


def _positive_ints() -> tuple[str, Callable[[Any], bool]]:
    return ("a list of positive integers (frames)",
            lambda v: isinstance(v, (list, tuple)) and all(_is_int(x) and x > 0 for x in v))


#: the units of a budget: frames collected (agents on an env) or gradient steps (agents learning from the dataset)
UNITS = ("frames", "updates")


def _unit(unit: str) -> str:
    if unit not in UNITS:
        raise ValueError(f"unit must be one of {UNITS} (frames collected or gradient steps), got {unit!r}")
    return unit


@dataclass(frozen=True)
class TrainConfig:
    """``train``: the training budget."""

    total_frames: int = _setting(_int(1), 204_800)  # agents on the model env (and online): frames collected
    total_updates: int = _setting(_int(1), 100_000)  # agents learning from the dataset itself: gradient steps
    online: bool = _setting(_bool(), False)  # train in the real env from scratch, in real actions (no models, no CVAE)
    snapshot_frames: tuple[int, ...] = _setting(_positive_ints(), ())  # keep the agent's state at these steps too

    def total(self, unit: str) -> int:
        """The budget in ``unit``: ``"frames"`` (collected) or ``"updates"`` (gradient steps)."""
        return self.total_frames if _unit(unit) == "frames" else self.total_updates


@dataclass(frozen=True)
class EvalConfig:
    """``eval``: when and how the real-env evaluations run."""

    at_start: bool = _setting(_bool(), True)  # also evaluate the untrained agent
    model_env: bool = _setting(_bool(), True)  # also roll the policy out in the model (the model-real gap)
    every_frames: int = _setting(_int(1), 40_960)
    every_updates: int = _setting(_int(1), 10_000)
    episodes: int = _setting(_int(1), 30)  # deterministic real-env episodes per evaluation
    model_episodes: int | None = _setting(_int(1, optional=True), 50)  # episodes in the model env (null: episodes)
    sampled: bool = _setting(_bool(), False)  # also evaluate the sampled policy
    max_steps: int = _setting(_int(1), 1000)

    def every(self, unit: str) -> int:
        """The evaluation period in ``unit``: ``"frames"`` or ``"updates"``."""
        return self.every_frames if _unit(unit) == "frames" else self.every_updates


@dataclass(frozen=True)
class SelectionConfig:
    """``selection``: the offline policy selection (:mod:`~torchrl_offhrl.recipes.selection`)."""

    criterion: str = _setting(_choice(*CRITERIA), "last")
    include_start: bool = _setting(_bool(), False)  # the untrained policy is a candidate too
    guard: bool = _setting(_bool(), True)  # return the start policy when no member shows a gain over it (selection.PolicySelector)
    return_cap: str = _setting(_choice("data", "none"), "data")  # the guard's returns clipped at the data's best episode (selection.data_return_cap)
    fallback: str = _setting(_choice("bc_unless_start", "start_unless_bc", "start"), "bc_unless_start")  # what a fired guard returns (recipes.fallback)


@dataclass(frozen=True)
class CollectorConfig:
    """``collector``: the model envs stepped side by side."""

    num_envs: int = _setting(_int(1), 64)


@dataclass(frozen=True)
class TransferConfig:
    """``transfer``: the online phase on another task after the offline one (``task`` null: offline only)."""

    task: str | None = _setting((f"null or a task of torchrl_offhrl.envs.TASKS ({', '.join(map(repr, TASKS))})",
                                 lambda v: v is None or v in TASKS), None)
    online_frames: int = _setting(_int(1), 300_000)
    num_envs: int = _setting(_int(1), 16)
    decoder: str = _setting(_choice("discard", "keep"), "discard")
    from_scratch: bool = _setting(_bool(), False)
    eval_every_frames: int = _setting(_int(1), 10_000)


@dataclass(frozen=True)
class LoggerConfig:
    """``logger``: TorchRL's logger of the training scalars."""

    backend: str | None = _setting(_choice("csv", "tensorboard", "wandb", "mlflow", None), "csv")
    kwargs: dict = _setting(("a mapping", lambda v: isinstance(v, Mapping)), default_factory=dict)


def _optional(rule: tuple[str, Callable[[Any], bool]]) -> tuple[str, Callable[[Any], bool]]:
    return "null or " + rule[0], lambda v: v is None or rule[1](v)


def _auto(rule: tuple[str, Callable[[Any], bool]]) -> tuple[str, Callable[[Any], bool]]:
    return rule[0] + " or 'auto'", lambda v: v == "auto" or rule[1](v)


def _nested_setting(cls: type):
    """A field holding a nested section (its default: ``cls()``; its value: a mapping of ``cls``'s fields)."""
    return _setting(("a mapping of " + ", ".join(f.name for f in fields(cls)), lambda v: isinstance(v, Mapping)), default_factory=cls)


@dataclass(frozen=True)
class FitConfig:
    """``ensemble.fit`` / ``cvae.fit``: :class:`~torchrl_offhrl.models.SupervisedTrainer`'s settings (a fit runs to convergence on
    the held-out episodes: it stops once no member improved by more than ``rel_tol`` for ``patience`` epochs)."""

    lr: float = _setting(_num(0, lo_open=True), 1e-3)
    batch_size: int = _setting(_int(1), 256)
    max_epochs: int = _setting(_int(1), 200)  # bounds a fit that never settles
    max_steps: int | None = _setting(_int(1, optional=True), None)  # a fixed step budget instead (null: none)
    patience: int = _setting(_int(0), 5)
    rel_tol: float = _setting(_num(0, 1, hi_open=True), 0.005)


@dataclass(frozen=True)
class EnsembleConfig:
    """``ensemble``: the dynamics (and reward) ensemble (:class:`~torchrl_offhrl.models.DynamicsEnsemble`)."""

    num_models: int = _setting(_int(1), 5)
    hidden_sizes: tuple[int, ...] = _setting(_sizes(), (512, 512))
    reward_hidden_sizes: tuple[int, ...] | None = _setting(_optional(_sizes()), None)  # null: hidden_sizes
    loss: str = _setting(_choice("l1", "mse", "nll"), "l1")
    num_elites: int | None = _setting(_int(1, optional=True), None)  # keep this many members after the fit (null: all)
    learn_reward: bool = _setting(_bool(), True)  # false: the task's own reward function (block stacking)
    fit: FitConfig = _nested_setting(FitConfig)


@dataclass(frozen=True)
class CVAEConfig:
    """``cvae``: the latent action space (:class:`~torchrl_offhrl.models.ConditionalVAE`)."""

    hidden_sizes: tuple[int, ...] = _setting(_sizes(), (720, 720))
    kl_weight: float = _setting(_num(0), 0.05)
    goal_key: str | None = _setting(("null or a dataset key", lambda v: v is None or isinstance(v, str)), None)  # goal-conditioned
    fit: FitConfig = _nested_setting(FitConfig)


@dataclass(frozen=True)
class ModelEnvConfig:
    """``model_env``: the P-MDP's settings; ``auto`` computes one from the data and the fitted models (:mod:`~torchrl_offhrl.envs.rules`)."""

    horizon: int | str = _setting(_auto(_int(1)), "auto")
    member_mode: str = _setting(_choice("episode", "step", "mean"), "episode")
    sample: bool = _setting(_bool(), False)
    reset_states: str = _setting(_choice("initial", "any", "auto"), "auto")
    discrepancy: str = _setting(_choice(*DISCREPANCIES), "variance")
    latent_bound: float | str = _setting(_auto(_num(0, lo_open=True)), "auto")
    latent_origin: str = _setting(_choice("best", "behaviour", "zero"), "best")
    origin_share: float = _setting(_num(0, 1, lo_open=True), 0.1)
    reward_scale: float | str = _setting(("a positive number or 'auto'", lambda v: v == "auto" or (_is_num(v) and v > 0)), "auto")
    reward_penalty: float = _setting(_num(0), 0.0)
    pessimism: dict | None = _setting(("null or a mapping of threshold (> 0), fraction (> 0) or quantile (in (0, 1)), and penalty (>= 0), "
                                       "finite numbers", lambda v: _pessimism_ok(v)), None)


@dataclass(frozen=True)
class AblationConfig:
    """``ablation``: the paper's ablations."""

    no_cvae: bool = _setting(_bool(), False)  # the agent acts in real actions
    no_pessimism: bool = _setting(_bool(), False)  # no discrepancy termination, no penalty


#: the typed sections by their key in the config
SECTIONS: dict[str, type] = {"train": TrainConfig, "eval": EvalConfig, "selection": SelectionConfig, "collector": CollectorConfig,
                             "transfer": TransferConfig, "logger": LoggerConfig, "ensemble": EnsembleConfig, "cvae": CVAEConfig,
                             "model_env": ModelEnvConfig, "ablation": AblationConfig}


def _typed(prefix: str, cls: type):
    """``(key path, dataclass)`` of a section and of every section nested in it (``ensemble.fit``), read off its fields."""
    yield prefix, cls
    for f in fields(cls):
        if f.default_factory is not MISSING and is_dataclass(nested := f.default_factory()):
            yield from _typed(f"{prefix}.{f.name}", type(nested))


def section_defaults(key: str) -> dict:
    """The defaults of typed section ``key`` as plain values (lists for tuples), e.g. ``section_defaults("transfer")``."""
    return _plain_defaults(SECTIONS[key])


def _plain_defaults(cls: type) -> dict:
    out = {}
    for f in fields(cls):
        v = f.default_factory() if f.default is MISSING else f.default
        out[f.name] = _plain_defaults(type(v)) if is_dataclass(v) else list(v) if isinstance(v, tuple) else v
    return out


def parse_section(key: str, values: Mapping | None):
    """Typed section ``key`` from its mapping alone (absent keys: the defaults), for code that holds part of a config.

    Example:
        >>> parse_section("train", {"total_updates": 500}).total("updates")
        500
    """
    return _section(SECTIONS[key], values)


def _section(cls: type, values: Mapping | None):
    """A section's dataclass from its mapping (absent keys: the defaults); lists become tuples where the field is one, a
    nested section's mapping its dataclass."""
    kwargs = {}
    for f in fields(cls):
        if values is not None and f.name in values:
            v = values[f.name]
            default = f.default_factory() if f.default is MISSING else f.default
            if is_dataclass(default):
                kwargs[f.name] = _section(type(default), v)
            elif str(f.type).startswith("tuple") and isinstance(v, (list, tuple)):  # tuple[...] (or | None): lists from the YAML
                kwargs[f.name] = tuple(v)
            else:
                kwargs[f.name] = dict(v) if isinstance(v, Mapping) else v
    return cls(**kwargs)


@dataclass(frozen=True)
class RunConfig:
    """The typed view of a validated recipe config: the sections the training loop reads (:meth:`parse`).

    The algorithm (``algo``), task (``env``) and model sections stay
    mappings: their schemas are the agent's signature, the task registry and
    the model classes.

    Example:
        >>> rc = RunConfig.parse({"seed": 3, "train": {"total_frames": 4096}, "transfer": {"task": "backward"}})
        >>> rc.train.total("frames"), rc.eval.every("updates"), rc.transfer.task, rc.transfer.online_frames
        (4096, 10000, 'backward', 300000)
        >>> RunConfig.parse({"seed": 0}).transfer is None
        True
        >>> RunConfig.parse({"train": {"total_frame": 10}})
        Traceback (most recent call last):
        ...
        ValueError: invalid config values (nothing was run):
          train.total_frame: unknown key; train takes total_frames, total_updates, online, snapshot_frames
    """

    seed: int
    train: TrainConfig
    eval: EvalConfig
    selection: SelectionConfig
    collector: CollectorConfig
    transfer: TransferConfig | None     # None: offline training only (transfer.task null)
    logger: LoggerConfig

    @classmethod
    def parse(cls, cfg: Mapping) -> RunConfig:
        """Validate ``cfg`` (:func:`validate_config`) and return its typed sections."""
        validate_config(cfg)
        own = {f.name for f in fields(cls)}
        sections = {k: _section(c, cfg.get(k)) for k, c in SECTIONS.items() if k in own}
        if sections["transfer"].task is None:
            sections["transfer"] = None
        return cls(seed=int(cfg.get("seed", 0)), **sections)


#: the top level's own keys (the sections aside): key -> (what is allowed, check)
TOP_LEVEL: dict[str, tuple[str, Callable[[Any], bool]]] = {
    "seed": _int(0),
    "dataset_seed": _int(0),
    "num_transitions": _int(1, optional=True),
    "dataset_num_envs": _int(1),
    "val_ratio": _num(0, 1, lo_open=True, hi_open=True),
    "torch_threads": _int(1, optional=True),
    "fit_threads": _int(1, optional=True),
}


#: key path -> (what is allowed, check), every one held by a field above (absent keys are left to their defaults)
RULES: dict[str, tuple[str, Callable[[Any], bool]]] = {
    **TOP_LEVEL, **{f"{path}.{f.name}": f.metadata["rule"] for key, section in SECTIONS.items() for path, cls in _typed(key, section)
                    for f in fields(cls)}}

#: config keys renamed since runs were written under the old names: section -> {old: new}. PPO's coefficients and KL
#: target took its losses' names when the agent stopped restating them (TorchRL's ``critic_coeff``, ``entropy_coeff``,
#: ``dtarg``). A run's config read back (:func:`~torchrl_offhrl.recipes.config.upgrade_config`) and its fingerprint use the new names, so an older run
#: still resumes, archives and evaluates as the run it is.
RENAMED_KEYS: dict[str, dict[str, str]] = {"algo": {"vf_coef": "critic_coeff", "ent_coef": "entropy_coeff", "kl_target": "dtarg"}}


def renamed_key(path: str, value) -> str | None:
    """The problem to report for ``path`` (e.g. ``"algo.vf_coef"``) set to ``value`` when it is a key of an older version
    (:data:`RENAMED_KEYS`): its new name and the setting to write instead; None for any other key.

    >>> renamed_key("algo.vf_coef", 0.5)
    'algo.vf_coef: renamed algo.critic_coeff (the name its loss gives it); write algo.critic_coeff=0.5'
    """
    section, _, key = path.partition(".")
    new = RENAMED_KEYS.get(section, {}).get(key)
    return None if new is None else f"{path}: renamed {section}.{new} (the name its loss gives it); write {section}.{new}={value}"


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
    "dtarg": _num(0, lo_open=True),                   # PPO's KL penalty's target (TorchRL's KLPENPPOLoss)
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
    "rollout_freq": _int(1, optional=True),           # MOPO's schedule (agents.MOPOAgent)
    "rollout_batch_size": _int(1, optional=True),
    "model_retain_rollouts": _int(1),
}


def _pessimism_ok(v) -> bool:
    """``model_env.pessimism``: null, or its keys each a finite number in range (a NaN or negative penalty would only fail,
    or silently reward ending episodes, once training runs)."""
    if v is None:
        return True
    if not isinstance(v, Mapping):
        return False
    ranges = {"threshold": (0, None), "fraction": (0, None), "quantile": (0, 1), "penalty": (None, None)}
    for k, x in v.items():
        if k not in ranges:
            return False
        if x is None:
            continue
        if not _is_num(x) or not math.isfinite(float(x)):
            return False
        lo, hi = ranges[k]
        if k == "penalty" and x < 0:
            return False
        if lo is not None and not x > lo or hi is not None and not x < hi:
            return False
    return True


def _algo_problems(algo: Mapping) -> list[str]:
    """An algorithm's keys its agent does not take (``name`` and ``label`` aside), named before any data or model work."""
    from ..agents import AGENTS, agent_defaults, unknown_hyperparameters

    name = algo.get("name")
    if name not in AGENTS:
        return [f"algo.name: expected one of {', '.join(sorted(AGENTS))}, got {name!r}"] if name is not None else []
    try:  # a loss named by algo.loss brings its own arguments: importing it can fail, which is one more problem to name
        unknown = unknown_hyperparameters(name, algo)
    except (ValueError, TypeError) as err:
        return [str(err)]
    if not unknown:
        return []
    accepted = agent_defaults(name, loss=algo.get("loss"))  # the loss imported above: it cannot fail here
    takes = ", ".join(sorted(accepted))
    return [(RENAMED_KEYS["algo"].get(k) in accepted and renamed_key(f"algo.{k}", algo[k]))
            or f"algo.{k}: unknown hyper-parameter of algo={name}; it takes {takes}" for k in unknown]


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
    for key, section in (typed for k, c in SECTIONS.items() for typed in _typed(k, c)):
        given = _get(cfg, key)
        if isinstance(given, Mapping):
            names = [f.name for f in fields(section)]
            problems += [f"{key}.{k}: unknown key; {key} takes {', '.join(names)}" for k in given if k not in names]
        elif given is not None and given is not _MISSING and "." not in key:
            problems.append(f"{key}: expected a mapping of {', '.join(f.name for f in fields(section))}, got {given!r}")
    if "device" in cfg:
        what = _device_problem(cfg["device"])
        if what:
            problems.append(f"device: expected {what}, got {cfg['device']!r}")
    for key, value in (cfg.get("algo") or {}).items():
        rule = ALGO_RULES.get(key)
        if rule is None and key.endswith("_lr"):  # a head's own step size (null: the agent's lr)
            rule = _num(0, lo_open=True, optional=True)
        if rule is None and key.endswith(("_coef", "_coeff")):  # a loss term's weight (MOC's *_coef, TorchRL's PPO *_coeff)
            rule = _num(0)
        if rule is not None and not rule[1](value):
            problems.append(f"algo.{key}: expected {rule[0]}, got {value!r}")
    if isinstance(cfg.get("algo"), Mapping):
        problems += _algo_problems(cfg["algo"])
    if problems:
        raise ValueError("invalid config values (nothing was run):\n  " + "\n  ".join(problems))
