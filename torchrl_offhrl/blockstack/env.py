"""The goal-conditioned block-stacking tasks of the paper on gymnasium-robotics' MuJoCo Fetch robot.

* ``BlockStack2-v0`` (task 1, UOF's ``TwoObjectOneOrderBinaryHighLvGoal``):
  red and blue blocks, 3 goals: (0) grasp blue, (1) blue on red, (2) blue on
  red and the gripper back at a fixed point, closed.
* ``BlockStack3-v0`` (task 2, UOF's ``ThreeObjectOneStageTwoOrder...``):
  red, blue and green, 6 goals: 0-2 as task 1, 3-5 the same with green.

Both are ``gymnasium_robotics`` goal envs with a 4-D action (gripper
displacement and finger command, in ``[-1, 1]``) and the observation dict

* ``observation``: UOF's state vector (34 / 46 entries, layout in
  :mod:`torchrl_offhrl.blockstack.goals`);
* ``desired_goal``: the episode's goal, one-hot (sampled uniformly at
  reset, or ``reset(options={"goal": k})``);
* ``achieved_goal``: the success flags of every sub-goal at this state;
* ``sub_goals``: every option's low-level goal at this state, ``[n_goals,
  5 + 3 n_blocks]`` (an option-conditioned agent reads row ``option``);
* ``achieved_sub_goal``: the state's achieved low-level goal.

The reward is the high level's (0 when the success flags equal the goal's
one-hot vector, else -1; ``info["is_success"]`` is 1 then); episodes never
terminate, the time limit (25 steps, the paper's; ``max_episode_steps=50``
for UOF's tests) truncates them. Everything is computed by the shared tensor
functions of :mod:`torchrl_offhrl.blockstack.goals`.

Deviations from UOF, each a constructor argument: blocks weigh
``block_mass=2.0`` kg (gymnasium-robotics' object mass; UOF's 50 kg blocks
slip out of a MuJoCo grasp while carried, and its task-1 red block weighs
50 t: pass ``block_mass=(50000, 50)`` for UOF's task 1), and blocks start at
least ``min_block_distance=0.1`` m apart (UOF lets them overlap: ``0``).
"""
from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from ..registry import stacking_tasks, task_of
from . import goals as G

__all__ = ["BLOCK_COLOURS", "BlockStackEnv", "blockstack_xml", "make_blockstack_env", "register_blockstack_envs"]

BLOCK_COLOURS = ("red", "blue", "green")
_RGBA = {"red": "0.85 0.1 0.1 1", "blue": "0.1 0.2 0.85 1", "green": "0.1 0.7 0.2 1"}
#: registered id -> number of blocks
DEFAULT_HORIZON = 25


def _fetch_assets() -> Path:
    import gymnasium_robotics

    return Path(gymnasium_robotics.__file__).resolve().parent / "envs" / "assets"


@lru_cache(maxsize=None)
def blockstack_xml(n_blocks: int, masses: tuple[float, ...]) -> str:
    """The MJCF of the table scene with ``n_blocks`` free 5 cm blocks (gymnasium-robotics' pick-and-place scene, its object replaced)."""
    assets = _fetch_assets()
    blocks = "\n".join(
        f'''    <body name="{c}" pos="{1.1 + 0.1 * i} 0.5 0.425">
      <joint name="{c}:joint" type="free" damping="0.01"/>
      <geom size="0.025 0.025 0.025" type="box" condim="3" name="{c}" rgba="{_RGBA[c]}" mass="{m}"/>
      <site name="{c}" pos="0 0 0" size="0.02 0.02 0.02" rgba="{_RGBA[c]}" type="sphere"/>
    </body>''' for i, (c, m) in enumerate(zip(BLOCK_COLOURS[:n_blocks], masses)))
    return f'''<?xml version="1.0" encoding="utf-8"?>
<mujoco>
  <compiler angle="radian" coordinate="local" meshdir="{assets / 'stls' / 'fetch'}" texturedir="{assets / 'textures'}"/>
  <option timestep="0.002"><flag warmstart="enable"/></option>
  <include file="{assets / 'fetch' / 'shared.xml'}"/>
  <worldbody>
    <geom name="floor0" pos="0.8 0.75 0" size="0.85 0.7 1" type="plane" condim="3" material="floor_mat"/>
    <body name="floor0" pos="0.8 0.75 0">
      <site name="target0" pos="0 0 0.5" size="0.02 0.02 0.02" rgba="1 1 0 0.5" type="sphere"/>
    </body>
    <include file="{assets / 'fetch' / 'robot.xml'}"/>
    <body pos="1.3 0.75 0.2" name="table0">
      <geom size="0.25 0.35 0.2" type="box" mass="2000" material="table_mat"/>
    </body>
{blocks}
    <light directional="true" ambient="0.2 0.2 0.2" diffuse="0.8 0.8 0.8" specular="0.3 0.3 0.3" castshadow="false" pos="0 0 4" dir="0 0 -1" name="light0"/>
  </worldbody>
  <actuator>
    <position ctrllimited="true" ctrlrange="0 0.2" joint="robot0:l_gripper_finger_joint" kp="30000" name="robot0:l_gripper_finger_joint" user="1"/>
    <position ctrllimited="true" ctrlrange="0 0.2" joint="robot0:r_gripper_finger_joint" kp="30000" name="robot0:r_gripper_finger_joint" user="1"/>
  </actuator>
</mujoco>'''


def _fetch_base():
    from gymnasium.utils import EzPickle
    from gymnasium_robotics.envs.fetch.fetch_env import MujocoFetchEnv

    return MujocoFetchEnv, EzPickle


def _make_class():
    MujocoFetchEnv, EzPickle = _fetch_base()

    class BlockStackEnv(MujocoFetchEnv, EzPickle):
        """Block stacking with ``n_blocks`` blocks on the Fetch robot (module docstring: tasks, observations, rewards, deviations from UOF).

        Args:
            n_blocks: 2 (task 1) or 3 (task 2).
            block_mass: kg, one number for every block or one per block (red, blue[, green]).
            min_block_distance: blocks start at least this far apart in x, y (m); 0 lets them overlap (UOF).
            obj_range: each block starts at the gripper's initial x, y plus ``U(-obj_range, obj_range)^2``,
                at least 0.1 m from it (UOF and gymnasium-robotics: 0.15).
            goal: every episode's goal (``None``: drawn uniformly at each reset); ``reset(options={"goal": k})``
                sets one episode's.
            render_mode, width, height: as gymnasium-robotics' Fetch envs (``rgb_array`` with ``MUJOCO_GL=egl`` off-screen).
        """

        def __init__(self, n_blocks: int = 2, block_mass: float | Sequence[float] = 2.0, min_block_distance: float = 0.1,
                     obj_range: float = 0.15, goal: int | None = None, **kwargs):
            self.n_blocks = G.check_blocks(n_blocks)
            if goal is not None and not 0 <= int(goal) < G.n_goals(self.n_blocks):
                raise ValueError(f"goal must be in [0, {G.n_goals(self.n_blocks)}) for {self.n_blocks} blocks, got {goal}")
            self.fixed_goal = None if goal is None else int(goal)
            masses = (float(block_mass),) * self.n_blocks if np.isscalar(block_mass) else tuple(float(m) for m in block_mass)
            if len(masses) != self.n_blocks or not all(m > 0 for m in masses):
                raise ValueError(f"block_mass must be a positive number or {self.n_blocks} positive numbers (red, blue[, green]), got {block_mass!r}")
            if min_block_distance < 0 or min_block_distance > obj_range:
                raise ValueError(f"min_block_distance must be in [0, obj_range={obj_range}], got {min_block_distance}")
            self.block_masses, self.min_block_distance = masses, float(min_block_distance)
            self.blocks = BLOCK_COLOURS[: self.n_blocks]
            self.n_goals = G.n_goals(self.n_blocks)
            self._goal_index = None
            self._xml = blockstack_xml(self.n_blocks, masses)
            initial_qpos = {"robot0:slide0": 0.405, "robot0:slide1": 0.48, "robot0:slide2": 0.0}
            # the model path must exist for the base class; the scene itself is built from self._xml
            MujocoFetchEnv.__init__(
                self, model_path=str(_fetch_assets() / "fetch" / "pick_and_place.xml"), has_object=False, block_gripper=False,
                n_substeps=20, gripper_extra_height=0.2, target_in_the_air=False, target_offset=0.0, obj_range=float(obj_range),
                target_range=0.15, distance_threshold=G.SUCCESS_DISTANCE, initial_qpos=initial_qpos, reward_type="sparse", **kwargs)
            EzPickle.__init__(self, n_blocks=n_blocks, block_mass=block_mass, min_block_distance=min_block_distance, obj_range=obj_range, goal=goal,
                              **kwargs)
            from gymnasium import spaces

            obs = self._get_obs()
            self.observation_space = spaces.Dict({
                k: spaces.Box(-np.inf, np.inf, shape=v.shape, dtype="float64") for k, v in obs.items()})

        # --- simulation -------------------------------------------------------------------------------------
        def _initialize_simulation(self):
            self.model = self._mujoco.MjModel.from_xml_string(self._xml)
            self.data = self._mujoco.MjData(self.model)
            self._model_names = self._utils.MujocoModelNames(self.model)
            self.model.vis.global_.offwidth = self.width
            self.model.vis.global_.offheight = self.height
            self._env_setup(initial_qpos=self.initial_qpos)
            self.initial_time = self.data.time
            self.initial_qpos = np.copy(self.data.qpos)
            self.initial_qvel = np.copy(self.data.qvel)

        def _reset_sim(self):
            super()._reset_sim()  # the robot's initial state
            centre = self.initial_gripper_xpos[:2]
            placed: list[np.ndarray] = []
            for c in self.blocks:
                for _ in range(10_000):
                    xy = centre + self.np_random.uniform(-self.obj_range, self.obj_range, size=2)
                    if np.linalg.norm(xy - centre) >= 0.1 and all(np.linalg.norm(xy - p) >= self.min_block_distance for p in placed):
                        break
                placed.append(xy)
                qpos = self._utils.get_joint_qpos(self.model, self.data, f"{c}:joint").copy()
                qpos[:3] = (*xy, G.REST_Z)
                qpos[3:] = (1.0, 0.0, 0.0, 0.0)
                self._utils.set_joint_qpos(self.model, self.data, f"{c}:joint", qpos)
                self._utils.set_joint_qvel(self.model, self.data, f"{c}:joint", np.zeros(6))
            self._mujoco.mj_forward(self.model, self.data)
            return True

        def reset(self, *, seed=None, options=None):
            """``options={"goal": k}`` fixes the episode's goal (default: uniform over the task's goals)."""
            goal = None if options is None else options.get("goal")
            if goal is not None and not 0 <= int(goal) < self.n_goals:
                raise ValueError(f"options['goal'] must be in [0, {self.n_goals}) for {self.n_blocks} blocks, got {goal}")
            self._goal_index = goal
            return super().reset(seed=seed, options=options)

        def _sample_goal(self):
            k = self._goal_index if self._goal_index is not None else self.fixed_goal
            k = int(k) if k is not None else int(self.np_random.integers(self.n_goals))
            return np.eye(self.n_goals)[k]

        # --- observations, goals, rewards ---------------------------------------------------------------------
        def _get_obs(self):
            u, m, d = self._utils, self.model, self.data
            dt = self.n_substeps * m.opt.timestep
            grip = u.get_site_xpos(m, d, "robot0:grip").copy()
            grip_vel = u.get_site_xvelp(m, d, "robot0:grip") * dt
            if getattr(self, "_finger_adr", None) is None:  # the two finger joints' qpos / qvel addresses (gymnasium-robotics' robot_get_obs
                # reads every robot joint by name at each step; the observation takes the last two, the fingers)
                names = [n for n in self._model_names.joint_names if n.startswith("robot")][-2:]
                ids = [self._model_names.joint_name2id[n] for n in names]
                self._finger_adr = (m.jnt_qposadr[ids].copy(), m.jnt_dofadr[ids].copy())
            qadr, vadr = self._finger_adr
            positions, velocities = [], []
            for c in self.blocks:
                pos = u.get_site_xpos(m, d, c).copy()
                positions.append(np.concatenate([pos, grip - pos]))
                velocities.append(np.concatenate([grip_vel - u.get_site_xvelp(m, d, c) * dt, u.get_site_xvelr(m, d, c) * dt]))
            obs = np.concatenate([grip, grip_vel, d.qvel[vadr] * dt, d.qpos[qadr], *positions, *velocities])
            t = torch.from_numpy(obs)
            goal = self.goal if np.size(self.goal) == self.n_goals else np.zeros(self.n_goals)
            fields = G.goal_fields(t, self.n_blocks)
            return {"observation": obs, "desired_goal": np.asarray(goal, dtype=np.float64).copy(), **{k: v.numpy() for k, v in fields.items()}}

        def compute_reward(self, achieved_goal, desired_goal, info):
            """The high level's reward (:func:`torchrl_offhrl.blockstack.goals.goal_reward`), batched as gymnasium-robotics' goal envs."""
            r = G.goal_reward(np.asarray(achieved_goal), np.asarray(desired_goal)).double().numpy()
            return float(r) if r.ndim == 0 else r

        def _is_success(self, achieved_goal, desired_goal):
            return float(self.compute_reward(achieved_goal, desired_goal, None) == 0)

        def _render_callback(self):
            # the yellow target marks where the gripper must go for the episode's goal
            if np.size(self.goal) == self.n_goals:
                target = self._get_obs()["sub_goals"][int(np.argmax(self.goal)), 2:5]
                offset = (self.data.site_xpos - self.model.site_pos)[0]
                site_id = self._mujoco.mj_name2id(self.model, self._mujoco.mjtObj.mjOBJ_SITE, "target0")
                self.model.site_pos[site_id] = target - offset
            self._mujoco.mj_forward(self.model, self.data)

    BlockStackEnv.__module__ = __name__
    return BlockStackEnv


_CLASS = None


def __getattr__(name):  # the class is built on first use: importing this module does not import gymnasium-robotics
    global _CLASS
    if name == "BlockStackEnv":
        if _CLASS is None:
            _CLASS = _make_class()
        return _CLASS
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _entry_point(**kwargs):
    return __getattr__("BlockStackEnv")(**kwargs)


def register_blockstack_envs() -> None:
    """Register ``BlockStack2-v0`` / ``BlockStack3-v0`` with Gymnasium (25 steps; ``gymnasium.make(id, max_episode_steps=50)`` for 50)."""
    import gymnasium

    for env_id, task in stacking_tasks().items():  # the task registry's stacking tasks
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point=f"{__name__}:_entry_point", max_episode_steps=DEFAULT_HORIZON, kwargs={"n_blocks": task.n_blocks})


def make_blockstack_env(env_id: str, num_envs: int = 1, device="cpu", goals: Sequence[int] | None = None, **gym_kwargs):
    """``num_envs`` copies of a block-stacking env batched by TorchRL's ``SerialEnv``, float32.

    ``goals`` (one per copy) fixes each copy's goal for every episode, e.g.
    ``[k for k in range(3) for _ in range(30)]`` for UOF's evaluation of 30
    episodes per goal in one batch; ``None`` draws them at each reset.

    Each copy is TorchRL's ``GymEnv(env_id, **gym_kwargs)`` (e.g.
    ``max_episode_steps=50``, ``block_mass=50.0``); the batch resets each
    copy on its own when its episode ends. Why not Gymnasium's vector env as
    for the locomotion envs: TorchRL 0.14's reader of a vector env's final
    observations fails on dict observations at the first autoreset.
    """
    from torchrl.envs import DoubleToFloat, SerialEnv, TransformedEnv

    if not task_of(env_id).goal_conditioned:
        raise ValueError(f"{env_id!r} is not a block-stacking env; they are {', '.join(stacking_tasks())}")
    register_blockstack_envs()
    if goals is not None and len(goals) != int(num_envs):
        raise ValueError(f"goals must give one goal per env ({num_envs}), got {len(goals)}")
    make = _EnvFactory(env_id, gym_kwargs)
    kwargs = [{}] * int(num_envs) if goals is None else [{"goal": int(g)} for g in goals]
    batched = SerialEnv(int(num_envs), make, create_env_kwargs=kwargs, device=device)
    return TransformedEnv(batched, DoubleToFloat())


class _EnvFactory:
    """A picklable ``GymEnv`` constructor (so that the batch can also go to TorchRL's ``ParallelEnv`` workers)."""

    def __init__(self, env_id: str, gym_kwargs: dict):
        self.env_id, self.gym_kwargs = env_id, dict(gym_kwargs)

    def __call__(self, **kwargs):
        from torchrl.envs import GymEnv

        register_blockstack_envs()
        return GymEnv(self.env_id, **{**self.gym_kwargs, **kwargs})
