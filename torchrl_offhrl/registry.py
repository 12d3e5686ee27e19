"""The envs, tasks and dataset levels the project knows by name (below every other layer).

The task registry (:data:`TASKS`, :func:`task_of`) is the one place that
says what kind of task an env is: a Markov *locomotion* task (Hopper,
HalfCheetah, and any other Gymnasium id, read as one), or a goal-conditioned
*stacking* task with its number of blocks. Code asks ``task_of(env_id)``
instead of testing ids against lists.

Reference scores live in :mod:`torchrl_offhrl.scores`, the tasks' terminal
states (where the model env ends episodes) in :mod:`torchrl_offhrl.envs.tasks`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["ENV_IDS", "LEVELS", "TASKS", "Task", "resolve_env", "stacking_tasks", "task_of"]


@dataclass(frozen=True)
class Task:
    """What kind of task an env is.

    ``family``: ``"locomotion"`` (a Markov task scored by its return, D4RL's
    normalisation where defined) or ``"stacking"`` (goal-conditioned block
    stacking: per-goal success, agents conditioned on the sub-goal, episodes of
    ``horizon`` steps); ``n_blocks``: the blocks of a stacking task (0 otherwise);
    ``terminates``: whether an episode can end before its time limit (Hopper
    falls; HalfCheetah's episodes always run to the limit).
    """

    env_id: str
    short: str
    family: str = "locomotion"
    n_blocks: int = 0
    terminates: bool = True

    @property
    def goal_conditioned(self) -> bool:
        """Whether the task has goals (the block-stacking tasks)."""
        return self.family == "stacking"


#: Every task the project ships, by Gymnasium id.
TASKS: dict[str, Task] = {t.env_id: t for t in (
    Task("Hopper-v5", "hopper"),
    Task("HalfCheetah-v5", "halfcheetah", terminates=False),
    Task("BlockStack2-v0", "blockstack2", "stacking", 2),
    Task("BlockStack3-v0", "blockstack3", "stacking", 3),
)}


#: Short dataset names of the envs and their Gymnasium ids (the registry's tasks).
ENV_IDS: dict[str, str] = {t.short: env_id for env_id, t in TASKS.items()}
#: Dataset levels of D4RL's protocol.
LEVELS = ("random", "medium", "expert", "medium-expert")


def resolve_env(env_id_or_short: str) -> tuple[str, str]:
    """``(env_id, short)`` for a short name (``"hopper"``) or a full Gymnasium id (``"Hopper-v5"``).

    Examples:
        >>> resolve_env("hopper")
        ('Hopper-v5', 'hopper')
        >>> resolve_env("HalfCheetah-v5")
        ('HalfCheetah-v5', 'halfcheetah')
    """
    key = env_id_or_short.lower()
    if key in ENV_IDS:
        return ENV_IDS[key], key
    m = re.match(r"^(?:.*/)?([A-Za-z0-9_]+)-v\d+$", env_id_or_short)
    if m:
        return env_id_or_short, m.group(1).lower()
    raise ValueError(
        f"{env_id_or_short!r}: not a known short name {sorted(ENV_IDS)} nor a Gymnasium id "
        f"like 'Hopper-v5'."
    )


def task_of(env: str | None) -> Task:
    """The :class:`Task` of a Gymnasium id or short name; an id the project does not ship is a locomotion task.

    Examples:
        >>> task_of("blockstack3").n_blocks, task_of("BlockStack3-v0").goal_conditioned
        (3, True)
        >>> task_of("Walker2d-v5")
        Task(env_id='Walker2d-v5', short='walker2d', family='locomotion', n_blocks=0, terminates=True)
    """
    if env is None:
        return Task("", "")
    try:
        env_id, short = resolve_env(env)
    except ValueError:  # a name that is no Gymnasium id (e.g. a toy dataset's): a task without goals
        return Task(str(env), str(env).lower())
    return TASKS.get(env_id) or Task(env_id, short)


def stacking_tasks() -> dict[str, Task]:
    """The goal-conditioned block-stacking tasks, by Gymnasium id."""
    return {k: t for k, t in TASKS.items() if t.goal_conditioned}
