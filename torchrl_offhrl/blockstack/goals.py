"""Sub-goals, successes and rewards of the block-stacking tasks as pure, vectorised tensor functions of the state.

The real envs (:mod:`torchrl_offhrl.blockstack.env`) and the model env (:class:`torchrl_offhrl.envs.BlockStackModelEnv`)
compute their goals and rewards with these functions, so that an agent
sees the same task in both. Every function takes observations of any
leading batch shape ``[..., obs_dim]`` (torch tensors; the gym env passes
numpy arrays through :func:`torch.as_tensor`).

The definitions follow the official UOF code the paper used (see
``block_stacking.md`` of the reference notes). ``n_blocks`` is 2 (task 1:
red and blue) or 3 (task 2: red, blue, green). Observation layout
(UOF's, velocities multiplied by ``dt = 0.04``)::

    [0:3]   gripper position            [3:6] gripper linear velocity
    [6:8]   finger velocities           [8:10] finger positions (qpos)
    then per block c (red, blue[, green]), 6 dims: position, gripper - position
    then per block c, 6 dims: gripper velocity - block velocity, block angular velocity

The low-level goal (sub-goal) of option ``k`` is a vector of
``5 + 3 * n_blocks`` numbers, ``[finger_r, finger_l, gripper xyz, red xyz,
blue xyz(, green xyz)]``, recomputed from the current state: with
``G(c)`` block ``c``'s current x, y at resting height :data:`REST_Z`, ``R``
red's current position, ``W`` = :data:`GRASP_WIDTH` and ``E`` =
:data:`END_POINT`,

==========================  =========  ===================  ====================================
sub-goal                    fingers    gripper              blocks
==========================  =========  ===================  ====================================
0 pick blue                 W, W       G(blue) + 0.005 z    all at G(c)
1 blue on red               W, W       R + 0.055 z          blue at R + 0.05 z, others at G(c)
2 end, blue on red          0.005      E                    blue at R + 0.05 z, others at G(c)
3-5 (task 2)                as 0-2 with green in place of blue (blue stays at G(blue))
==========================  =========  ===================  ====================================

The achieved sub-goal is ``[finger qpos, gripper, block positions]`` of
the state. Sub-goal ``k`` is met when the whole vector is within
:data:`SUCCESS_DISTANCE` (L2) of its sub-goal. The high level's
``achieved_goal`` is the vector of success flags of every sub-goal, its
``desired_goal`` a one-hot goal index.
"""
from __future__ import annotations

import torch

__all__ = [
    "END_POINT", "GRASP_WIDTH", "REST_Z", "SUCCESS_DISTANCE", "abstract_demonstration", "blocks_for_obs_dim", "check_blocks", "achieved_goal_flags", "achieved_sub_goal",
    "block_positions", "first_option", "goal_fields", "goal_reward", "next_option", "option_met", "n_goals", "obs_dim", "sub_goal_dim", "sub_goal_reached", "sub_goal_reward", "sub_goals", "sub_goals_reference",
    "success_by_goal",
]

#: resting height of a block's centre on the table (UOF's constant; MuJoCo settles at ~0.4249)
REST_Z = 0.425
#: each finger's position when closed on a block (UOF's ``W``)
GRASP_WIDTH = 0.023
#: each finger's position in the final sub-goals (closed)
CLOSED_WIDTH = 0.005
#: the fixed point the gripper returns to in the final sub-goals
END_POINT = (1.25, 0.75, 0.65)
#: a sub-goal is met when its whole vector is within this L2 distance
SUCCESS_DISTANCE = 0.02
#: height of the gripper above the centre of the block it holds (grasp sub-goal)
GRASP_OFFSET = 0.005
#: height of a stacked block's centre above the lower block's centre
STACK_OFFSET = 0.05
#: height of the gripper above the lower block's centre when it has stacked a block on it
PLACE_OFFSET = 0.055


def check_blocks(n_blocks: int) -> int:
    """``n_blocks`` if it is 2 or 3, else a ValueError."""
    if n_blocks not in (2, 3):
        raise ValueError(f"n_blocks must be 2 (task 1: red, blue) or 3 (task 2: red, blue, green), got {n_blocks!r}")
    return int(n_blocks)


def n_goals(n_blocks: int) -> int:
    """Number of goals (= options = sub-goals): 3 for task 1, 6 for task 2."""
    return 3 * (check_blocks(n_blocks) - 1)


def obs_dim(n_blocks: int) -> int:
    """Observation size: 34 for task 1, 46 for task 2."""
    return 10 + 12 * check_blocks(n_blocks)


def blocks_for_obs_dim(dim: int) -> int | None:
    """The number of blocks of a task whose observations have ``dim`` entries (2 for 34, 3 for 46), or None for another size."""
    return {obs_dim(2): 2, obs_dim(3): 3}.get(int(dim))


def sub_goal_dim(n_blocks: int) -> int:
    """Sub-goal size: 11 for task 1, 14 for task 2."""
    return 5 + 3 * check_blocks(n_blocks)


def _as_obs(obs, n_blocks: int) -> torch.Tensor:
    obs = torch.as_tensor(obs)
    if not obs.is_floating_point():
        obs = obs.float()
    if obs.shape[-1] != obs_dim(n_blocks):
        raise ValueError(f"observations of the {n_blocks}-block task have {obs_dim(n_blocks)} entries, got shape {tuple(obs.shape)}")
    return obs


def block_positions(obs, n_blocks: int) -> torch.Tensor:
    """``[..., n_blocks, 3]``: the blocks' positions (red, blue[, green])."""
    obs = _as_obs(obs, n_blocks)
    return torch.stack([obs[..., 10 + 6 * c: 13 + 6 * c] for c in range(n_blocks)], dim=-2)


def achieved_sub_goal(obs, n_blocks: int) -> torch.Tensor:
    """``[..., 5 + 3 n_blocks]``: finger positions, gripper position, block positions of the state."""
    obs = _as_obs(obs, n_blocks)
    return torch.cat([obs[..., 8:10], obs[..., 0:3], block_positions(obs, n_blocks).flatten(-2)], dim=-1)


def sub_goals(obs, n_blocks: int) -> torch.Tensor:
    """``[..., n_goals, 5 + 3 n_blocks]``: every option's sub-goal at this state (table in the module docstring).

    Every entry of a sub-goal is a constant or an entry of the observation
    plus a constant, so the map is affine: it runs as one matrix product,
    ``obs @ M.T + c``, with ``(M, c)`` read off :func:`sub_goals_reference`
    (the definition, entry by entry) once per dtype and device.
    """
    obs = _as_obs(obs, n_blocks)
    m, c = _affine(n_blocks, obs.dtype, obs.device)
    return (obs @ m.T + c).unflatten(-1, (n_goals(n_blocks), sub_goal_dim(n_blocks)))


_AFFINE: dict = {}


def _affine(n_blocks: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    key = (n_blocks, dtype, device)
    if key not in _AFFINE:
        d = obs_dim(n_blocks)
        c = sub_goals_reference(torch.zeros(d, dtype=torch.float64), n_blocks).flatten()
        m = sub_goals_reference(torch.eye(d, dtype=torch.float64), n_blocks).flatten(-2) - c  # row i: the response to obs entry i
        _AFFINE[key] = (m.T.contiguous().to(dtype=dtype, device=device), c.to(dtype=dtype, device=device))
    return _AFFINE[key]


def sub_goals_reference(obs, n_blocks: int) -> torch.Tensor:
    """:func:`sub_goals` computed entry by entry from the definitions (slower; what the fast affine form is read from)."""
    obs = _as_obs(obs, n_blocks)
    blocks = block_positions(obs, n_blocks)
    rest = blocks.clone()
    rest[..., 2] = REST_Z  # G(c): each block's x, y at resting height
    red = blocks[..., 0, :]
    up = obs.new_tensor([0.0, 0.0, 1.0])
    end = obs.new_tensor(END_POINT).expand_as(red)
    out = []
    for moved in range(1, n_blocks):  # blue (goals 0-2), then green (goals 3-5)
        stacked = rest.clone()
        stacked[..., moved, :] = red + STACK_OFFSET * up
        for fingers, gripper, layout in (
            (GRASP_WIDTH, rest[..., moved, :] + GRASP_OFFSET * up, rest),
            (GRASP_WIDTH, red + PLACE_OFFSET * up, stacked),
            (CLOSED_WIDTH, end, stacked),
        ):
            f = obs.new_full((*obs.shape[:-1], 2), fingers)
            out.append(torch.cat([f, gripper, layout.flatten(-2)], dim=-1))
    return torch.stack(out, dim=-2)


def sub_goal_reached(achieved, goal) -> torch.Tensor:
    """``|achieved - goal| < SUCCESS_DISTANCE`` over the last dimension (bool); shapes broadcast."""
    achieved, goal = torch.as_tensor(achieved), torch.as_tensor(goal)
    return torch.linalg.vector_norm((achieved - goal).float(), dim=-1) < SUCCESS_DISTANCE


def sub_goal_reward(achieved, goal) -> torch.Tensor:
    """The low level's reward: 0 where ``achieved`` (at s') meets ``goal``, else -1 (float)."""
    return sub_goal_reached(achieved, goal).float() - 1.0


def goal_fields(obs, n_blocks: int) -> dict[str, torch.Tensor]:
    """The goal entries of a state, as the real envs and the model env write them.

    ``sub_goals`` (:func:`sub_goals`), ``achieved_sub_goal``
    (:func:`achieved_sub_goal`) and ``achieved_goal`` (the success flags of
    every sub-goal, in the observations' dtype), each computed once.
    """
    obs = _as_obs(obs, n_blocks)
    sub, achieved = sub_goals(obs, n_blocks), achieved_sub_goal(obs, n_blocks)
    return {"sub_goals": sub, "achieved_sub_goal": achieved, "achieved_goal": sub_goal_reached(achieved.unsqueeze(-2), sub).to(obs.dtype)}


def achieved_goal_flags(obs, n_blocks: int) -> torch.Tensor:
    """``[..., n_goals]``: 1.0 for every sub-goal the state meets (the high level's ``achieved_goal``), in the observations' dtype."""
    return goal_fields(obs, n_blocks)["achieved_goal"]


def goal_reward(achieved_goal, desired_goal) -> torch.Tensor:
    """The high level's reward: 0 where the success flags equal the one-hot ``desired_goal``, else -1 (float).

    UOF also requires the running option to be the goal's; the env does
    not know the agent's option, so hierarchical agents add that condition.
    """
    achieved_goal, desired_goal = torch.as_tensor(achieved_goal), torch.as_tensor(desired_goal)
    return (achieved_goal.round() == desired_goal.round()).all(-1).float() - 1.0


def abstract_demonstration(goal: int, n_blocks: int) -> list[int]:
    """The option sequence that ends in ``goal`` (UOF's abstract demonstrations).

    Examples:
        >>> abstract_demonstration(2, 2), abstract_demonstration(4, 3)
        ([0, 1, 2], [3, 4])
    """
    if not 0 <= int(goal) < n_goals(n_blocks):
        raise ValueError(f"goal must be in [0, {n_goals(n_blocks)}) for the {n_blocks}-block task, got {goal}")
    start = 3 * (int(goal) // 3)
    return list(range(start, int(goal) + 1))


def next_option(option: torch.Tensor, goal: torch.Tensor, flags: torch.Tensor) -> torch.Tensor:
    """The options after a step: each env moves on along its goal's abstract demonstration when its sub-goal is met.

    ``option`` and ``goal`` are ``[B]`` integer tensors, ``flags`` the
    ``[B, n_goals]`` success flags at s' (the env's ``achieved_goal``). An
    env already in its goal's option stays in it.

    Examples:
        >>> import torch
        >>> next_option(torch.tensor([0, 0, 2]), torch.tensor([2, 0, 2]), torch.tensor([[1., 0, 0], [1, 0, 0], [0, 0, 1]]))
        tensor([1, 0, 2])
    """
    return torch.where(option_met(option, flags) & (option < goal), option + 1, option)


def option_met(option: torch.Tensor, flags: torch.Tensor) -> torch.Tensor:
    """``[B]`` bool: whether each env's ``option`` has its sub-goal met in the success ``flags`` (``[B, n_goals]``)."""
    return flags.gather(-1, option.long().unsqueeze(-1)).squeeze(-1) > 0.5


def first_option(goal: torch.Tensor) -> torch.Tensor:
    """The first option of each goal's abstract demonstration (0 for goals 0-2, 3 for goals 3-5)."""
    return 3 * torch.div(goal.long(), 3, rounding_mode="floor")


def success_by_goal(reward: torch.Tensor, alive: torch.Tensor, goal: torch.Tensor, num_goals: int) -> torch.Tensor:
    """``[num_goals]``: the share of each goal's episodes that succeeded (NaN for a goal with no episode).

    An episode succeeds when its high-level reward is 0 at some step it is
    still running (UOF's test). ``reward`` and ``alive`` are ``[E, T]`` (an
    evaluation rollout: rewards and :func:`~torchrl_offhrl.rollouts.first_episode_mask`),
    ``goal`` is ``[E]``.

    Examples:
        >>> import torch
        >>> r = torch.tensor([[-1., 0.], [-1., -1.], [0., -1.]])
        >>> success_by_goal(r, torch.ones(3, 2, dtype=torch.bool), torch.tensor([0, 0, 2]), 3)
        tensor([0.5000,    nan, 1.0000])
    """
    ok = ((reward == 0) & alive.bool()).any(-1).float()
    counts = torch.zeros(num_goals).index_add_(0, goal.long().cpu(), torch.ones_like(ok).cpu())
    hits = torch.zeros(num_goals).index_add_(0, goal.long().cpu(), ok.cpu())
    return hits / counts  # 0 / 0 = NaN where a goal has no episode
