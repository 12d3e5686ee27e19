"""Tasks of the transfer setting: the same MuJoCo body, another reward (e.g. running backwards).

The paper's transfer setting (Section "Transfer setting") trains offline on
data of the forward-running task, then fine-tunes online on a task that
rewards running *backwards*. Gymnasium's v5 locomotion envs expose the
weight of the forward-velocity term of their reward
(``forward_reward_weight``), so a task is a set of ``gymnasium.make``
keyword arguments: ``backward`` flips the sign of that weight, and keeps
its size, the healthy reward and the control cost, so returns of the two
tasks are on the same scale.
"""
from __future__ import annotations

from ..data import make_gym_env

__all__ = ["TASKS", "make_task_env", "task_kwargs"]

#: task name -> ``gymnasium.make`` keyword arguments (Hopper-v5, HalfCheetah-v5, Walker2d-v5, Ant-v5, ...)
TASKS: dict[str, dict] = {
    "forward": {},
    "backward": {"forward_reward_weight": -1.0},
}


def task_kwargs(task: str) -> dict:
    """The ``gymnasium.make`` keyword arguments of a named task.

    Examples:
        >>> task_kwargs("backward")
        {'forward_reward_weight': -1.0}
        >>> task_kwargs("sideways")
        Traceback (most recent call last):
        ...
        ValueError: unknown task 'sideways': the tasks are 'forward', 'backward' (torchrl_offhrl.envs.TASKS)
    """
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}: the tasks are {', '.join(map(repr, TASKS))} (torchrl_offhrl.envs.TASKS)")
    return dict(TASKS[task])


def make_task_env(env_id: str, task: str = "forward", num_envs: int = 1, device="cpu", **gym_kwargs):
    """The batched real env of ``env_id`` with the reward of ``task`` (:func:`~torchrl_offhrl.data.make_gym_env`).

    Raises ``ValueError`` naming the env and the task when the env has no
    such reward weight (e.g. ``backward`` on an env without a
    forward-velocity term).
    """
    kwargs = {**task_kwargs(task), **gym_kwargs}
    try:
        return make_gym_env(env_id, num_envs=num_envs, device=device, **kwargs)
    except TypeError as err:
        if not task_kwargs(task):
            raise
        raise ValueError(f"{env_id} does not take the reward arguments {task_kwargs(task)} of task {task!r} ({err}); "
                         "the locomotion envs of Gymnasium v5 (Hopper-v5, HalfCheetah-v5, Walker2d-v5, Ant-v5) do") from None
