"""Small shared helpers."""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_write", "cache_dir"]


@contextmanager
def atomic_write(path: str | os.PathLike):
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    On any error (or interrupt) the temporary file is removed, so a reader
    never sees a half-written file under the final name.
    """
    path = Path(path).expanduser()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        # mkstemp creates the file private (0600); give it the permissions a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


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
