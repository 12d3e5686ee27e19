"""Small shared helpers."""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_dir"]


def cache_dir() -> Path:
    """Where datasets and fitted models are cached.

    ``$TORCHRL_OFFHRL_CACHE`` when set, else ``$XDG_CACHE_HOME/torchrl_offhrl``
    (``~/.cache/torchrl_offhrl``). Created on first use.
    """
    root = os.environ.get("TORCHRL_OFFHRL_CACHE")
    if root is None:
        root = os.path.join(os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "torchrl_offhrl")
    path = Path(root).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    return path
