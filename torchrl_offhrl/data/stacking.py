"""Behaviour for the block-stacking tasks: a scripted pick-and-stack controller and how it follows a goal's options.

:class:`ScriptedStacker` maps a batch of observations and the options the
envs are in to Fetch actions, with no state of its own (everything it needs
is in the observation), so one call serves any number of envs. Options
follow UOF's abstract demonstrations (:func:`~torchrl_offhrl.blockstack.goals.abstract_demonstration`):
an episode with goal ``k`` starts in the first option of ``k``'s sequence
and moves to the next one when the running option's sub-goal is met
(:func:`next_option`).

The script (checked on the Fetch robot of gymnasium-robotics): move the
gripper towards a target with ``clip(2 (target - gripper) / 0.05, -1, 1)``
(a saturated action moves the mocap 5 cm, the gripper follows with a lag);

* pick (options 0, 3): above the block at +6 cm with the fingers open until
  the x, y error is under 8 mm (descending diagonally knocks the block),
  then down to the grasp height (+5 mm) and close;
* place (1, 4): fingers closed, above red at +8 cm until aligned, then down
  to red + 5.5 cm;
* end (2, 5): near the stack, open and move straight up (a diagonal
  retreat knocks the block off), then go to the end point closing the
  fingers to 5 mm.

Noise makes the data levels: with probability ``random_prob`` an action is
uniform in the action box, otherwise Gaussian noise of ``noise_std`` is
added to its three displacement entries.
"""
from __future__ import annotations

import numpy as np
import torch

from ..blockstack import goals as G
from ..blockstack.goals import first_option, next_option
from .collect import combine_levels, package_versions

__all__ = ["GOAL_FIELDS", "SCRIPT_LEVELS", "ScriptedStacker", "collect_stacking", "combine_stacking", "first_option", "generate_stacking_dataset", "next_option", "scripted_success"]

_ALIGN = 0.008     # x, y error under which the gripper descends
_SAFE = 0.06       # height above a block to reach it from
_CARRY = 0.08      # height above red to carry a block at
_GAIN = 2.0 / 0.05


class ScriptedStacker:
    """A stateless scripted controller for :mod:`~torchrl_offhrl.blockstack.env`'s tasks (module docstring: the script).

    Args:
        n_blocks: 2 or 3.
        random_prob: probability of a uniformly random action.
        noise_std: Gaussian noise on the displacement entries of the other actions.
        generator: a ``torch.Generator`` for the noise (a collection is then deterministic for a seed).

    ``controller(observation, option)`` with ``observation`` ``[B, obs_dim]``
    and ``option`` ``[B]`` returns ``[B, 4]`` actions in ``[-1, 1]``.
    """

    def __init__(self, n_blocks: int, random_prob: float = 0.0, noise_std: float = 0.0, generator: torch.Generator | None = None):
        self.n_blocks = G.check_blocks(n_blocks)
        if not 0.0 <= random_prob <= 1.0 or noise_std < 0:
            raise ValueError(f"random_prob must be in [0, 1] and noise_std >= 0, got {random_prob}, {noise_std}")
        self.random_prob, self.noise_std, self.generator = float(random_prob), float(noise_std), generator

    def clean_action(self, observation: torch.Tensor, option: torch.Tensor) -> torch.Tensor:
        """The script's action without noise."""
        obs = torch.as_tensor(observation, dtype=torch.float32)
        option = torch.as_tensor(option).long().reshape(obs.shape[:-1])
        grip, fingers = obs[..., 0:3], obs[..., 8:10]
        blocks = G.block_positions(obs, self.n_blocks)
        red = blocks[..., 0, :]
        moved = blocks.gather(-2, (1 + option // 3).view(*option.shape, 1, 1).expand(*option.shape, 1, 3)).squeeze(-2)
        stage = option % 3
        up = obs.new_tensor([0.0, 0.0, 1.0])
        q = fingers.mean(-1)
        open_, close = torch.ones_like(q), -torch.ones_like(q)

        # pick: reach above, descend when aligned, close when at the grasp height
        grasp = moved + G.GRASP_OFFSET * up
        xy_b = torch.linalg.vector_norm(grip[..., :2] - moved[..., :2], dim=-1)
        at_grasp = (xy_b < 0.02) & ((grip[..., 2] - grasp[..., 2]).abs() < 0.015)
        aligned_b = xy_b < _ALIGN
        pick_target = torch.where((aligned_b | at_grasp).unsqueeze(-1), grasp, moved + _SAFE * up)
        pick_fingers = torch.where(at_grasp, close, open_)

        # place: carry above red, descend when aligned; fingers closed
        place = red + G.PLACE_OFFSET * up
        xy_r = torch.linalg.vector_norm(grip[..., :2] - red[..., :2], dim=-1)
        place_target = torch.where((xy_r < _ALIGN).unsqueeze(-1), place, red + _CARRY * up)

        # end: near the stack open and go straight up, then to the end point closing to 5 mm
        near_stack = (xy_r < 0.02) & (grip[..., 2] < red[..., 2] + G.PLACE_OFFSET + 0.04)
        end = obs.new_tensor(G.END_POINT).expand_as(grip)
        end_target = torch.where(near_stack.unsqueeze(-1), grip + 0.05 * up, end)
        end_fingers = torch.where(near_stack, open_, G.CLOSED_WIDTH - q)

        target = torch.where((stage == 0).unsqueeze(-1), pick_target, torch.where((stage == 1).unsqueeze(-1), place_target, end_target))
        finger = torch.where(stage == 0, pick_fingers, torch.where(stage == 1, close, end_fingers))
        xyz = ((target - grip) * _GAIN).clamp(-1.0, 1.0)
        return torch.cat([xyz, finger.clamp(-1.0, 1.0).unsqueeze(-1)], dim=-1)

    def __call__(self, observation: torch.Tensor, option: torch.Tensor) -> torch.Tensor:
        action = self.clean_action(observation, option)
        if self.noise_std > 0:
            noise = torch.randn(action.shape[:-1] + (3,), generator=self.generator) * self.noise_std
            action = torch.cat([(action[..., :3] + noise).clamp(-1.0, 1.0), action[..., 3:]], dim=-1)
        if self.random_prob > 0:
            rand = torch.rand(action.shape, generator=self.generator) * 2 - 1
            pick = torch.rand(action.shape[:-1] + (1,), generator=self.generator) < self.random_prob
            action = torch.where(pick, rand, action)
        return action


# ------------------------------------------------------------------ datasets
#: level -> (probability of a uniformly random action, Gaussian noise on the displacement) of the scripted controller;
#: ``medium-expert`` is the ``medium`` and ``expert`` datasets concatenated (D4RL's protocol)
SCRIPT_LEVELS: dict[str, tuple[float, float]] = {"expert": (0.0, 0.05), "medium": (0.1, 0.1)}
#: bump when the script or the recorded fields change: part of the cache key of named datasets
SCRIPT_VERSION = 1
#: the goal fields recorded next to the D4RL keys (TensorDict key: meaning)
GOAL_FIELDS = {
    "desired_goal": "the episode's goal, one-hot (the high level's goal)",
    "achieved_goal": "success flags of every sub-goal at s",
    ("next", "achieved_goal"): "success flags of every sub-goal at s'",
    "option": "the option (sub-goal index) the controller followed at s",
    "sub_goal": "that option's sub-goal at s (the low level's goal)",
    "achieved_sub_goal": "the achieved sub-goal at s",
    ("next", "achieved_sub_goal"): "the achieved sub-goal at s'",
    ("next", "sub_goal_reward"): "the low level's reward: 0 when the option's sub-goal is met at s', else -1",
    ("next", "option_done"): "the option's sub-goal is met at s' (the option terminates)",
}


def collect_stacking(env_id: str, num_transitions: int, random_prob: float = 0.0, noise_std: float = 0.0, num_envs: int = 8,
                     seed: int = 0, horizon: int | None = None, progress: bool = True, metadata: dict | None = None,
                     controller=None):
    """Episodes of :class:`ScriptedStacker` in a block-stacking env, as an :class:`~torchrl_offhrl.data.OfflineDataset`.

    All ``num_envs`` envs run whole episodes side by side (the tasks have a
    fixed horizon and never terminate), so ``num_transitions`` is rounded up
    to whole rounds of ``num_envs`` episodes. Each episode's goal is drawn
    uniformly by its env; the controller follows the goal's options
    (:func:`next_option`). Besides the D4RL keys (``reward`` is the high
    level's) every transition carries :data:`GOAL_FIELDS`. ``controller``
    replaces the script (``random_prob`` and ``noise_std`` then unused): any
    callable ``(observation [B, obs_dim], option [B]) -> action [B, 4]``, the
    hook for the paper's route of data from partially trained UOF agents
    (:class:`~torchrl_offhrl.recipes.uof_policies.UOFController`); a
    controller with a ``select_option(obs, option)`` method (``obs`` the env's
    dict of tensors, ``option`` None at the start of an episode) picks the
    options itself instead of following the goal's abstract demonstration,
    and its ``card`` attribute (a dict) goes into the metadata.
    ``metadata["goal_success"]`` holds the fraction of episodes of each goal
    that reached it (high-level reward 0 at some step) and
    ``metadata["goal_episodes"]`` their counts. The same seed gives the same
    tensors.
    """
    import time

    import gymnasium as gym
    from tensordict import TensorDict
    from tqdm.auto import tqdm

    from ..blockstack import DEFAULT_HORIZON, register_blockstack_envs
    from ..registry import stacking_tasks, task_of
    from .dataset import OfflineDataset

    if not task_of(env_id).goal_conditioned:
        raise ValueError(f"collect_stacking: {env_id!r} is not a block-stacking env ({', '.join(stacking_tasks())})")
    register_blockstack_envs()
    n_blocks = task_of(env_id).n_blocks
    horizon = int(horizon or DEFAULT_HORIZON)
    # Gymnasium's vector env, reset by hand at the start of each round (every episode ends at the horizon together):
    # no per-step TensorDict bookkeeping, which cost as much as the MuJoCo step itself
    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="sync",
                        vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.DISABLED}, max_episode_steps=horizon)
    gen = torch.Generator().manual_seed(seed)
    scripted = controller is None
    controller = ScriptedStacker(n_blocks, random_prob, noise_std, generator=gen) if scripted else controller
    choose = getattr(controller, "select_option", None)  # a controller with its own high level picks the options
    rounds = -(-int(num_transitions) // (num_envs * horizon))
    rows = torch.arange(num_envs)
    steps: list[dict] = []
    t0 = time.time()
    bar = tqdm(total=rounds * num_envs * horizon, desc=f"collect {env_id}", disable=not progress, unit="step")
    for r in range(rounds):
        obs, _ = venv.reset(seed=seed if r == 0 else None)  # env i is seeded with seed + i, then continues its own stream
        obs = {k: torch.from_numpy(v) for k, v in obs.items()}
        goal = obs["desired_goal"].argmax(-1)
        option = choose(obs, None) if choose else first_option(goal)
        for t in range(horizon):
            action = torch.as_tensor(controller(obs["observation"].float(), option), dtype=torch.float32)
            nobs, reward, terminated, truncated, _ = venv.step(action.double().numpy())
            nobs = {k: torch.from_numpy(v) for k, v in nobs.items()}
            flags = nobs["achieved_goal"]
            done_opt = G.option_met(option, flags).unsqueeze(-1)
            steps.append({
                "observation": obs["observation"], "action": action, "desired_goal": obs["desired_goal"], "achieved_goal": obs["achieved_goal"],
                "option": option, "sub_goal": obs["sub_goals"][rows, option], "achieved_sub_goal": obs["achieved_sub_goal"],
                ("next", "observation"): nobs["observation"], ("next", "reward"): torch.from_numpy(np.asarray(reward)).unsqueeze(-1),
                ("next", "terminated"): torch.from_numpy(np.asarray(terminated)).unsqueeze(-1),
                ("next", "truncated"): torch.from_numpy(np.asarray(truncated)).unsqueeze(-1),
                ("next", "achieved_goal"): flags, ("next", "achieved_sub_goal"): nobs["achieved_sub_goal"],
                ("next", "sub_goal_reward"): done_opt.float() - 1.0, ("next", "option_done"): done_opt,
            })
            option = choose(nobs, option) if choose else next_option(option, goal, flags)
            obs = nobs
            bar.update(num_envs)
        if not bool(steps[-1][("next", "truncated")].all()):
            raise RuntimeError(f"{env_id}: an episode did not end at the horizon {horizon}")
    bar.close()
    venv.close()
    # [rounds * horizon, num_envs] -> episode after episode: [rounds, num_envs, horizon] flattened
    stacked = {}
    for key in steps[0]:
        v = torch.stack([st[key] for st in steps]).unflatten(0, (rounds, horizon)).transpose(1, 2).flatten(0, 2)
        stacked[key] = v.float() if v.dtype == torch.float64 else v
    data = TensorDict({}, batch_size=[rounds * num_envs * horizon])
    for key, v in stacked.items():
        data.set(key, v)
    goals = data["desired_goal"].argmax(-1).reshape(-1, horizon)[:, 0]
    reached = (data["next", "reward"].reshape(-1, horizon) == 0).any(-1)
    n_goals = data["desired_goal"].shape[-1]
    success = {str(k): (float(reached[goals == k].float().mean()) if bool((goals == k).any()) else None) for k in range(n_goals)}
    meta = {
        "env_id": env_id, "seed": seed, "num_envs": num_envs, "horizon": horizon, "n_blocks": n_blocks,
        "policy": "scripted-stacker" if scripted else (getattr(controller, "card", None) or {}).get("name", type(controller).__name__),
        "policy_card": {"name": "scripted-stacker", "version": SCRIPT_VERSION, "random_prob": random_prob, "noise_std": noise_std}
        if scripted else {"name": type(controller).__name__, **(getattr(controller, "card", None) or {})},
        "goal_success": success, "goal_episodes": {str(k): int((goals == k).sum()) for k in range(n_goals)},
        "success_rate": float(reached.float().mean()),
        "goal_fields": {"/".join(k) if isinstance(k, tuple) else k: v for k, v in GOAL_FIELDS.items()},
        "collection_seconds": round(time.time() - t0, 2), "versions": package_versions(),
    }
    meta.update(metadata or {})
    ds = OfflineDataset(data, meta, (-torch.ones(4), torch.ones(4)))
    ds.metadata["unfinished_episodes"] = []
    ds.metadata["returns"] = ds.return_stats()
    return ds


def combine_stacking(parts, seed: int):
    """``medium`` + ``expert`` -> ``medium-expert`` (episodes renumbered), with the goal statistics of both parts."""
    ds = combine_levels(parts, seed, keep=("env_id", "num_envs", "versions", "horizon", "n_blocks", "goal_fields"),
                        part_keys=("goal_success", "collection_seconds"))
    eps = {k: sum(p.metadata["goal_episodes"][k] for p in parts) for k in parts[0].metadata["goal_episodes"]}
    ds.metadata["goal_episodes"] = eps
    ds.metadata["goal_success"] = {
        k: (sum((p.metadata["goal_success"][k] or 0.0) * p.metadata["goal_episodes"][k] for p in parts) / eps[k]) if eps[k] else None for k in eps}
    ds.metadata["success_rate"] = sum(p.metadata["success_rate"] * len(p) for p in parts) / sum(len(p) for p in parts)
    return ds


def generate_stacking_dataset(env_id: str, level: str, num_transitions: int = 1_000_000, seed: int = 0, num_envs: int = 8,
                              progress: bool = True, horizon: int | None = None):
    """A block-stacking dataset of a scripted ``level`` (:data:`SCRIPT_LEVELS`; ``medium-expert`` = medium + expert, each ``num_transitions``).

    The paper's data came from partially trained UOF agents (task 1: 20 and
    50 epochs, task 2: 200): ``offhrl collect blockstack2 --policy
    blockstack2-uof-epoch20`` collects with a UOF policy trained online
    (:mod:`~torchrl_offhrl.recipes.uof_policies`) through
    :func:`collect_stacking`'s ``controller`` hook.
    """
    if level == "medium-expert":
        ds = combine_stacking([generate_stacking_dataset(env_id, lv, num_transitions, seed, num_envs, progress, horizon) for lv in ("medium", "expert")],
                              seed)
    elif level in SCRIPT_LEVELS:
        random_prob, noise_std = SCRIPT_LEVELS[level]
        ds = collect_stacking(env_id, num_transitions, random_prob, noise_std, num_envs=num_envs, seed=seed, horizon=horizon, progress=progress)
    else:
        raise ValueError(f"block-stacking datasets come in the levels {[*SCRIPT_LEVELS, 'medium-expert']}, got {level!r}")
    short = env_id.split("-")[0].lower()
    ds.metadata.update({"dataset": f"{short}-{level}", "level": level, "seed": seed, "num_transitions_requested": num_transitions,
                        "protocol": "scripted pick-and-stack controller with noise (torchrl_offhrl.data.stacking.SCRIPT_LEVELS); "
                                    "medium-expert = medium + expert concatenated"})
    return ds


def scripted_success(env_id: str, episodes: int = 10, horizon: int | None = None, random_prob: float = 0.0, noise_std: float = 0.0,
                     seed: int = 0, **env_kwargs) -> dict[int, float]:
    """Per goal, the fraction of ``episodes`` (seeds ``seed * 1000 + goal * episodes + i``) in which the script reaches it.

    An episode reaches its goal when the high-level reward is 0 at some step
    (UOF's test). Goals are set with ``reset(options={"goal": k})``.
    """
    import gymnasium as gym

    from ..blockstack import DEFAULT_HORIZON, register_blockstack_envs
    from ..registry import task_of

    register_blockstack_envs()
    n_blocks = task_of(env_id).n_blocks
    env = gym.make(env_id, max_episode_steps=int(horizon or DEFAULT_HORIZON), **env_kwargs)
    controller = ScriptedStacker(n_blocks, random_prob, noise_std, generator=torch.Generator().manual_seed(seed))
    out = {}
    for k in range(G.n_goals(n_blocks)):
        reached = 0
        for i in range(episodes):
            obs, _ = env.reset(seed=seed * 1000 + k * episodes + i, options={"goal": k})
            goal = torch.tensor([k])
            option, hit, done = first_option(goal), False, False
            while not done:
                action = controller(torch.as_tensor(obs["observation"]).unsqueeze(0), option)[0]
                obs, reward, terminated, truncated, _ = env.step(action.double().numpy())
                hit |= reward == 0
                option = next_option(option, goal, torch.as_tensor(obs["achieved_goal"]).unsqueeze(0))
                done = terminated or truncated
            reached += int(hit)
        out[k] = reached / episodes
    env.close()
    return out
