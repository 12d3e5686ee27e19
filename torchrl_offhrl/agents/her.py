"""Hindsight relabelling of the low-level goal (the sub-goal) for goal-conditioned agents (UOF's low level, SAC + HER).

TorchRL's :class:`~torchrl.data.HERReplayBuffer` does the relabelling; this
module sets it up for the block-stacking tasks: the relabelled goal is
``sub_goal``, taken from an ``("next", "achieved_sub_goal")`` later in the same
segment, and the low level's reward ``("next", "sub_goal_reward")`` is
recomputed with the task's own function
(:func:`torchrl_offhrl.blockstack.goals.sub_goal_reward`: 0 when the achieved
sub-goal at s' is within 2 cm of the goal, else -1), except at a pessimistic
termination of the model env, where it is the env's penalty whatever the goal.
The high level's reward ``("next", "reward")`` is left alone.
Segments are option segments by default, as UOF relabels (a segment ends where
the option's sub-goal is met or the episode ends), or whole episodes
(``per_option=False``, gymnasium-robotics' and Stable-Baselines3's usual
'future' HER).
"""
from __future__ import annotations

import functools
from pathlib import Path

import torch
from tensordict import TensorDictBase

from ..blockstack.goals import option_met, sub_goal_reward

__all__ = ["LOW_DONE", "LOW_REWARD", "SEGMENT_END", "ReplayBuffers", "low_level_done", "low_level_keys", "mark_segments", "prepare_low_level",
           "relabelled_reward", "sub_goal_her_buffer"]

#: the key that ends a relabelling segment
SEGMENT_END = ("next", "segment_end")
#: the low level's reward (0 / -1 for its sub-goal, the penalty at a pessimistic termination)
LOW_REWARD = ("next", "sub_goal_reward")
#: where the low level's bootstrap stops: its sub-goal met at s', or a termination
LOW_DONE = ("next", "sub_goal_done")


def relabelled_reward(td: TensorDictBase) -> torch.Tensor:
    """``[..., 1]``: the low-level reward of ``td``'s (relabelled) ``sub_goal`` at its ``("next", "achieved_sub_goal")``.

    Where the model env ended the episode with its penalty
    (``("next", "penalized")``), the env's reward there (``-penalty``).
    """
    r = sub_goal_reward(td.get(("next", "achieved_sub_goal")), td.get("sub_goal")).unsqueeze(-1)
    penalized = td.get(("next", "penalized"), None)
    if penalized is not None:
        r = torch.where(penalized.reshape(r.shape), td.get(("next", "reward")).reshape(r.shape).to(r.dtype), r)
    return r


def mark_segments(td: TensorDictBase, per_option: bool = True) -> TensorDictBase:
    """Write :data:`SEGMENT_END`: the episode's end, with ``per_option`` also where the option's sub-goal is met (``("next", "option_done")``).

    On a collected batch (``[envs, time]``, two dimensions or more) the last
    step of each env's stretch ends a segment too: the batch is stored env by
    env, so the next stored transition belongs to another env.
    """
    end = td.get(("next", "done")).bool().clone()
    if per_option:
        end = end | td.get(("next", "option_done")).bool().reshape(end.shape)
    if td.ndim >= 2:
        end[:, -1] = True
    td.set(SEGMENT_END, end)
    return td


def prepare_low_level(td: TensorDictBase, per_option: bool = True) -> TensorDictBase:
    """Annotate a collected batch (``[envs, time]``) for the low level's HER buffer; returns it.

    Writes ``("next", "sub_goal")`` (the goal stays the transition's own:
    the critic's target at s' is for the same goal), ``("next",
    "option_done")`` (the running ``option``'s sub-goal met at s'),
    :data:`SEGMENT_END` and :data:`LOW_REWARD`.
    """
    nxt = td.get("next")
    nxt.set("sub_goal", td.get("sub_goal"))
    nxt.set("option_done", option_met(td.get("option"), nxt.get("achieved_goal")).unsqueeze(-1))
    mark_segments(td, per_option)
    td.set(LOW_REWARD, relabelled_reward(td))
    return td


def low_level_keys(td: TensorDictBase, action_key: str) -> list:
    """What the low level's HER buffer keeps of an annotated batch (:func:`prepare_low_level`): the goal-conditioned transition and its rewards."""
    keys = ["observation", "sub_goal", action_key, "option", ("next", "observation"), ("next", "sub_goal"), ("next", "achieved_sub_goal"),
            ("next", "reward"), ("next", "terminated"), ("next", "done"), SEGMENT_END, LOW_REWARD]
    return keys + ([("next", "penalized")] if ("next", "penalized") in td.keys(True) else [])


def low_level_done(td: TensorDictBase, on_success: bool = True) -> TensorDictBase:
    """Write :data:`LOW_DONE` on a sampled (possibly relabelled) batch: the sub-goal met at s' (reward 0) or ``("next", "terminated")``.

    ``on_success=False``: only ``("next", "terminated")`` (the model env's
    pessimistic terminations) stops the bootstrap; a met sub-goal does not
    end anything (Stable-Baselines3's HER: goal envs end at their time limit only).
    """
    r = td.get(LOW_REWARD)
    term = td.get(("next", "terminated"), None)
    done = (r == 0) if on_success else torch.zeros_like(r, dtype=torch.bool)
    if term is not None:
        done = done | term.reshape(done.shape).bool()
    td.set(LOW_DONE, done)
    return td


@functools.cache
def _her_buffer_class():
    """TorchRL's ``HERReplayBuffer`` with an episode-cache key that survives a full storage.

    TorchRL 0.14.1 keys its cache of episode ends on ``storage._last_cursor``,
    which becomes a tensor of indices once the storage wraps around, and then
    compares the keys with ``!=``: every sample after the wrap raises
    'Boolean value of Tensor with more than one value is ambiguous' (seen at
    200k frames of online UOF, ``buffer_size`` 200k). The key here holds the
    cursor's indices as a tuple; the relabelling itself is TorchRL's.
    """
    from torchrl.data import HERReplayBuffer

    class WrapSafeHERReplayBuffer(HERReplayBuffer):
        def _storage_cache_key(self, storage) -> tuple:
            size, cursor, full = super()._storage_cache_key(storage)
            if isinstance(cursor, torch.Tensor):
                cursor = tuple(cursor.reshape(-1).tolist())
            return size, cursor, full

    return WrapSafeHERReplayBuffer


def sub_goal_her_buffer(capacity: int, batch_size: int, her_ratio: float = 0.8, strategy: str = "future", device="cpu"):
    """A TorchRL ``HERReplayBuffer`` relabelling ``sub_goal`` within segments and recomputing :data:`LOW_REWARD`.

    Add batches through :func:`prepare_low_level` (or :func:`mark_segments`
    and :data:`LOW_REWARD`) first; run :func:`low_level_done` on samples.
    """
    from torchrl.data import LazyTensorStorage

    return _her_buffer_class()(relabelled_reward, her_ratio=her_ratio, strategy=strategy, goal_key="sub_goal", reward_key=LOW_REWARD,
                           achieved_goal_key=("next", "achieved_sub_goal"), end_key=SEGMENT_END,
                           storage=LazyTensorStorage(int(capacity), device=device), batch_size=int(batch_size))


class ReplayBuffers:
    """Several named replay buffers checkpointed as one (the loop saves an agent's ``replay_buffer`` with ``dumps`` / ``loads``).

    ``len()`` is the total number of stored transitions; each buffer goes into
    its own sub-folder.
    """

    def __init__(self, **buffers):
        self.buffers = dict(buffers)

    def __getitem__(self, name: str):
        return self.buffers[name]

    def __len__(self) -> int:
        return sum(len(b) for b in self.buffers.values())

    def dumps(self, path) -> None:
        Path(path).mkdir(parents=True, exist_ok=True)
        for name, b in self.buffers.items():
            if len(b):
                b.dumps(Path(path) / name)

    def loads(self, path) -> None:
        for name, b in self.buffers.items():
            if (Path(path) / name).is_dir():
                b.loads(Path(path) / name)

    def empty(self) -> None:
        for b in self.buffers.values():
            b.empty()
