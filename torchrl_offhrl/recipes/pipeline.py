"""Builders shared by the examples: dataset, fitted models, composed envs.

Every recipe goes through these, so a dataset and its fitted models are made
once and cached, and every algorithm trains on the same composed env.
"""
from __future__ import annotations

import hashlib
import json
import logging
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torchrl.envs import Compose, TransformedEnv

from ..agents import action_box
from ..data import OfflineDataset
from ..registry import task_of
from ..envs import DEFAULT_LATENT_BOUND, AffineActionMap, BlockStackModelEnv, LatentActionTransform, PessimisticModelEnv, SubGoalTracker, make_task_env
from ..models import ConditionalVAE, DynamicsEnsemble, LatentOrigin
from ..utils import CorruptFileError, atomic_write, cache_dir, remove_stale_tmp, threads, to_plain
from .config import LATER_DEFAULTS, fit_as_before
from .schema import ModelEnvConfig

__all__ = [
    "DEFAULT_ORIGIN_SHARE",
    "GaussianLatentPolicy",
    "apply_latent_origin",
    "fit_or_load_models",
    "fit_or_load_origin",
    "origin_path",
    "origin_share",
    "make_eval_model_env",
    "make_model_env",
    "make_real_env",
]

log = logging.getLogger(__name__)


def _digest(obj: Any) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _as_json(obj: Any):
    """``obj`` as it reads back from ``ident.json`` (tuples as lists, other objects as strings), to compare with it."""
    return json.loads(json.dumps(obj, default=str))


def _record_source(path: Path, ident: dict, source) -> None:
    """Keep, beside a cache entry, its identity and every data source it served (to say when a source's content changed)."""
    try:
        known = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):  # damaged: written again
        known = {}
    sources = list(known.get("sources", []))
    if source and source not in sources:
        sources.append(source)
    elif known:
        return
    with atomic_write(path) as tmp:
        Path(tmp).write_text(json.dumps({**_as_json(ident), "sources": sources}, indent=1))


def _entries_for_other_data(source, ident: dict) -> list[Path]:
    """Cache entries with the same settings for a dataset from the same ``source`` but with other content."""
    if not source:
        return []
    rest = _as_json({k: v for k, v in ident.items() if k != "data"})
    found = []
    for meta in sorted((cache_dir() / "models").glob("*/ident.json")):
        try:
            other = json.loads(meta.read_text())
        except (OSError, ValueError):
            continue
        same_settings = rest == {k: v for k, v in other.items() if k not in ("data", "sources")}
        if source in other.get("sources", []) and other.get("data") != ident["data"] and same_settings:
            found.append(meta.parent)
    return found


def _same_model_elsewhere(ident: dict, folder: Path, part: str) -> Path | None:
    """``<part>.pt`` of another cache entry fitted on the same data with the same ``part`` settings (``"ensemble"`` or ``"cvae"``), or None.

    The ensemble does not depend on the CVAE's settings nor the CVAE on the
    ensemble's, so a run (or a trial of ``offhrl tune models``) that only
    changes the other model reuses it instead of fitting it again.
    """
    keys = ("data", part, "val_ratio", "seed")
    want = _as_json({k: ident[k] for k in keys})
    for meta in sorted((cache_dir() / "models").glob("*/ident.json")):
        if meta.parent == folder or not (meta.parent / f"{part}.pt").is_file():
            continue
        try:
            other = json.loads(meta.read_text())
        except (OSError, ValueError):
            continue
        if part == "ensemble" and other.get("ensemble", {}).get("reward_hidden_sizes", "absent") is None:
            other["ensemble"] = {k: v for k, v in other["ensemble"].items() if k != "reward_hidden_sizes"}
        if _as_json({k: other.get(k) for k in keys}) == want:
            return meta.parent / f"{part}.pt"
    return None


def load_cached(cls, path):
    """A cached model, or None when there is none or it is corrupt (then it is deleted, with a warning, to be fitted again)."""
    if not path.is_file():
        return None
    try:
        return cls.load(path)
    except CorruptFileError as err:
        warnings.warn(f"the model cache entry is corrupt, fitting the model again: {err}", stacklevel=3)
        path.unlink()
        return None


#: a fit's state while it runs, in its cache folder (models.SupervisedTrainer's ``checkpoint``): a killed fit resumes from it
FIT_STATE = "{part}.fit-state.pt"


def fit_or_load_models(
    cfg: Mapping, data: OfflineDataset, progress: bool = True, with_cvae: bool = True
) -> tuple[DynamicsEnsemble, ConditionalVAE | None, dict]:
    """Fit the ensemble and the CVAE on ``data``, or load them from the cache.

    Checkpoints live in ``cache_dir()/models/<key>/`` where the key hashes the
    dataset's content (:meth:`~torchrl_offhrl.data.OfflineDataset.content_hash`)
    and the model and fit configs: change either and the models are fitted
    again (a file replaced by other data at the same path is reported). While
    a model is fitted its state is kept there too (:data:`FIT_STATE`, every two
    minutes): the same call after a kill or a lost session resumes the fit
    where it was, to the weights it would have had. Returns ``(ensemble, cvae, info)``;
    ``with_cvae=False`` fits (or loads) the ensemble alone and returns ``None`` for the CVAE (a later call fits
    it into the same folder). ``cfg["fit_threads"]`` (optional; None: torch's count) is the torch thread count while
    they are fitted, restored afterwards.
    """
    with threads(cfg.get("fit_threads")):
        return _fit_or_load_models(cfg, data, progress, with_cvae)


def _as_before(cfg: Mapping, section: str) -> dict:
    """A model's config as its cache key reads it: :func:`~torchrl_offhrl.recipes.config.fit_as_before` (``rel_tol`` 0 left out),
    and each key added later left out while it holds the value that reproduces the entries made before it existed
    (:data:`~torchrl_offhrl.recipes.config.LATER_DEFAULTS`, which the run fingerprint reads too)."""
    model_cfg, later = fit_as_before(to_plain(cfg[section])), LATER_DEFAULTS.get(section, {})
    return {k: v for k, v in model_cfg.items() if not (k in later and v == later[k])}


def _fit_or_load_models(cfg: Mapping, data: OfflineDataset, progress: bool, with_cvae: bool) -> tuple:
    device = torch.device(cfg.get("device", "cpu"))
    ecfg, ccfg = _as_before(cfg, "ensemble"), _as_before(cfg, "cvae")
    ident = {
        "data": data.content_hash(),  # the content, not the path: a file replaced by other data gets new models
        "ensemble": ecfg,
        "cvae": ccfg,
        "val_ratio": cfg["dataset"].get("val_ratio", 0.1),
        "seed": cfg["seed"],
    }
    remove_stale_tmp(cache_dir() / "models")  # left by saves that were killed
    folder = cache_dir() / "models" / _digest(ident)
    info = {"model_dir": str(folder)}
    e_path, c_path = folder / "ensemble.pt", folder / "cvae.pt"
    source = data.metadata.get("source")
    if not (e_path.is_file() and (c_path.is_file() or not with_cvae)):
        stale = _entries_for_other_data(source, ident)
        if stale:
            print(f"the data at {source} is not what the cached models {', '.join(map(str, stale))} were fitted on "
                  f"(content hash {ident['data']} now): fitting models for it")
    val_ratio = cfg["dataset"].get("val_ratio", 0.1)
    torch.manual_seed(cfg["seed"])
    ensemble = load_cached(DynamicsEnsemble, e_path)
    shared = None if ensemble is not None else _same_model_elsewhere(ident, folder, "ensemble")
    if shared is not None and (ensemble := load_cached(DynamicsEnsemble, shared)) is not None:
        ensemble.save(e_path)  # each entry holds its own copy: deleting the other leaves this one whole
        info["ensemble"] = f"loaded from {shared.parent.name} (fitted with other CVAE settings)"
    if ensemble is not None:
        info.setdefault("ensemble", "loaded")
    else:
        ensemble = DynamicsEnsemble.for_dataset(
            data, num_models=ecfg["num_models"], hidden_sizes=ecfg["hidden_sizes"], loss=ecfg["loss"], learn_reward=ecfg.get("learn_reward", True),
            reward_hidden_sizes=ecfg.get("reward_hidden_sizes"), num_elites=ecfg.get("num_elites"),
        ).to(device)
        ensemble.fit(data, val_ratio=val_ratio, split_seed=cfg["seed"], progress=progress, seed=cfg["seed"], **ecfg["fit"],
                     checkpoint=folder / FIT_STATE.format(part="ensemble"))
        ensemble.save(e_path)
        info["ensemble"] = "fitted"
        info["ensemble_history"] = ensemble.training_history
    cvae = load_cached(ConditionalVAE, c_path) if with_cvae else None
    if not with_cvae:
        info["cvae"] = "not asked for"
    elif cvae is not None:
        info["cvae"] = "loaded"
    elif (shared := _same_model_elsewhere(ident, folder, "cvae")) is not None and (cvae := load_cached(ConditionalVAE, shared)) is not None:
        cvae.save(c_path)
        info["cvae"] = f"loaded from {shared.parent.name} (fitted with other ensemble settings)"
    else:
        cvae = ConditionalVAE.for_dataset(data, goal_key=ccfg.get("goal_key"), hidden_sizes=ccfg["hidden_sizes"], kl_weight=ccfg["kl_weight"]).to(device)
        cvae.fit(data, val_ratio=val_ratio, split_seed=cfg["seed"], progress=progress, seed=cfg["seed"], **ccfg["fit"],
                 checkpoint=folder / FIT_STATE.format(part="cvae"))
        cvae.save(c_path)
        info["cvae"] = "fitted"
        info["cvae_history"] = cvae.training_history
    _record_source(folder / "ident.json", ident, source)
    return ensemble.to(device), (cvae.to(device) if cvae is not None else None), info


#: ``model_env.latent_origin``'s choices
LATENT_ORIGINS = ("best", "behaviour", "zero")
#: the share of the data's transitions ``latent_origin=best`` clones when ``model_env.origin_share`` is not given (a
#: run's config before the key existed): the schema's default, :class:`~torchrl_offhrl.recipes.schema.ModelEnvConfig`
DEFAULT_ORIGIN_SHARE = ModelEnvConfig.origin_share


def origin_share(env: Mapping) -> float | None:
    """The share of the data the latent origin is fitted on for a model env config (None: ``latent_origin=zero``)."""
    mode = env.get("latent_origin", "zero")
    if mode not in LATENT_ORIGINS:
        raise ValueError(f"model_env.latent_origin must be one of {', '.join(LATENT_ORIGINS)}, got {mode!r}")
    return {"best": float(env.get("origin_share", DEFAULT_ORIGIN_SHARE)), "behaviour": 1.0, "zero": None}[mode]


def origin_path(model_dir, share: float) -> Path:
    """Where the latent origin fitted on ``share`` of the data is cached: ``latent_origin.pt`` (all of it) or ``latent_origin_top<share>.pt``."""
    return Path(model_dir) / ("latent_origin.pt" if share >= 1.0 else f"latent_origin_top{share:g}.pt")


def fit_or_load_origin(cfg: Mapping, data: OfflineDataset, cvae: ConditionalVAE, model_dir, progress: bool = True, share: float = 1.0):
    """The :class:`~torchrl_offhrl.models.LatentOrigin` of ``cvae`` on ``data`` (cached beside the CVAE, :func:`origin_path`).

    Fitted when absent, by regression on the CVAE posterior's means of the
    pairs of ``data``'s highest-return episodes that cover ``share`` of it
    (:meth:`~torchrl_offhrl.data.OfflineDataset.top_return_episodes`; 1: all
    of it), with the CVAE's widths, fit settings (to convergence) and episode
    split; its folder is the CVAE's own (``model_dir``: the CVAE and the data
    decide it). Returns ``(origin, info)``, ``info`` the episodes it cloned
    (None when loaded from the cache without the data).
    """
    path = origin_path(model_dir, share)
    info = None
    if data is not None and share < 1.0:
        mask, info = data.top_return_episodes(share)
    origin = load_cached(LatentOrigin, path)
    if origin is not None:
        return origin.to(cvae.decoder.obs_mean.device), info
    if data is None:
        raise FileNotFoundError(f"{path} is missing (or was corrupt) and no dataset was given to fit it again: rerun the training "
                                "command, which fits it beside the CVAE")
    if share < 1.0:
        data = OfflineDataset(data.data[mask], metadata=data.metadata, action_bounds=(data.action_low, data.action_high))
    ccfg = fit_as_before(to_plain(cfg["cvae"]))
    with threads(cfg.get("fit_threads")):
        origin = cvae.fit_origin(data, hidden_sizes=ccfg["hidden_sizes"], val_ratio=cfg["dataset"].get("val_ratio", 0.1), split_seed=cfg["seed"],
                                 progress=progress, seed=cfg["seed"], **ccfg["fit"])
    origin.save(path)
    return origin, info


def apply_latent_origin(cfg: Mapping, data: OfflineDataset, cvae: ConditionalVAE, model_dir, progress: bool = True):
    """Set ``cvae``'s decoder to decode latents relative to ``cfg["env"]["latent_origin"]`` (``model_config`` with its ``env``).

    ``best`` (the default): the :class:`~torchrl_offhrl.models.LatentOrigin`
    fitted on the data's highest-return episodes covering ``origin_share``
    (default 0.1) of its transitions; ``behaviour``: fitted on all of the
    data (:func:`fit_or_load_origin`). Shifted latents are clamped to the
    env's ``latent_bound``: an agent's latent 0 decodes to the chosen data's
    action at each state, so an untrained agent starts as a behaviour cloner
    of those episodes. ``zero`` (the paper): latents are decoded as they are.
    Returns ``(origin, info)`` (``(None, None)`` for ``zero``).
    """
    env = cfg.get("env") or {}
    share = origin_share(env)
    if share is None:
        cvae.decoder.set_origin(None)
        return None, None
    if model_dir is None:
        raise ValueError(f"model_env.latent_origin={env.get('latent_origin')} is fitted beside the CVAE in the model cache: the run's model folder is unknown")
    origin, info = fit_or_load_origin(cfg, data, cvae, model_dir, progress=progress, share=share)
    cvae.decoder.set_origin(origin, float(env.get("latent_bound", DEFAULT_LATENT_BOUND)))
    return origin, info


#: the ``cfg["env"]`` keys :func:`make_model_env` hands to the model env's constructor when they are set
MODEL_ENV_KEYS = ("penalty", "reward_penalty", "discrepancy", "quantile", "fraction", "horizon", "member_mode", "sample", "reset_states")


def make_model_env(
    cfg: Mapping,
    ensemble: DynamicsEnsemble,
    cvae: ConditionalVAE | None,
    data: OfflineDataset,
    batch_size: int | None = None,
    latent: bool = True,
    threshold: float | None = None,
    reset_states: str | None = None,
    member_draw: str = "random",
    horizon: int | None = None,
    member_mode: str | None = None,
    sample: bool | None = None,
) -> TransformedEnv:
    """``TransformedEnv(PessimisticModelEnv(...), LatentActionTransform(...))``.

    ``latent=False`` (the paper's "no CVAE" ablation, and transfer) leaves the
    agent acting in real actions. ``threshold`` overrides ``cfg.env.threshold``:
    pass an env's calibrated ``base_env.threshold`` to build more envs (e.g. for
    evaluation) without scoring the dataset again. ``reset_states`` overrides
    ``cfg.env.reset_states`` (``"initial"``, the default: episodes start where
    the data's episodes start; ``"any"``: at any dataset state).
    ``member_draw="cyclic"`` gives env ``i`` member ``i % K`` (evaluations).
    ``horizon`` overrides ``cfg.env.horizon`` (evaluations run real-episode lengths); ``member_mode`` and ``sample``
    override ``cfg.env``'s (evaluations: one member per episode, its mean).
    """
    env_cfg = cfg["env"]
    if threshold is None:
        threshold = env_cfg.get("threshold")
    stacking = task_of(data.env_id).goal_conditioned  # goal-conditioned: the tasks' goals and rewards on the predicted states
    # the keys the config gives; the rest keep PessimisticModelEnv's own defaults (declared there, once)
    given = {key: env_cfg[key] for key in MODEL_ENV_KEYS if key in env_cfg}
    given.update({key: value for key, value in (("horizon", horizon), ("reset_states", reset_states), ("member_mode", member_mode)) if value})
    if sample is not None:
        given["sample"] = bool(sample)
    if "horizon" in given:
        given["horizon"] = int(given["horizon"])
    base = (BlockStackModelEnv if stacking else PessimisticModelEnv)(
        ensemble, data, threshold=threshold, member_draw=member_draw, batch_size=[] if batch_size is None else [batch_size],
        device=cfg.get("device", "cpu"), seed=cfg.get("seed"), **given,
    )
    if not latent:
        return TransformedEnv(base, SubGoalTracker()) if stacking else TransformedEnv(base)
    if cvae is None:
        raise ValueError("latent=True needs a fitted ConditionalVAE.")
    # the transform as the env's own transform (not in a Compose): the decoded
    # action is then kept in every stepping style, hand-written loops included
    latent_t = LatentActionTransform(cvae.decoder, latent_bound=env_cfg.get("latent_bound", DEFAULT_LATENT_BOUND), goal_key=cvae.goal_key)
    if stacking:  # the decoder's goal: the option's sub-goal, tracked along the goal's abstract demonstration
        return TransformedEnv(base, Compose(SubGoalTracker(), latent_t))
    return TransformedEnv(base, latent_t)


def make_eval_model_env(cfg: Mapping, ensemble: DynamicsEnsemble, cvae: ConditionalVAE | None, data: OfflineDataset, episodes: int,
                        max_steps: int, threshold: float, latent: bool = True) -> TransformedEnv:
    """The model env of the evaluations (:func:`make_model_env`): ``episodes`` episodes of ``max_steps`` steps from the data's
    start states, member ``i % K`` for episode ``i``. Two policies evaluated in envs built alike with the same seed start
    every episode from the same state under the same member, so their returns pair up (the guard's comparisons: the
    agent, its start and the percentile BC, in latent or real actions). Whatever training uses, each episode keeps its
    member and steps with its mean (``member_mode="episode"``, ``sample=False``): the guard's bound is per member."""
    return make_model_env(cfg, ensemble, cvae, data, batch_size=int(episodes), latent=latent, threshold=threshold, reset_states="initial",
                          member_draw="cyclic", horizon=int(max_steps), member_mode="episode", sample=False)


def make_real_env(env_id: str, cvae: ConditionalVAE | None = None, num_envs: int = 1, latent_bound: float = DEFAULT_LATENT_BOUND, device="cpu",
                  task: str = "forward", discard_decoder: bool = False, **gym_kwargs):
    """The real Gymnasium env (batched, float32) of ``task`` (:data:`~torchrl_offhrl.envs.TASKS`), through the decoder when ``cvae`` is given.

    ``discard_decoder=True`` (transfer fine-tuning) keeps the latent action
    space but maps it onto the action box with
    :class:`~torchrl_offhrl.envs.AffineActionMap` instead of the decoder
    (``cvae`` is then not used).
    """
    env = make_task_env(env_id, task, num_envs=num_envs, device=device, **gym_kwargs)
    if task_of(env_id).goal_conditioned:
        env.append_transform(SubGoalTracker())
    if discard_decoder:
        _, low, high = action_box(env, "action")
        env.append_transform(LatentActionTransform(AffineActionMap(latent_bound, low, high).to(device), latent_bound=latent_bound))
    elif cvae is not None:
        env.append_transform(LatentActionTransform(cvae.decoder, latent_bound=latent_bound, goal_key=cvae.goal_key))
    return env


class GaussianLatentPolicy(torch.nn.Module):
    """Writes ``latent_action ~ N(0, scale^2 I)``: the CVAE prior as a policy.

    Decoded, it acts like the behaviour policy; a reference point for model
    rollouts and a sanity check of the composed env.
    """

    def __init__(self, latent_dim: int, scale: float = 1.0, key: str = "latent_action"):
        super().__init__()
        self.latent_dim = latent_dim
        self.scale = scale
        self.key = key

    def forward(self, tensordict):
        obs = tensordict.get("observation")
        z = torch.randn(*obs.shape[:-1], self.latent_dim, device=obs.device) * self.scale
        return tensordict.set(self.key, z)
