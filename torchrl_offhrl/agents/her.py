"""Hindsight relabelling of the low-level goal (the sub-goal) for goal-conditioned agents (UOF's low level, SAC + HER).

TorchRL's :class:`~torchrl.data.HERReplayBuffer` does the relabelling; this
module sets it up for the block-stacking data: the relabelled goal is
``sub_goal``, taken from an ``("next", "achieved_sub_goal")`` later in the same
segment, and the reward is recomputed with the task's own function
(:func:`torchrl_offhrl.blockstack.goals.sub_goal_reward`: 0 when the achieved
sub-goal at s' is within 2 cm of the goal, else -1). Segments are option
segments by default, as UOF relabels (a segment ends where the option's
sub-goal is met or the episode ends), or whole episodes
(``per_option=False``, gymnasium-robotics' usual 'future' HER).
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from ..blockstack.goals import sub_goal_reward

__all__ = ["SEGMENT_END", "mark_segments", "relabelled_reward", "sub_goal_her_buffer"]

#: the key that ends a relabelling segment
SEGMENT_END = ("next", "segment_end")


def relabelled_reward(td: TensorDictBase) -> torch.Tensor:
    """``[..., 1]``: the low-level reward of ``td``'s (relabelled) ``sub_goal`` at its ``("next", "achieved_sub_goal")``."""
    return sub_goal_reward(td.get(("next", "achieved_sub_goal")), td.get("sub_goal")).unsqueeze(-1)


def mark_segments(td: TensorDictBase, per_option: bool = True) -> TensorDictBase:
    """Write :data:`SEGMENT_END`: the episode's end, and with ``per_option`` also where the option's sub-goal is met (``("next", "option_done")``)."""
    end = td.get(("next", "done")).bool()
    if per_option:
        end = end | td.get(("next", "option_done")).bool().reshape(end.shape)
    td.set(SEGMENT_END, end)
    return td


def sub_goal_her_buffer(capacity: int, batch_size: int, her_ratio: float = 0.8, strategy: str = "future", device="cpu"):
    """A TorchRL ``HERReplayBuffer`` relabelling ``sub_goal`` within segments (add batches through :func:`mark_segments` first)."""
    from torchrl.data import HERReplayBuffer, LazyTensorStorage

    return HERReplayBuffer(relabelled_reward, her_ratio=her_ratio, strategy=strategy, goal_key="sub_goal",
                           achieved_goal_key=("next", "achieved_sub_goal"), end_key=SEGMENT_END,
                           storage=LazyTensorStorage(int(capacity), device=device), batch_size=int(batch_size))
