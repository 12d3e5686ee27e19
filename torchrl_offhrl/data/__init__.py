"""Offline data: loading, writing, normalisation statistics, splits, collection, generation, the named dataset cache."""
from .collect import collect_dataset, make_gym_env
from .dataset import DatasetError, NormalizationStats, OfflineDataset, make_toy_dataset
from .catalog import named_dataset
from .generate import SampledPolicy, generate_dataset
from .io import export_minari, load_dataset, save_dataset
from .policies import PolicyNotFoundError, list_policies, load_policy, ship_policy

__all__ = [
    "DatasetError",
    "NormalizationStats",
    "OfflineDataset",
    "PolicyNotFoundError",
    "SampledPolicy",
    "collect_dataset",
    "export_minari",
    "generate_dataset",
    "list_policies",
    "load_dataset",
    "load_policy",
    "make_gym_env",
    "make_toy_dataset",
    "named_dataset",
    "save_dataset",
    "ship_policy",
]
