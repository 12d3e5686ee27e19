"""The guard's second fallback: a percentile behaviour cloner of the run's best episodes, fitted and evaluated at the run's end.

A run's start (``model_env.latent_origin=best``) clones the data's
highest-return episodes through the CVAE decoder. A plain regression of the
same episodes' actions (:class:`~torchrl_offhrl.models.PercentileBC`) is
another cloner of them, and on half of the design datasets a much better one
in the real env (``experiments/diagnostics/start_quality.py``). With
``selection.fallback: bc_unless_start`` (the default) a fired guard returns
this cloner unless the model's own paired comparison shows the start above
it (:meth:`~torchrl_offhrl.recipes.selection.PolicySelector.verdict`). This
module fits the cloner (one per run seed, cached beside the CVAE:
:func:`bc_path`) and
evaluates it as the run evaluates its agent: the same real-env episodes and
the same model episodes (the same start states under the same member, in
real actions), so its model episodes pair up with the start's.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping

import torch

from ..data import OfflineDataset
from ..models import ClonedPolicy, PercentileBC
from ..utils import threads
from .pipeline import load_cached, make_eval_model_env, make_real_env

__all__ = ["bc_path", "evaluate_fallback", "fit_or_load_bc"]


def bc_path(model_dir, share: float, seed: int) -> Path:
    """Where the percentile BC of ``share`` of the data fitted with ``seed`` is cached: ``percentile_bc_top<share>_seed<seed>.pt``
    beside the CVAE.

    The seed is in the name because the cloner is a policy the run returns: runs of different seeds must return
    independently fitted cloners, or a table's seeds would score one network several times and its confidence interval
    would measure only the evaluation's noise.
    """
    return Path(model_dir) / f"percentile_bc_top{share:g}_seed{int(seed)}.pt"


def fit_or_load_bc(cfg: Mapping, data: OfflineDataset, model_dir, share: float, seed: int, progress: bool = True) -> PercentileBC:
    """The :class:`~torchrl_offhrl.models.PercentileBC` of the highest-return episodes covering ``share`` of ``data``.

    Fitted when absent (its own fit settings, :attr:`~torchrl_offhrl.models.PercentileBC.default_fit`: to convergence on
    held-out episodes; the episode split, the initialisation and the batches drawn from ``seed``, the run's seed) and cached
    per seed in the CVAE's folder ``model_dir`` (:func:`bc_path`). ``cfg`` is the models' config
    (:func:`~torchrl_offhrl.recipes.config.model_config`: the validation share, the fit threads); its own ``seed`` is the
    dataset's, shared by every run on the data, which is why the run's seed is passed apart.
    """
    seed = int(seed)
    path = bc_path(model_dir, share, seed) if model_dir is not None else None
    bc = load_cached(PercentileBC, path) if path is not None else None
    if bc is not None:
        return bc
    mask, _ = data.top_return_episodes(share)
    best = OfflineDataset(data.data[mask], metadata=data.metadata, action_bounds=(data.action_low, data.action_high))
    val_ratio = float((cfg.get("dataset") if isinstance(cfg.get("dataset"), Mapping) else {}).get("val_ratio", 0.1))
    # at most 1,000 passes over the training transitions (at least one check): small data converges in few steps, and
    # its held-out error, a handful of pairs, can creep down for ever (the design data's fits stopped after 7,500-14,500
    # steps, well inside this bound)
    fit = PercentileBC.default_fit
    n_train = max(1, int(len(best) * (1 - val_ratio)))
    max_steps = max(int(fit["steps_per_epoch"]), -(-1000 * n_train // int(fit["batch_size"])))
    with threads(cfg.get("fit_threads")):
        bc = PercentileBC.for_dataset(best).fit(best, val_ratio=val_ratio, split_seed=seed, progress=progress, seed=seed,
                                                max_steps=max_steps)
    bc.eval()
    if path is not None:
        bc.save(path)
    return bc


def evaluate_fallback(bc: PercentileBC, env_id: str, episodes: int, max_steps: int, seed: int, pcfg: Mapping, ensemble, data, threshold: float,
                      model_episodes: int | None = None, ref=None, gamma: float = 0.99, device="cpu") -> dict:
    """The evaluation record of ``bc`` as the run's :class:`~torchrl_offhrl.recipes.evaluation.Evaluator` records its agent's:
    ``episodes`` real-env episodes from ``seed``, and ``model_episodes`` model episodes (None: none) of ``max_steps`` steps
    from the same start states under the same members as the agent's (:func:`~torchrl_offhrl.recipes.pipeline.make_eval_model_env`,
    the same seed), in real actions: its ``model_episode_returns`` pair up with the start's."""
    from .evaluation import Evaluator

    policy = ClonedPolicy(bc.to(device))
    real = make_real_env(env_id, None, num_envs=episodes, device=device)
    model = None
    if model_episodes:
        model = make_eval_model_env(pcfg, ensemble, None, data, model_episodes, max_steps, threshold, latent=False)
    ev = Evaluator(real, env_id, episodes, max_steps, seed=seed, ref=ref, model_env=model, gamma=gamma)
    try:
        with torch.no_grad():
            return ev(policy)
    finally:
        real.close()
