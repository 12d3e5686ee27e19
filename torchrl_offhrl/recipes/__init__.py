"""Recipes: the algorithm-agnostic training loop and what it is built from.

* :mod:`.config`: hydra composition, dataset resolution, model and P-MDP settings, run naming;
* :mod:`.pipeline`: fitted (cached) models, the composed model env, the real env;
* :mod:`.evaluation`: real-env evaluation during training and of saved runs;
* :mod:`.rundir`: checkpoints, resumption, records and logs of a run;
* :mod:`.report`: summaries, learning curves, multi-seed aggregation;
* :mod:`.train`: ``train(cfg)``, the run read top to bottom, and what it is made of (one builder per setting);
* :mod:`.loop`: the one training loop, and where its batches come from (a collector on an env, or the dataset);
* :mod:`.demo`: the embedded demo.

``from torchrl_offhrl.recipes.train import train`` (not re-exported here: the
function would shadow its module).
"""
from .config import compose, resolve_dataset
from .pipeline import (
    GaussianLatentPolicy,
    fit_or_load_models,
    make_model_env,
    make_real_env,
)

__all__ = ["GaussianLatentPolicy", "compose", "fit_or_load_models", "make_model_env", "make_real_env", "resolve_dataset"]
