"""Where the results presets read and write: a checkout of this repository.

The presets write the pages under ``docs/results/`` of a checkout and the runs
under its ``outputs/``. The checkout is the one this package was installed
from in editable mode (``make install``), else the current directory, else
``$TORCHRL_OFFHRL_ROOT`` when set (it wins over both).
"""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["ROOT", "repo_root", "require_checkout"]


def repo_root() -> Path:
    """The checkout the presets work in (see the module's docstring)."""
    if os.environ.get("TORCHRL_OFFHRL_ROOT"):
        return Path(os.environ["TORCHRL_OFFHRL_ROOT"]).resolve()
    source = Path(__file__).resolve().parents[2]
    if (source / "docs" / "results").is_dir():
        return source
    return Path.cwd().resolve()


#: the checkout, resolved when the package is imported
ROOT = repo_root()


def require_checkout(root: Path = ROOT) -> Path:
    """``root`` if it holds ``docs/results/``; else a ``FileNotFoundError`` that says what to do."""
    if not (root / "docs" / "results").is_dir():
        raise FileNotFoundError(
            f"offhrl results works in a checkout of torchrl_offhrl (it writes docs/results/ and outputs/), and {root} has no "
            "docs/results/: run it from the repository root, install the checkout with `pip install -e .`, or set TORCHRL_OFFHRL_ROOT")
    return root
