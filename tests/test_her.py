"""Hindsight relabelling of the sub-goal on block-stacking data (TorchRL's HERReplayBuffer with the task's reward)."""
from __future__ import annotations

import torch

from torchrl_offhrl.agents.her import LOW_REWARD, SEGMENT_END, mark_segments, relabelled_reward, sub_goal_her_buffer
from torchrl_offhrl.blockstack import goals as G


def test_relabelled_goals_come_from_later_in_the_same_option_segment():
    from torchrl_offhrl.data.stacking import collect_stacking

    ds = collect_stacking("BlockStack2-v0", 100, 0.0, 0.05, num_envs=2, seed=3, progress=False)
    data = mark_segments(ds.data.clone())
    data.set(LOW_REWARD, relabelled_reward(data))
    ends = data[SEGMENT_END].squeeze(-1)
    assert torch.equal(ends, (data["next", "done"] | data["next", "option_done"]).squeeze(-1))
    rb = sub_goal_her_buffer(1000, 64, her_ratio=1.0)
    rb.extend(data)
    torch.manual_seed(0)
    batch = rb.sample()
    # every relabelled goal is an achieved sub-goal at s' of a transition at or after it, within its segment
    seg = torch.cumsum(torch.cat([torch.zeros(1, dtype=torch.long), ends[:-1].long()]), 0)
    achieved = data["next", "achieved_sub_goal"]
    idx = batch["index"]  # where each sampled transition sits in the storage (TorchRL writes it)
    for i in range(len(batch)):
        t = int(idx[i])
        same = (seg == seg[t]) & (torch.arange(len(data)) >= t)
        assert (achieved[same] == batch["sub_goal"][i]).all(-1).any()
    # rewards recomputed with the task's function: 0 where the goal is the transition's own achieved sub-goal
    torch.testing.assert_close(batch[LOW_REWARD], relabelled_reward(batch))
    own = (batch["sub_goal"] == batch["next", "achieved_sub_goal"]).all(-1)
    assert own.any() and (batch[LOW_REWARD].squeeze(-1)[own] == 0).all()
    torch.testing.assert_close(batch["next", "reward"], data["next", "reward"][idx])  # the high level's reward is left alone


def test_relabelled_reward_by_hand():
    td = {"sub_goal": torch.zeros(3, 11)}
    achieved = torch.zeros(3, 11)
    achieved[1, 2] = 0.019
    achieved[2, 2] = 0.03
    from tensordict import TensorDict

    t = TensorDict({"sub_goal": td["sub_goal"], "next": {"achieved_sub_goal": achieved}}, batch_size=[3])
    torch.testing.assert_close(relabelled_reward(t), torch.tensor([[0.0], [0.0], [-1.0]]))
    assert G.SUCCESS_DISTANCE == 0.02


def test_the_buffer_keeps_sampling_once_it_is_full_and_wraps():
    """TorchRL 0.14.1's HERReplayBuffer fails once its storage wraps (its episode cache compares a tensor cursor); ours does not.

    Seen after 200k frames of online UOF (buffer_size 200k): 'Boolean value of Tensor with more than one value is ambiguous'.
    After the wrap, relabelled goals still come from the same segment, at or after the transition.
    """
    from torchrl_offhrl.data.stacking import collect_stacking

    ds = collect_stacking("BlockStack2-v0", 100, 0.0, 0.05, num_envs=2, seed=3, progress=False)
    data = mark_segments(ds.data.clone())
    data.set(LOW_REWARD, relabelled_reward(data))
    rb = sub_goal_her_buffer(60, 16, her_ratio=1.0)
    for start in range(0, 100, 25):  # 100 transitions through a 60-slot storage: the last extends wrap around
        rb.extend(data[start:start + 25])
        batch = rb.sample()
        assert batch.shape == (16,)
    torch.testing.assert_close(batch[LOW_REWARD], relabelled_reward(batch))
    assert len(rb) == 60
