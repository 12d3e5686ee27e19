"""torchrl_offhrl: offline hierarchical reinforcement learning as TorchRL components."""
from importlib.metadata import PackageNotFoundError, version as _dist_version

try:  # one source of truth: pyproject.toml's version, as installed
    __version__ = _dist_version("torchrl-offhrl")
except PackageNotFoundError:  # a source tree on sys.path without an install
    __version__ = "0+unknown"
