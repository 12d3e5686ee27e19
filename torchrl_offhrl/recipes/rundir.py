"""A run directory: the resolved config, the checkpoint an interrupted run resumes from, the evaluation records and the logs.

Layout (``outputs/runs/<algo>-<env>-<dataset>-seed<seed>/``): ``config.json``,
``checkpoint.pt`` (the agent's state, frame and update counters, evaluation
records, RNG state, the offline policy selection's state, the config fingerprint and, for agents with a replay
buffer, the name of the ``replay-<frames>/`` folder saved with it),
``evals.json``, ``logs/`` (TorchRL logger) and whatever the report writes.
Every file is written atomically; a replay folder is written before the
checkpoint that names it and the previous one deleted only after. The
checkpoint before the last is kept as ``checkpoint.prev.pt``: a damaged
``checkpoint.pt`` is reported and the run resumes from it instead (agents
without a replay buffer; an off-policy agent's previous buffer is not kept,
so its fallback stops with the missing buffer named).
"""
from __future__ import annotations

import contextlib
import os
import re
import shutil
import warnings
from pathlib import Path

import torch

from ..utils import CorruptFileError, atomic_write, checksum_path, load_torch_file, save_torch_file, write_json
from .config import RESUMABLE_KEYS, fingerprints_match

__all__ = ["RunDirectory", "RunInUseError", "trim_csv_logs"]


class RunInUseError(RuntimeError):
    """A run directory another live run holds (its ``.lock``): the CLI says so in one line."""


class RunDirectory:
    """Checkpoints and records of one training run (see the module docstring for the layout).

    Args:
        path: the run directory (created).
        fingerprint: the config's :func:`~torchrl_offhrl.recipes.config.config_fingerprint`;
            a checkpoint written under another one is refused on :meth:`resume`.
    """

    def __init__(self, path, fingerprint: str):
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        self.fingerprint = fingerprint
        self.checkpoint_path = self.path / "checkpoint.pt"
        self.previous_path = self.path / "checkpoint.prev.pt"
        self.data_hash: str | None = None  # the training data's content hash: set it before resume() to check it
        self.frames = 0
        self.updates = 0
        self.unit = "frames"  # what the run's budget counts: "frames" (collected) or "updates" (gradient steps, dataset agents)
        self.records: list[dict] = []
        self.selector = None  # a PolicySelector: its state (the selected policy) is checkpointed with the run
        self.resume_state = None  # after resume(): the RNG and batch-source state to set on the first source
        self._replay: str | None = None

    @property
    def step(self) -> int:
        """The run's progress in its :attr:`unit`: the x-axis of its logs and curves."""
        return self.updates if self.unit == "updates" else self.frames

    def remove_if_empty(self) -> bool:
        """Delete the directory if it holds nothing but its lock file (a run that failed before writing); True if deleted."""
        try:
            if {p.name for p in self.path.iterdir()} <= {".lock"}:
                shutil.rmtree(self.path)
                return True
        except OSError:
            pass
        return False

    @contextlib.contextmanager
    def locked(self):
        """Hold an exclusive lock on the directory (``.lock``) while the block runs; refuse if another run holds it.

        An OS file lock (``flock``): the OS releases it when its process dies,
        so a killed run never blocks the next one. Where ``fcntl`` is missing
        (Windows) the block runs unlocked.
        """
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX
            yield self
            return
        fd = os.open(self.path / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "another process"
                raise RunInUseError(
                    f"{self.path} is in use by a run that is still going (pid {holder}): two runs in one run_dir would "
                    "interleave their checkpoints and logs. Wait for it to finish, or give another run_dir=."
                ) from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
            try:
                yield self
            finally:
                os.ftruncate(fd, 0)
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def resume(self, agent, device="cpu") -> bool:
        """Load the checkpoint into ``agent`` (and its replay buffer) and the counters; False when there is none."""
        if not self.checkpoint_path.is_file():
            return False
        try:
            state = load_torch_file(self.checkpoint_path, "run checkpoint", f"delete it to start over (or restore {self.previous_path.name})",
                                    map_location=device)
        except CorruptFileError as err:
            if not self.previous_path.is_file():
                raise
            warnings.warn(f"{err}; resuming from the checkpoint before it, {self.previous_path}", stacklevel=2)
            state = load_torch_file(self.previous_path, "previous run checkpoint", f"delete it and {self.checkpoint_path.name} to start over",
                                    map_location=device)
        if not fingerprints_match(state.get("fingerprint"), self.fingerprint):
            raise ValueError(
                f"{self.path} holds a checkpoint of a run with a different configuration (only {', '.join(RESUMABLE_KEYS)} "
                f"may change when resuming); give another run_dir= or out_root=, or delete {self.checkpoint_path} to start over"
            )
        saved_data = state.get("data_hash")
        if None not in (saved_data, self.data_hash) and saved_data != self.data_hash:
            raise ValueError(
                f"{self.path} holds a run trained on other data (content hash {saved_data}; the dataset given now has {self.data_hash}): "
                f"the file was replaced or changed. Give another run_dir=, or restore the data the run was trained on"
            )
        agent.load_state_dict(state["agent"])
        self.frames, self.updates, self.records = int(state["frames"]), int(state["updates"]), list(state["records"])
        if self.selector is not None:
            self.selector.load_state_dict(state.get("selection"))
        torch.set_rng_state(state["rng"])
        # the batch source's state and the RNG as they were at the checkpoint: set again on the new source, right before
        # its first batch (TrainingLoop.run_phase), so that a resumed run draws what the uninterrupted one drew
        self.resume_state = {"rng": state["rng"], "source": state.get("source")}
        replay = state.get("replay")
        if replay is not None and not (isinstance(replay, str) and re.fullmatch(r"replay-\d+", replay)):
            # the name is later joined to the run directory and removed with rmtree: never outside it
            raise ValueError(f"{self.checkpoint_path} names its replay buffer {replay!r}, not a replay-<frames> folder of the run; "
                             "the checkpoint is corrupt or was not written by `offhrl train`: delete it to start over")
        self._replay = replay
        if agent.replay_buffer is not None and self._replay is not None:
            if not (self.path / self._replay).is_dir():
                raise FileNotFoundError(f"the checkpoint's replay buffer {self.path / self._replay} is missing; delete {self.checkpoint_path} to start over")
            agent.replay_buffer.loads(self.path / self._replay)
        print(f"resuming {self.path} from its checkpoint at {self.step} {self.unit}")
        return True

    def write_json(self, name: str, obj) -> Path:
        """A record of the run, written atomically with its checksum (:func:`~torchrl_offhrl.utils.write_json`)."""
        return write_json(self.path / name, obj)

    def checkpoint(self, agent, source: dict | None = None) -> None:
        """Save the agent, its replay buffer (if any and not empty), the counters, the records, the RNG state and the batch
        source's state (``source``: :func:`~torchrl_offhrl.recipes.loop.source_state`, the envs where they stand)."""
        new_replay = None
        rb = agent.replay_buffer
        if rb is not None and len(rb):  # an empty buffer (the evaluation before training) has nothing to save
            new_replay = f"replay-{self.frames}"
            shutil.rmtree(self.path / new_replay, ignore_errors=True)
            rb.dumps(self.path / new_replay)
        state = {
            "agent": agent.state_dict(), "frames": self.frames, "updates": self.updates, "records": self.records,
            "rng": torch.get_rng_state(), "replay": new_replay, "fingerprint": self.fingerprint, "data_hash": self.data_hash,
            "selection": None if self.selector is None else self.selector.state_dict(), "source": source,
        }
        if self.checkpoint_path.is_file():  # the one before stays, for a checkpoint damaged later (resume falls back to it)
            # with the checksum it was written with (not one of its bytes now: a checkpoint damaged since stays damaged)
            for src, dst in ((self.checkpoint_path, self.previous_path), (checksum_path(self.checkpoint_path), checksum_path(self.previous_path))):
                if src.is_file():
                    with atomic_write(dst) as tmp:
                        shutil.copyfile(src, tmp)
        save_torch_file(state, self.checkpoint_path)  # with its checksum, checked on resume
        write_json(self.path / "evals.json", self.records, indent=1)
        if self._replay is not None and self._replay != new_replay:  # one buffer on disk: the previous checkpoint
            shutil.rmtree(self.path / self._replay, ignore_errors=True)  # keeps the agent, not its (large) buffer
        self._replay = new_replay

    def logger(self, backend: str | None, **kwargs):
        """A TorchRL logger writing under ``logs/`` (None without a backend).

        On resume, what was logged after the checkpoint is not repeated: CSV
        rows after it are dropped; TensorBoard gets a writer with
        ``purge_step`` (its readers discard the older events from that step
        on). W&B keeps its own step counter and is left as it is.
        """
        if not backend:
            return None
        from torchrl.record.loggers import get_logger

        if self.step and backend == "csv":
            trim_csv_logs(self.path / "logs", self.step)
        logger = get_logger(backend, logger_name=str(self.path), experiment_name="logs", **kwargs)
        if self.frames and backend == "tensorboard":
            from torch.utils.tensorboard import SummaryWriter

            log_dir = logger.experiment.log_dir
            logger.experiment.close()
            logger.experiment = SummaryWriter(log_dir=log_dir, purge_step=self.step + 1)
        return logger


def trim_csv_logs(log_dir: Path, max_step: int) -> int:
    """Drop the rows of TorchRL CSV logs (``step,value`` lines) logged after ``max_step``.

    A resumed run restarts from its checkpoint, so the steps it logged between
    that checkpoint and the interruption would otherwise appear twice.
    Returns the number of rows dropped. Each file is rewritten atomically.
    """
    dropped = 0
    for csv in sorted(Path(log_dir).glob("**/*.csv")):
        lines = csv.read_text().splitlines()
        keep = [line for line in lines if not line or float(line.split(",", 1)[0]) <= max_step]
        if len(keep) != len(lines):
            dropped += len(lines) - len(keep)
            with atomic_write(csv) as tmp:
                Path(tmp).write_text("".join(line + "\n" for line in keep))
    return dropped
