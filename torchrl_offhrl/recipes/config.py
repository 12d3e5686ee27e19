"""Config resolution for the recipes: hydra composition, the dataset a config names, the models' and the P-MDP's settings, run naming.

One schema serves every command: ``configs/offline_train.yaml`` (with its
``algo/`` and ``env/`` groups); ``demo.yaml`` and ``pipeline.yaml`` start
from it and change budgets.
"""
from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Mapping
from pathlib import Path

from ..data import OfflineDataset, load_dataset
from ..data.catalog import named_dataset
from ..envs.latent import DEFAULT_LATENT_BOUND
from ..registry import LEVELS
from ..utils import to_plain
from .schema import RENAMED_KEYS, renamed_key, section_defaults


def _register_resolvers() -> None:
    """``${offhrl_mul:a,b,...}``: the product of integers, for a budget a config states in its own units (MOPO's: rollouts of
    ``algo.rollout_batch_size`` x ``model_env.horizon`` frames, ``configs/algo/mopo.yaml``)."""
    import math

    from omegaconf import OmegaConf

    def mul(*xs):
        if any(x is None for x in xs):
            raise ValueError("a budget counted in rollouts needs algo.rollout_batch_size and model_env.horizon; with either null "
                             "(SAC's schedule) give train.total_frames and eval.every_frames in frames")
        return math.prod(int(x) for x in xs)

    if not OmegaConf.has_resolver("offhrl_mul"):
        OmegaConf.register_new_resolver("offhrl_mul", mul)


_register_resolvers()

__all__ = [
    "RENAMED_KEYS", "RESUMABLE_KEYS", "acts_in_latent_space", "algo_label", "auto_reward_scale", "latent_bound", "learns_from_dataset", "resolve_reward_scale", "return_range_reward_scale", "compose", "config_dir", "config_fingerprint", "default_run_dir", "fingerprints_match", "fit_as_before", "model_config", "model_env_config",
    "data_label", "model_env_batch", "needs_rules", "offline_rules_for", "pessimism_for", "pessimism_table", "resolve_dataset", "rules_not_used", "transfer_config", "transfer_label", "upgrade_config",
]

#: Settings that may change between a run and its resumption; anything else must match the checkpoint.
RESUMABLE_KEYS = ("train", "eval", "logger", "run_dir", "out_root", "torch_threads", "fit_threads", "device")  # and transfer.online_frames / eval_every_frames


def config_dir() -> Path:
    """The hydra configs, shipped inside the package (``configs/`` in a checkout links to them)."""
    path = Path(__file__).resolve().parents[1] / "configs"
    if not (path / "offline_train.yaml").is_file():
        raise FileNotFoundError(f"the package's configs are missing from {path}; reinstall torchrl_offhrl")
    return path


def compose(config_name: str, overrides: list[str], command: str | None = None):
    """The hydra config ``config_name`` with ``overrides`` (``key=value`` strings).

    A malformed override, an unknown config group option or key raises
    ``ValueError`` with hydra's explanation.
    """
    from hydra import compose as hcompose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    bad = [o for o in overrides if "=" not in o and not o.startswith("~")]  # ~key: hydra's deletion of a key
    if bad:
        raise SystemExit(f"error: overrides must look like key=value (or ~key to delete one), got {bad}; see `offhrl {command or 'train'} --help`")
    renamed = [m for o in overrides if "=" in o and (m := renamed_key(o.split("=", 1)[0].lstrip("+~"), o.split("=", 1)[1]))]
    if renamed:  # a key of an older version: say what it is called now rather than hydra's "could not override"
        raise ValueError("; ".join(renamed))
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base=None):
            cfg = hcompose(config_name, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:
        raise ValueError(f"{err} (configs in {config_dir()}; an override is key=value, a config group option "
                         f"is e.g. algo=sac|ppo|moc, env=hopper|halfcheetah)") from err
    if config_name == "demo":  # the demo's short-budget minibatch is the on-policy agents' (MOC, PPO); others keep their own batches
        _drop_untaken_minibatch(cfg)
    return cfg


def _drop_untaken_minibatch(cfg) -> None:
    from omegaconf import open_dict

    from ..agents import AGENTS, agent_defaults

    algo = cfg.get("algo")
    if algo is not None and "minibatch_size" in algo and algo.get("name") in AGENTS and "minibatch_size" not in agent_defaults(algo.name):
        with open_dict(algo):
            del algo["minibatch_size"]


def resolve_dataset(cfg: Mapping) -> OfflineDataset:
    """The dataset a recipe config names: ``cfg.dataset`` is a file path, a local Minari id, or a level name.

    Level names (``medium``, ``hopper-medium``, ``medium-expert``, ...) of
    ``cfg.env`` are generated with the shipped behaviour policies on first
    use and cached (:func:`torchrl_offhrl.data.named_dataset`), with
    ``num_transitions`` transitions (null: 1M), collected by
    ``dataset_num_envs`` envs with seed ``dataset_seed``.
    """
    spec, env_name, env_id = str(cfg["dataset"]), cfg["env"]["name"], cfg["env"]["env_id"]
    path = Path(spec).expanduser()
    if path.exists() or path.suffix in (".hdf5", ".h5"):
        return load_dataset(path, env_id=env_id)
    if "/" in spec:  # a Minari id such as mujoco/hopper/medium-v0
        return load_dataset(spec, env_id=env_id)
    level = spec[len(env_name) + 1 :] if spec.startswith(env_name + "-") else spec
    if level not in LEVELS:
        raise ValueError(
            f"dataset={spec!r} is neither an existing file, a Minari id, nor a level name "
            f"({', '.join(LEVELS)}); give a path to an HDF5 file or one of those names."
        )
    return named_dataset(
        f"{env_name}-{level}", num_transitions=cfg.get("num_transitions"), seed=cfg.get("dataset_seed", 0), num_envs=cfg.get("dataset_num_envs", 8),
    )


def latent_bound(cfg: Mapping) -> float:
    """The latent box's half-width of a run: what its offline rules resolved (``resolved_model_env``, in a run's
    ``config.json``), else ``model_env.latent_bound`` (:data:`~torchrl_offhrl.envs.DEFAULT_LATENT_BOUND` if unset or
    ``auto`` with no CVAE to compute it from)."""
    resolved = (cfg.get("resolved_model_env") or {}).get("latent_bound")
    if resolved is not None:
        return float(resolved)
    value = (cfg.get("model_env") or {}).get("latent_bound", DEFAULT_LATENT_BOUND)
    # auto is the CVAE's posterior box (envs.rules.latent_bound_rule), resolved when a run starts; a run that fits no CVAE (from
    # scratch, in real actions) only maps its latent box onto the action box, and takes the default one
    return DEFAULT_LATENT_BOUND if value == "auto" else float(value)


def model_config(cfg: Mapping) -> dict:
    """The part of a recipe config that :func:`~torchrl_offhrl.recipes.fit_or_load_models` reads (and keys its cache on)."""
    cfg = to_plain(cfg)
    return {
        "seed": cfg.get("dataset_seed", 0),
        "device": str(cfg.get("device", "cpu")),
        "dataset": {"val_ratio": cfg.get("val_ratio", 0.1)},
        "ensemble": cfg["ensemble"],
        "cvae": cfg["cvae"],
        "fit_threads": cfg.get("fit_threads"),  # how fast, not what, the fits compute: not in the cache key
    }


def pessimism_for(env_cfg: Mapping, level: str | None, overrides: Mapping | None = None, table: Mapping | None = None) -> dict:
    """The P-MDP's pessimism from a per-dataset ``table`` (the ``paper`` preset's; default: ``env_cfg['pessimism']``), then overrides."""
    table = to_plain(table if table is not None else env_cfg.get("pessimism", {}))
    out = dict(table.get("default", {"quantile": 0.99, "penalty": 20.0}))
    if level and level in table:
        out = dict(table[level])
    overrides = {k: v for k, v in (overrides or {}).items() if v is not None}
    if "quantile" in overrides and "fraction" not in overrides:
        out.pop("fraction", None)  # asking for a quantile replaces the table's fraction
    out.update(overrides)
    if out.get("fraction") is not None:
        out.pop("quantile", None)
    return out


#: the model env's settings the offline rules compute (torchrl_offhrl.envs.rules) where the config says ``auto``
RULE_KEYS = ("horizon", "reset_states", "latent_bound")


def pessimism_table(cfg: Mapping) -> dict | None:
    """The per-dataset pessimism table a config names, or None (the offline rules decide).

    The ``paper`` preset (``preset=paper``) ships the paper's tables under
    ``paper_pessimism.<env name>``; an env group may carry its own
    ``env.pessimism`` (the block-stacking tasks: the paper's 99th percentile,
    the same on every dataset).
    """
    env = cfg.get("env") or {}
    paper = (cfg.get("paper_pessimism") or {}).get(env.get("name"))
    if paper:
        return to_plain(paper)
    return to_plain(env["pessimism"]) if env.get("pessimism") else None


def needs_rules(cfg: Mapping) -> bool:
    """Whether a config leaves any model-env setting to the offline rules (a key set to ``auto``, or no pessimism given)."""
    menv = cfg.get("model_env") or {}
    if any(menv.get(k, "auto") == "auto" for k in RULE_KEYS):
        return True
    over = {k: v for k, v in (menv.get("pessimism") or {}).items() if v is not None}
    given = ("threshold" in over or "quantile" in over or "fraction" in over) and "penalty" in over
    return pessimism_table(cfg) is None and not given and not cfg.get("ablation", {}).get("no_pessimism", False)


def model_env_config(cfg: Mapping, level: str | None, data: OfflineDataset | None = None, rules=None) -> tuple[dict, dict]:
    """``(env settings for make_model_env, resolved pessimism)``: ``model_env`` with its ``auto`` keys and pessimism resolved.

    ``rules``: the :class:`~torchrl_offhrl.envs.rules.OfflineRules` of the
    run's data and models (:func:`offline_rules_for`); every ``auto`` key takes
    its value, and so do the threshold and penalty unless a table
    (:func:`pessimism_table`) or ``model_env.pessimism`` gives them.
    Without ``rules`` the ``auto`` keys are left out (settings that build no
    model env: the online ones).
    ``reward_scale: auto`` is resolved here to :func:`auto_reward_scale` of
    ``data`` with the agent's ``gamma`` (``algo.gamma``, else 0.99).
    """
    table = pessimism_table(cfg)
    overrides = {k: v for k, v in ((cfg.get("model_env") or {}).get("pessimism") or {}).items() if v is not None}
    if table is not None:
        pess = pessimism_for(cfg["env"], level, overrides, table=table)
    elif rules is not None:
        pess = {"threshold": rules.threshold, "penalty": rules.penalty}
        if "quantile" in overrides or "fraction" in overrides:
            pess.pop("threshold")  # a calibration asked for: the env calibrates on the dataset
        pess.update(overrides)
    else:
        pess = pessimism_for(cfg["env"], level, overrides)
    if cfg.get("ablation", {}).get("no_pessimism", False):
        pess = {"threshold": float("inf"), "penalty": 0.0}
    menv = {k: v for k, v in cfg.get("model_env", {}).items() if k != "pessimism"}
    for key in RULE_KEYS:
        if menv.get(key, "auto") == "auto":
            if rules is not None and (key != "latent_bound" or rules.latent_bound is not None):
                menv[key] = getattr(rules, key)
            else:
                menv.pop(key, None)
    scale = menv.get("reward_scale", 1.0)
    if scale == "auto" and data is None:
        raise ValueError("model_env.reward_scale=auto is computed from the dataset: pass data to model_env_config")
    menv["reward_scale"] = resolve_reward_scale(scale, data, float(cfg.get("algo", {}).get("gamma", 0.99)), key="model_env.reward_scale")
    return {**menv, **pess}, pess


def model_env_batch(cfg: Mapping) -> int:
    """How many envs a run's model env steps at once: the agent's own rollout batch where its config names one (MOPO's
    ``algo.rollout_batch_size``, 50,000 branched rollouts), else ``collector.num_envs``."""
    return int((cfg.get("algo") or {}).get("rollout_batch_size") or cfg["collector"]["num_envs"])


def rules_not_used(cfg: Mapping, settings: Mapping, rules) -> dict[str, str]:
    """What the calibration report states that the run does not use, and why: ``{"pessimism" | "horizon" | "reset_states" |
    "latent_bound": reason}``. ``settings``: :func:`model_env_config`'s env settings for ``cfg`` with ``rules``. A report
    that printed the rules' threshold or episode length for a run that sets its own (MOPO: no termination, 5-step
    rollouts) would describe another model env than the one the agent trains in."""
    out = {}
    if cfg.get("ablation", {}).get("no_pessimism", False):
        out["pessimism"] = "ablation.no_pessimism: no episode ends on the members' disagreement, no penalty"
    elif (settings.get("threshold"), settings.get("penalty")) != (rules.threshold, rules.penalty):
        given = ", ".join(f"{k} {settings[k]:.4g}" for k in ("threshold", "penalty")
                          if isinstance(settings.get(k), (int, float)) and settings[k] != getattr(rules, k))
        source = "the paper preset's table" if pessimism_table(cfg) is not None else "model_env.pessimism"
        out["pessimism"] = f"{source} gives " + (given or "a calibration of its own")
    menv = cfg.get("model_env") or {}
    for key in RULE_KEYS:
        if menv.get(key, "auto") != "auto":
            out[key] = f"model_env.{key}={menv[key]} (the config's)"
    return out


def offline_rules_for(cfg: Mapping, data: OfflineDataset, ensemble, cvae=None):
    """The offline rules (:func:`torchrl_offhrl.envs.rules.offline_rules`) of a run: its data, models, split and discount; None when the
    config leaves nothing to them (:func:`needs_rules`)."""
    if not needs_rules(cfg) or ensemble is None:
        return None
    from ..envs.rules import offline_rules

    menv = cfg.get("model_env") or {}
    return offline_rules(ensemble, data, cvae, val_ratio=float(cfg.get("val_ratio", 0.1)), split_seed=int(cfg.get("dataset_seed", 0)),
                         discrepancy=menv.get("discrepancy", "variance"), gamma=float((cfg.get("algo") or {}).get("gamma", 0.99)))


def resolve_reward_scale(spec, data: OfflineDataset | None, gamma: float = 0.99, key: str = "algo.reward_scale") -> float:
    """A reward scale from its config value: a positive number, ``"auto"`` (:func:`auto_reward_scale`) or ``"return_range"`` (:func:`return_range_reward_scale`)."""
    if spec in ("auto", "return_range"):
        if data is None:
            raise ValueError(f"{key}={spec} is computed from the dataset: pass the data")
        return auto_reward_scale(data, gamma) if spec == "auto" else return_range_reward_scale(data)
    if not isinstance(spec, (int, float)) or isinstance(spec, bool) or not spec > 0:
        raise ValueError(f"{key} must be a positive number, 'auto' or 'return_range', got {spec!r}")
    return float(spec)


def return_range_reward_scale(data: OfflineDataset) -> float:
    """``1000 / (max - min)`` of the dataset's complete episode returns: IQL's reward normalisation for locomotion.

    As the IQL paper (Kostrikov et al., 2022) and CORL do for the D4RL
    locomotion datasets: the spread of episode returns becomes 1000, which
    is what IQL's temperature (3.0) was tuned against.
    """
    returns = data.episode_returns(complete_only=True)
    if returns.numel() == 0:
        returns = data.episode_returns()
    spread = float(returns.max() - returns.min()) if returns.numel() else 0.0
    if not spread > 0:
        raise ValueError("reward_scale=return_range: the dataset's episode returns have zero spread (one episode?); set algo.reward_scale to a number")
    return 1000.0 / spread


def auto_reward_scale(data: OfflineDataset, gamma: float = 0.99) -> float:
    """``1 / std`` of the dataset's discounted returns-to-go: the value targets an on-policy critic meets become O(1).

    Unscaled MuJoCo returns-to-go are in the hundreds (Hopper medium: 194 +- 76
    at gamma 0.99); a 64x64 critic stepped by Adam at the paper's lr 1e-4 then
    explains ~0% of their variance after 3,000 steps, against ~45% for the same
    targets divided by 100 (``experiments/diagnostics/critic_probe.py``), so advantages are
    noise and PPO/MOC drift instead of improving. The paper's PPO values come
    from rl-zoo, which divides rewards by a running return std (SB3's
    ``VecNormalize``); this is the same scale, fixed from the data so that a
    run is deterministic and resumable. The scale multiplies the rewards
    only (no shift: the sign of the rewards, and so the cost of ending an
    episode, is kept).
    """
    std = float(data.returns_to_go(gamma).std())
    if not std > 0:
        raise ValueError("reward_scale=auto: the dataset's returns-to-go have zero spread; set model_env.reward_scale to a number")
    return 1.0 / std


def safe_name(part: str) -> str:
    """``part`` as one folder-name component: every character outside ``[A-Za-z0-9._+=-]`` (a path separator, a space, a
    shell character) becomes ``_``, and a name that is empty or starts with a dot (``..``, a hidden folder) gets a ``_``
    prefix, so a config value can never put a run outside its out_root.

    Examples:
        >>> safe_name("../../etc"), safe_name("moc_official"), safe_name("my run/1")
        ('_.._.._etc', 'moc_official', 'my_run_1')
    """
    out = re.sub(r"[^A-Za-z0-9._+=-]", "_", str(part))
    return out if out and not out.startswith(".") else "_" + out


def default_run_dir(cfg: Mapping) -> Path:
    """``<out_root>/<algo label>-<env>-<dataset>[-<ablations>][-<transfer label>][-online]-seed<seed>``.

    A dataset given as a file or a Minari id is named by its stem plus a short
    hash of the full path, so two files with the same name never share a run.
    The folder name is built from config values made safe (:func:`safe_name`):
    it is always one folder directly under ``out_root``.
    """
    spec = str(cfg["dataset"])
    ds = spec
    if "/" in spec or Path(spec).suffix:
        digest = hashlib.sha1(str(Path(spec).expanduser().resolve()).encode()).hexdigest()[:6]
        ds = f"{Path(spec).stem}-{digest}"
    abl = "".join(f"-{k}" for k, v in to_plain(cfg.get("ablation", {})).items() if v)
    transfer = transfer_label(cfg)
    abl += f"-{transfer}" if transfer else ""
    abl += "-online" if (cfg.get("train") or {}).get("online") else ""
    return Path(cfg.get("out_root", "outputs/runs")) / safe_name(f"{algo_label(cfg['algo'])}-{cfg['env']['name']}-{ds}{abl}-seed{cfg['seed']}")


def learns_from_dataset(cfg: Mapping) -> bool:
    """Whether the config's agent is a model-free offline agent (``data_source = "dataset"``: IQL, CQL, TD3+BC, BC)."""
    from ..agents import agent_class

    return agent_class(cfg["algo"]["name"]).data_source == "dataset"


def acts_in_latent_space(cfg: Mapping) -> bool:
    """Whether the config's agent acts through the CVAE decoder: model-env agents unless ``ablation.no_cvae``; never a dataset
    agent, nor one trained online in the real env from scratch (``train.online``: real actions, no models)."""
    if cfg.get("ablation", {}).get("no_cvae", False) or learns_from_dataset(cfg):
        return False
    return not bool((cfg.get("train") or {}).get("online", False))


def transfer_config(cfg: Mapping) -> dict | None:
    """The run's transfer settings (``transfer.*``, defaults filled in), or None for an offline-only run (``transfer.task`` null).

    Examples:
        >>> transfer_config({"transfer": {"task": None}}) is None
        True
        >>> t = transfer_config({"transfer": {"task": "backward", "online_frames": 1000}})
        >>> t["task"], t["online_frames"], t["decoder"], t["from_scratch"]
        ('backward', 1000, 'discard', False)
    """
    t = dict(to_plain(cfg.get("transfer") or {}))
    if t.get("task") is None:
        return None
    return {**section_defaults("transfer"), **t}  # the defaults are TransferConfig's (recipes.schema)


def transfer_label(cfg: Mapping) -> str:
    """How a transfer run is named and grouped: ``"to-backward"``, ``"scratch-backward"`` (+ ``"-keepdecoder"``); ``""`` without transfer."""
    t = transfer_config(cfg)
    if t is None:
        return ""
    return ("scratch-" if t["from_scratch"] else "to-") + str(t["task"]) + ("-keepdecoder" if t["decoder"] == "keep" else "")


def data_label(summary: dict) -> str:
    """The data a run used, by name: the file (or Minari id) it was given, else the generated level (``hopper-medium``).

    >>> data_label({"dataset": "/data/my_robot.hdf5", "level": "medium", "env_id": "Hopper-v5"})
    '/data/my_robot.hdf5'
    >>> data_label({"dataset": "medium", "level": "medium", "env_id": "Hopper-v5"})
    'hopper-medium'
    """
    spec = str(summary.get("dataset"))
    if "/" in spec or Path(spec).suffix in (".hdf5", ".h5"):
        return spec
    level = summary.get("level") or spec
    env = str(summary.get("env_id", "")).split("-")[0].lower()
    return level if not env or level.startswith(env + "-") else f"{env}-{level}"


def algo_label(algo_cfg: Mapping) -> str:
    """How runs of an algorithm config are named and grouped: its ``label`` (e.g. ``moc_official``), else its agent ``name``."""
    return str(algo_cfg.get("label") or algo_cfg["name"])


#: settings added after runs already existed, with the value that reproduces those runs: a config holding
#: exactly that value fingerprints as one without the key, so older checkpoints still resume
#: (``reward_hidden_sizes: null``: the reward model takes the transition model's widths)
LATER_DEFAULTS: dict[str, dict[str, object]] = {"algo": {"intra_head_gain": 0.01, "loss": None, "policy_ema": None, "log_std_lr": None, "final_log_std": None, "prior_coef": 0.0,
                                                          "termination_coef": 1.0, "option_coef": 1.0, "normalize_advantage": True,
                                                          "loss_type": "clip", "dtarg": 0.01, "bc_init_steps": 0, "bc_init_lr": 1e-3,
                                                          "bc_init_batch_size": 256, "head_gain": 1.0,
                                                          "terminal_on_success": True},
                                                 "ensemble": {"reward_hidden_sizes": None, "num_elites": None, "learn_reward": True},
                                                 "cvae": {"goal_key": None}, "model_env": {"reward_penalty": 0.0, "latent_origin": "zero", "sample": False},
                                                 "selection": {"guard": False, "return_cap": "none", "fallback": "start"}}


def upgrade_config(cfg: Mapping) -> dict:
    """``cfg`` (a run's ``config.json``, however old) under today's key names (:data:`RENAMED_KEYS`); the values unchanged.

    >>> upgrade_config({"algo": {"name": "ppo", "vf_coef": 0.5, "lr": 3e-4}, "seed": 1})
    {'algo': {'name': 'ppo', 'critic_coeff': 0.5, 'lr': 0.0003}, 'seed': 1}
    """
    out = dict(cfg)
    for section, renamed in RENAMED_KEYS.items():
        if isinstance(out.get(section), Mapping):
            out[section] = {renamed.get(k, k): v for k, v in out[section].items()}
    return out


def fit_as_before(model_cfg: Mapping) -> dict:
    """A model's config (``ensemble`` or ``cvae``) with ``fit.rel_tol: 0`` (the convergence rule off) left out: the fit as it was
    before the key existed, so that its cache entries and checkpoints stay the same.

    >>> fit_as_before({"hidden_sizes": [8], "fit": {"lr": 0.001, "rel_tol": 0.0}})
    {'hidden_sizes': [8], 'fit': {'lr': 0.001}}
    """
    fit = model_cfg.get("fit")
    if isinstance(fit, Mapping) and fit.get("rel_tol", None) == 0.0:
        return {**model_cfg, "fit": {k: v for k, v in fit.items() if k != "rel_tol"}}
    return dict(model_cfg)


def config_fingerprint(cfg: Mapping) -> str:
    """The config minus :data:`RESUMABLE_KEYS`, as canonical JSON: a checkpoint resumes only under the same fingerprint."""
    kept = {k: v for k, v in upgrade_config(cfg).items() if k not in RESUMABLE_KEYS}
    if isinstance(kept.get("env"), Mapping) and "mopo" in kept["env"]:
        # a lookup table (MOPO's settings per dataset): what a run uses of it is in its model_env, resolved
        kept["env"] = {k: v for k, v in kept["env"].items() if k != "mopo"}
    table = pessimism_table(cfg)
    if table is not None:
        # the pessimism table a run reads (the paper preset's, or the env group's before it moved there): compared as the
        # table of this run's env, wherever the config holds it
        kept["env"] = {**{k: v for k, v in (kept.get("env") or {}).items() if k != "pessimism"}, "pessimism": table}
        kept.pop("paper_pessimism", None)
    kept.pop("preset", None)
    for part in ("ensemble", "cvae"):
        if isinstance(kept.get(part), Mapping):
            kept[part] = fit_as_before(kept[part])
    if isinstance(kept.get("model_env"), Mapping) and kept["model_env"].get("pessimism") is None and "pessimism" in kept["model_env"]:
        # no overrides of the pessimism table: null (the config's default) and {} (its default before) are the same run
        kept["model_env"] = {**kept["model_env"], "pessimism": {}}
    if isinstance(kept.get("selection"), Mapping):
        # the guard's return cap and fallback change nothing a run trains, only which kept policy its end returns (decided again from
        # the evaluation records whenever a finished run is called): a run resumes, or is re-finished, under either value
        kept["selection"] = {k: v for k, v in kept["selection"].items() if k not in ("return_cap", "fallback")}
    for section, defaults in LATER_DEFAULTS.items():
        if isinstance(kept.get(section), Mapping):
            kept[section] = {k: v for k, v in kept[section].items() if not (k in defaults and v == defaults[k])}
    if isinstance(kept.get("algo"), Mapping):
        # speed switches (torch.compile of the same loss, the same update captured as CUDA graphs): the same run with them
        # or without, and as before the keys existed
        kept["algo"] = {k: v for k, v in kept["algo"].items() if k not in ("compile", "cudagraphs")}
    if learns_from_dataset(cfg):  # a model-free agent fits no model: it is the same run whatever the (unused) model settings
        kept.pop("ensemble", None)
        kept.pop("cvae", None)
    if (cfg.get("train") or {}).get("online"):  # the budget may change on resume, not where the agent trains
        kept["train_online"] = True
    t = transfer_config(cfg)
    if t is None:  # an offline-only run is the same run whatever the (unused) transfer settings, and as before they existed
        kept.pop("transfer", None)
    else:  # the online budget and evaluation period may change on resume, as train and eval may
        kept["transfer"] = {k: v for k, v in t.items() if k not in ("online_frames", "eval_every_frames")}
    return json.dumps(kept, sort_keys=True, default=str)


def fingerprints_match(stored: str | None, fingerprint: str) -> bool:
    """Whether a checkpoint's ``stored`` fingerprint is the run of ``fingerprint`` (``None``: a checkpoint older than fingerprints).

    ``stored`` is read again under today's rules of :func:`config_fingerprint`
    (a fingerprint is itself a config minus :data:`RESUMABLE_KEYS`): a
    checkpoint written before a rule dropped a setting (for example the
    model settings of agents that fit no model) still resumes, and one whose
    kept settings differ still does not.
    """
    if stored is None or stored == fingerprint:
        return True
    try:
        old = json.loads(stored)
    except (TypeError, ValueError):
        return False
    return isinstance(old, Mapping) and config_fingerprint(old) == fingerprint
