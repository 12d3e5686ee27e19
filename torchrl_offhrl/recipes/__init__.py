"""Builders shared by the examples (datasets, fitted models, composed envs)."""
from .pipeline import (
    GaussianLatentPolicy,
    fit_or_load_models,
    get_dataset,
    make_model_env,
    make_real_env,
)

__all__ = ["GaussianLatentPolicy", "fit_or_load_models", "get_dataset", "make_model_env", "make_real_env"]
