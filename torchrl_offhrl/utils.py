"""Small shared helpers."""
from __future__ import annotations

import errno
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

__all__ = ["CorruptFileError", "DiskWriteError", "atomic_write", "cache_dir", "checksum_mismatch", "checksum_path", "file_digest", "load_torch_file", "one_thread", "read_json", "remove_stale_tmp",
           "save_torch_file", "threads", "to_plain", "write_checksum", "write_json"]


class CorruptFileError(ValueError):
    """A file that exists but cannot be read back (truncated, overwritten, not what its name says); the message names it."""


def file_digest(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def checksum_path(path: str | os.PathLike) -> Path:
    """Where the SHA-256 of a file the library writes is kept: ``<name>.sha256`` beside it."""
    path = Path(path)
    return path.with_name(path.name + ".sha256")


def write_checksum(path: str | os.PathLike, digest: str | None = None) -> Path:
    """Write ``path``'s SHA-256 (``digest`` when already computed) beside it, atomically; returns the checksum file."""
    out = checksum_path(path)
    digest = file_digest(path) if digest is None else digest
    with atomic_write(out) as tmp:
        Path(tmp).write_text(digest + "\n")
    return out


def checksum_mismatch(path: str | os.PathLike) -> Path | None:
    """The checksum file of ``path`` when the file's bytes do not match it (damaged after it was written), else None
    (they match, or there is no checksum: a file written elsewhere or before checksums, read as it is)."""
    digest_file = checksum_path(path)
    if not (digest_file.is_file() and Path(path).is_file()):
        return None
    try:
        expected = digest_file.read_text().strip()
    except OSError:
        expected = ""
    return None if file_digest(path) == expected else digest_file


def save_torch_file(obj, path: str | os.PathLike) -> Path:
    """``torch.save`` atomically, with the file's SHA-256 beside it (``<name>.sha256``), which :func:`load_torch_file` checks.

    The digest is written after the file: a process killed in between leaves
    a digest that does not match, which the reader treats as a damaged file
    (a run resumes from its previous checkpoint, a model is fitted again).

    Example:
        >>> import tempfile, pathlib
        >>> p = save_torch_file({"w": 1}, pathlib.Path(tempfile.mkdtemp()) / "m.pt")
        >>> load_torch_file(p, "model", "fit it again"), p.with_name("m.pt.sha256").is_file()
        ({'w': 1}, True)
    """
    import torch

    path = Path(path).expanduser()
    with atomic_write(path) as tmp:
        torch.save(obj, tmp)
        digest = file_digest(tmp)
    write_checksum(path, digest)
    return path


def load_torch_file(path: str | os.PathLike, what: str, fix: str, map_location="cpu"):
    """``torch.load(path, weights_only=True)``, with a one-line :class:`CorruptFileError` naming ``path`` and ``fix`` when it cannot be read.

    A file written by :func:`save_torch_file` is checked against its SHA-256
    first: a flipped byte that ``torch.load`` would read without complaint
    (a weight of 1e37) is refused the same way. Any error of the reader, not
    only the known ones, is reported as a damaged file.

    Example:
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "model.pt"
        >>> _ = p.write_bytes(b"not a checkpoint")
        >>> load_torch_file(p, "checkpoint", "delete it")
        Traceback (most recent call last):
        ...
        torchrl_offhrl.utils.CorruptFileError: .../model.pt: the checkpoint is corrupt or truncated (...); delete it
    """
    import torch

    digest_file = checksum_mismatch(path)
    if digest_file is not None:
        raise CorruptFileError(f"{path}: the {what} is corrupt or truncated (its bytes do not match its checksum, {digest_file.name}: "
                               f"damaged after it was written); {fix}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as err:  # any reader error (RuntimeError, EOFError, UnpicklingError, struct.error, ...): a damaged file
        reason = str(err).splitlines()[0][:200] if str(err) else type(err).__name__
        raise CorruptFileError(f"{path}: the {what} is corrupt or truncated ({reason}); {fix}") from None


def remove_stale_tmp(folder: str | os.PathLike, max_age_s: float = 3600.0) -> list[Path]:
    """Delete the ``*.tmp`` files :func:`atomic_write` left under ``folder`` when its process was killed; returns them.

    Only files older than ``max_age_s`` go: a younger one may belong to a
    save in progress in another process (a save takes seconds).
    """
    import time

    folder = Path(folder)
    if not folder.is_dir():
        return []
    now, removed = time.time(), []
    for tmp in folder.rglob("*.tmp"):
        try:
            if tmp.is_file() and now - tmp.stat().st_mtime > max_age_s:
                tmp.unlink()
                removed.append(tmp)
        except OSError:  # gone meanwhile, or not ours to remove
            continue
    return removed


class DiskWriteError(OSError):
    """A file the library writes could not be written (a full disk, a read-only or forbidden folder): one line naming the
    folder and what to do (the CLI prints it as it is)."""


#: the errnos of a folder that cannot take a file: full, over quota, read-only, forbidden
DISK_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}


def disk_write_error(err: OSError, path: str | os.PathLike | None = None, folder: str | os.PathLike | None = None) -> DiskWriteError:
    """``err`` (a write that failed) as a :class:`DiskWriteError` naming the file ``path`` and its folder (or only a
    ``folder``: a run folder that could not be made) and the fix."""
    folder = Path(path).expanduser().parent if path is not None else Path(folder if folder is not None else ".")
    try:
        free = f"; {shutil.disk_usage(folder).free / 2**20:.0f} MiB free there"
    except OSError:
        free = ""
    what = err.strerror or (os.strerror(err.errno) if err.errno else str(err))
    target = f"{Path(path).name} in {folder}" if path is not None else f"in {folder}"
    out = DiskWriteError(err.errno or errno.EIO, f"cannot write {target}: {what}{free}. Free space there, make it "
                         "writable, or point out_root= (runs) / $TORCHRL_OFFHRL_CACHE (datasets and models) at a folder that is")
    out.filename = str(folder)
    return out


@contextmanager
def atomic_write(path: str | os.PathLike):
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    On any error (or interrupt) the temporary file is removed, so a reader
    never sees a half-written file under the final name. A folder that cannot
    take the file (full, read-only, forbidden) raises :class:`DiskWriteError`
    naming it, whatever wrote the file.
    """
    path = Path(path).expanduser()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    except OSError as err:
        if err.errno in DISK_ERRNOS:
            raise disk_write_error(err, path) from None
        raise
    os.close(fd)
    try:
        yield tmp
        # mkstemp creates the file private (0600); give it the permissions a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException as err:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(err, OSError) and not isinstance(err, DiskWriteError) and err.errno in DISK_ERRNOS:
            raise disk_write_error(err, path) from None
        if isinstance(err, RuntimeError) and "write" in str(err).lower():  # torch.save's writer on a full disk
            raise disk_write_error(OSError(errno.ENOSPC, str(err)), path) from None
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


@contextmanager
def threads(n: int | None):
    """Run the block on ``n`` torch threads (restored afterwards); ``None`` leaves the count as it is."""
    import torch

    prev = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(prev)


@contextmanager
def one_thread():
    """Run small-batch policy inference on one torch thread (restored afterwards).

    A batch of 8 observations gains nothing from intra-op threads, and on a
    busy 2-core machine two threads made collection 5-8 times slower. One
    thread also makes the numbers independent of the caller's setting.
    """
    with threads(1):
        yield


def to_plain(cfg) -> dict:
    """A plain ``dict`` of a config: an OmegaConf/hydra config resolved and converted, any other mapping copied."""
    try:
        from omegaconf import OmegaConf

        if OmegaConf.is_config(cfg):
            return OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover
        pass
    return dict(cfg)


def import_class(path: str, base: type, key: str) -> type:
    """The class at the dotted ``path`` (``"package.module.Class"``), checked to subclass ``base``; ``key`` names the setting in errors.

    Example:
        >>> import collections
        >>> import_class("collections.OrderedDict", dict, "algo.loss") is collections.OrderedDict
        True
        >>> import_class("collections.OrderedDict", list, "algo.loss")
        Traceback (most recent call last):
        ...
        TypeError: algo.loss='collections.OrderedDict' is not a subclass of list
    """
    import importlib

    module, _, name = str(path).rpartition(".")
    if not module:
        raise ValueError(f"{key}={path!r}: give a dotted path 'package.module.Class'")
    try:
        cls = getattr(importlib.import_module(module), name)
    except ModuleNotFoundError as err:
        raise ValueError(f"{key}={path!r}: cannot import {module!r} ({err}); is the package installed or on PYTHONPATH?") from None
    except AttributeError:
        raise ValueError(f"{key}={path!r}: {module!r} has no {name!r}") from None
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise TypeError(f"{key}={path!r} is not a subclass of {base.__name__}")
    return cls


def write_json(path: Path, obj, indent: int = 2) -> Path:
    """Write a run's JSON record atomically, with its SHA-256 beside it (``<name>.sha256``), which :func:`read_json` checks."""
    path = Path(path)
    with atomic_write(path) as tmp:
        Path(tmp).write_text(json.dumps(obj, indent=indent, default=str))
    write_checksum(path)
    return path


def read_json(path: Path):
    """A run's JSON record (``config.json``, ``summary.json``, ``evals.json``); a damaged one is named in a ``ValueError``:
    not valid JSON, or (a :class:`CorruptFileError`) valid but no longer the bytes the run wrote
    (its ``.sha256``; a record without one, e.g. an archived copy, is read as it is)."""
    path = Path(path)
    digest = checksum_mismatch(path)
    if digest is not None:
        raise CorruptFileError(f"{path} does not match its checksum {digest.name}: it changed after the run wrote it (damaged, or "
                               f"edited by hand); rerun or resume the run to write it again, or delete {digest.name} to read it as it is")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{path} is not valid JSON ({err}): the file is damaged; rerun or resume the run to write it again") from None
