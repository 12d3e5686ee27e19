"""Offline data: loading, writing, normalisation statistics, splits, collection."""
from .collect import collect_dataset, make_gym_env
from .dataset import DatasetError, NormalizationStats, OfflineDataset, make_toy_dataset
from .io import load_dataset, save_dataset

__all__ = [
    "DatasetError",
    "NormalizationStats",
    "OfflineDataset",
    "collect_dataset",
    "load_dataset",
    "make_gym_env",
    "make_toy_dataset",
    "save_dataset",
]
