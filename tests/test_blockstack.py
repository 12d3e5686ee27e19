"""Block stacking: hand-computed sub-goals and rewards, the Gymnasium envs through TorchRL, the scripted controller, the datasets."""
from __future__ import annotations

import pytest
import torch

from torchrl_offhrl.blockstack import goals as G

RED, BLUE, GREEN = (1.20, 0.70, 0.425), (1.40, 0.80, 0.425), (1.30, 0.62, 0.425)
W, E = G.GRASP_WIDTH, G.END_POINT


def make_obs(gripper, fingers, blocks) -> torch.Tensor:
    """An observation of UOF's layout with the given gripper, fingers and block positions (velocities 0)."""
    n = len(blocks)
    obs = torch.zeros(G.obs_dim(n), dtype=torch.float64)
    obs[0:3] = torch.tensor(gripper)
    obs[8:10] = torch.tensor(fingers)
    for c, pos in enumerate(blocks):
        obs[10 + 6 * c: 13 + 6 * c] = torch.tensor(pos)
        obs[13 + 6 * c: 16 + 6 * c] = torch.tensor(gripper) - torch.tensor(pos)
    return obs


def above(pos, dz):
    return (pos[0], pos[1], pos[2] + dz)


def test_sub_goals_of_task_1_by_hand():
    obs = make_obs((1.3, 0.75, 0.5), (0.0, 0.0), [RED, above(BLUE, 0.03)])  # blue lifted 3 cm: its sub-goal entries are at rest height
    sub = G.sub_goals(obs, 2)
    expect = torch.tensor([
        [W, W, 1.40, 0.80, 0.430, *RED, *BLUE],
        [W, W, 1.20, 0.70, 0.480, *RED, 1.20, 0.70, 0.475],
        [0.005, 0.005, *E, *RED, 1.20, 0.70, 0.475],
    ], dtype=torch.float64)
    assert sub.shape == (3, 11)
    torch.testing.assert_close(sub, expect)
    torch.testing.assert_close(G.achieved_sub_goal(obs, 2), torch.tensor([0.0, 0.0, 1.3, 0.75, 0.5, *RED, 1.40, 0.80, 0.455], dtype=torch.float64))


def test_sub_goals_of_task_2_move_green_and_keep_blue_at_rest():
    obs = make_obs((1.3, 0.75, 0.5), (0.0, 0.0), [RED, BLUE, GREEN])
    sub = G.sub_goals(obs, 3)
    assert sub.shape == (6, 14) and G.sub_goal_dim(3) == 14 and G.n_goals(3) == 6
    torch.testing.assert_close(sub[0], torch.tensor([W, W, 1.40, 0.80, 0.430, *RED, *BLUE, *GREEN], dtype=torch.float64))
    torch.testing.assert_close(sub[3], torch.tensor([W, W, 1.30, 0.62, 0.430, *RED, *BLUE, *GREEN], dtype=torch.float64))
    torch.testing.assert_close(sub[4], torch.tensor([W, W, 1.20, 0.70, 0.480, *RED, *BLUE, 1.20, 0.70, 0.475], dtype=torch.float64))
    torch.testing.assert_close(sub[5], torch.tensor([0.005, 0.005, *E, *RED, *BLUE, 1.20, 0.70, 0.475], dtype=torch.float64))


@pytest.mark.parametrize("n_blocks", [2, 3])
def test_each_goal_state_meets_exactly_its_sub_goal(n_blocks):
    others = [GREEN] if n_blocks == 3 else []
    on_red = above(RED, 0.05)
    states = {  # goal -> a state that achieves it
        0: make_obs(above(BLUE, 0.005), (W, W), [RED, BLUE, *others]),
        1: make_obs(above(RED, 0.055), (W, W), [RED, on_red, *others]),
        2: make_obs(E, (0.005, 0.005), [RED, on_red, *others]),
    }
    if n_blocks == 3:
        states.update({
            3: make_obs(above(GREEN, 0.005), (W, W), [RED, BLUE, GREEN]),
            4: make_obs(above(RED, 0.055), (W, W), [RED, BLUE, on_red]),
            5: make_obs(E, (0.005, 0.005), [RED, BLUE, on_red]),
        })
    batch = torch.stack([states[k] for k in sorted(states)])
    flags = G.achieved_goal_flags(batch, n_blocks)
    torch.testing.assert_close(flags, torch.eye(G.n_goals(n_blocks), dtype=flags.dtype))
    # the high level's reward: 0 only for the state's own goal
    desired = torch.eye(G.n_goals(n_blocks))
    rewards = G.goal_reward(flags.unsqueeze(1), desired.unsqueeze(0))  # [state, goal]
    torch.testing.assert_close(rewards, torch.eye(G.n_goals(n_blocks)) - 1)


def test_success_threshold_is_on_the_whole_vector():
    base = make_obs(above(BLUE, 0.005), (W, W), [RED, BLUE])
    for shift, met in ((0.015, True), (0.025, False)):
        obs = base.clone()
        obs[0] += shift  # the gripper off in x only
        assert bool(G.achieved_goal_flags(obs, 2)[0]) is met
    obs = base.clone()
    obs[0] += 0.012
    obs[8] += 0.012  # two 1.2 cm errors: 1.7 cm in norm, still met; three are not
    assert bool(G.achieved_goal_flags(obs, 2)[0])
    obs[1] += 0.012
    assert not bool(G.achieved_goal_flags(obs, 2)[0])
    # a lifted block does not count as resting
    lifted = make_obs(above(BLUE, 0.03), (W, W), [RED, above(BLUE, 0.025)])
    assert not bool(G.achieved_goal_flags(lifted, 2)[0])


def test_sub_goal_reward_and_shapes():
    goal = torch.zeros(4, 11)
    achieved = torch.zeros(4, 11)
    achieved[1, 0] = 0.019
    achieved[2, 0] = 0.021
    achieved[3] = 1.0
    torch.testing.assert_close(G.sub_goal_reward(achieved, goal), torch.tensor([0.0, 0.0, -1.0, -1.0]))
    with pytest.raises(ValueError, match="34 entries"):
        G.sub_goals(torch.zeros(46), 2)
    with pytest.raises(ValueError, match="n_blocks"):
        G.n_goals(4)


def test_options_follow_the_abstract_demonstrations():
    from torchrl_offhrl.data.stacking import first_option, next_option

    assert [G.abstract_demonstration(k, 3) for k in range(6)] == [[0], [0, 1], [0, 1, 2], [3], [3, 4], [3, 4, 5]]
    goal = torch.tensor([2, 2, 1, 5, 0])
    option = first_option(goal)
    assert option.tolist() == [0, 0, 0, 3, 0]
    flags = torch.zeros(5, 6)
    flags[0, 0] = flags[2, 0] = flags[3, 3] = flags[4, 0] = 1  # env 1 has not met its sub-goal
    option = next_option(option, goal, flags)
    assert option.tolist() == [1, 0, 1, 4, 0]  # env 4 is in its goal's option and stays
    flags = torch.zeros(5, 6)
    flags[2, 1] = 1
    assert next_option(option, goal, flags).tolist() == [1, 0, 1, 4, 0]  # goal 1 is the last of its sequence


# ----------------------------------------------------------------------------------------------- the envs
@pytest.mark.parametrize("env_id,n_blocks", [("BlockStack2-v0", 2), ("BlockStack3-v0", 3)])
def test_env_specs_and_goals_match_the_shared_functions(env_id, n_blocks):
    from torchrl.envs import GymEnv
    from torchrl.envs.utils import check_env_specs

    from torchrl_offhrl.data import make_gym_env

    env = GymEnv(env_id)
    check_env_specs(env)
    td = env.rollout(25)
    assert td["observation"].shape == (25, G.obs_dim(n_blocks)) and td["sub_goals"].shape == (25, G.n_goals(n_blocks), G.sub_goal_dim(n_blocks))
    assert td["next", "truncated"][-1].all() and not td["next", "truncated"][:-1].any() and not td["next", "terminated"].any()
    nxt = td["next"]
    torch.testing.assert_close(nxt["achieved_goal"], G.achieved_goal_flags(nxt["observation"], n_blocks))
    torch.testing.assert_close(nxt["sub_goals"], G.sub_goals(nxt["observation"], n_blocks))
    torch.testing.assert_close(nxt["reward"].squeeze(-1), G.goal_reward(nxt["achieved_goal"], nxt["desired_goal"]))
    # batched: each copy resets on its own at the horizon, and the specs hold
    batched = make_gym_env(env_id, num_envs=2, max_episode_steps=5)
    check_env_specs(batched)
    roll = batched.rollout(12, break_when_any_done=False)
    assert roll.shape == (2, 12) and roll["observation"].dtype == torch.float32
    assert roll["next", "truncated"].squeeze(-1)[:, [4, 9]].all() and roll["next", "truncated"].sum() == 4


def test_env_arguments_and_goal_option():
    import gymnasium as gym

    from torchrl_offhrl.blockstack import register_blockstack_envs

    register_blockstack_envs()

    env = gym.make("BlockStack2-v0", block_mass=(50000.0, 50.0), min_block_distance=0.0, max_episode_steps=50)
    assert env.spec.max_episode_steps == 50
    obs, _ = env.reset(seed=3, options={"goal": 2})
    assert obs["desired_goal"].tolist() == [0.0, 0.0, 1.0]
    assert env.unwrapped.block_masses == (50000.0, 50.0)
    env = gym.make("BlockStack3-v0")
    for seed in range(20):  # blocks at least 0.1 m apart and from the gripper, on the table, at rest height
        obs, _ = env.reset(seed=seed)
        blocks = G.block_positions(torch.as_tensor(obs["observation"]), 3)
        d = torch.cdist(blocks[:, :2], blocks[:, :2]) + torch.eye(3)
        assert d.min() >= 0.1 - 1e-9
        assert (torch.linalg.vector_norm(blocks[:, :2] - torch.as_tensor(obs["observation"][:2]), dim=-1) >= 0.1 - 1e-9).all()
        torch.testing.assert_close(blocks[:, 2], torch.full((3,), G.REST_Z, dtype=blocks.dtype), atol=2e-3, rtol=0)
    with pytest.raises(ValueError, match="block_mass"):
        gym.make("BlockStack2-v0", block_mass=(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="goal"):
        env.reset(options={"goal": 6})


# ------------------------------------------------------------------------------------- controller and data
@pytest.mark.parametrize("env_id", ["BlockStack2-v0", "BlockStack3-v0"])
def test_noiseless_script_reaches_every_goal_at_horizon_50(env_id):
    from torchrl_offhrl.data.stacking import scripted_success

    rates = scripted_success(env_id, episodes=10, horizon=50, seed=0)
    assert all(r >= 0.9 for r in rates.values()), rates


def test_collection_is_deterministic_and_its_goal_fields_are_consistent(tmp_path):
    from torchrl_offhrl.data import load_dataset, save_dataset
    from torchrl_offhrl.data.stacking import GOAL_FIELDS, collect_stacking

    kw = dict(num_transitions=100, random_prob=0.1, noise_std=0.1, num_envs=2, seed=5, progress=False)
    ds = collect_stacking("BlockStack2-v0", **kw)
    again = collect_stacking("BlockStack2-v0", **kw)
    assert len(ds) == 100 and ds.num_episodes == 4
    for key in ds.data.keys(True, True):
        assert torch.equal(ds.data[key], again.data[key]), key
    d = ds.data
    assert all(key in d.keys(True, True) for key in GOAL_FIELDS)
    torch.testing.assert_close(d["next", "achieved_goal"], G.achieved_goal_flags(d["next", "observation"], 2))
    torch.testing.assert_close(d["sub_goal"], G.sub_goals(d["observation"], 2)[torch.arange(len(ds)), d["option"]])
    assert torch.equal(d["next", "sub_goal_reward"] == 0, d["next", "option_done"])
    assert torch.equal(d["next", "option_done"].squeeze(-1), d["next", "achieved_goal"].gather(-1, d["option"].unsqueeze(-1)).squeeze(-1) > 0.5)
    torch.testing.assert_close(d["next", "reward"].squeeze(-1), G.goal_reward(d["next", "achieved_goal"], d["desired_goal"]))
    # options never go back within an episode and end no later than the goal
    opt, goal = d["option"].reshape(4, 25), d["desired_goal"].argmax(-1).reshape(4, 25)
    assert (opt[:, 1:] >= opt[:, :-1]).all() and (opt <= goal).all()
    # round trip through HDF5 with the goal fields
    path = save_dataset(ds, tmp_path / "bs.hdf5")
    back = load_dataset(path)
    for key in ds.data.keys(True, True):
        assert torch.equal(ds.data[key], back.data[key]), key
    assert back.metadata["goal_success"] == ds.metadata["goal_success"]


def test_named_stacking_dataset_is_generated_and_cached(tmp_path, monkeypatch):
    from torchrl_offhrl.data import named_dataset
    from torchrl_offhrl.data.catalog import dataset_path

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path))
    ds = named_dataset("blockstack3-medium-expert", num_transitions=150, progress=False, num_envs=2)
    assert len(ds) == 2 * 150 and ds.metadata["level"] == "medium-expert" and set(ds.metadata["goal_success"]) == {str(k) for k in range(6)}
    assert dataset_path("blockstack3-medium-expert", 150, num_envs=2).is_file()
    again = named_dataset("blockstack3-medium-expert", num_transitions=150, progress=False, num_envs=2)
    assert torch.equal(again.data["sub_goal"], ds.data["sub_goal"])
    with pytest.raises(ValueError, match="levels"):
        named_dataset("blockstack2-random", num_transitions=50, progress=False)


def test_affine_sub_goals_equal_the_definition():
    for n in (2, 3):
        for dtype in (torch.float32, torch.float64):
            obs = torch.randn(7, 5, G.obs_dim(n), dtype=dtype)
            torch.testing.assert_close(G.sub_goals(obs, n), G.sub_goals_reference(obs, n))


# ------------------------------------------------------------------------------------------ the model env
@pytest.fixture(scope="module", params=["BlockStack2-v0", "BlockStack3-v0"])
def stacking_models(request):
    from torchrl_offhrl.data.stacking import collect_stacking
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble

    data = collect_stacking(request.param, 200, 0.1, 0.1, num_envs=4, seed=1, progress=False)
    ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(32,), learn_reward=False).fit(data, max_epochs=2, progress=False)
    cvae = ConditionalVAE.for_dataset(data, goal_key="sub_goal", hidden_sizes=(32,)).fit(data, max_epochs=2, progress=False)
    return request.param, data, ens, cvae


def test_composed_model_env_specs_rewards_and_goals(stacking_models):
    from torchrl.envs import Compose, TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from torchrl_offhrl.envs import BlockStackModelEnv, LatentActionTransform, SubGoalTracker

    env_id, data, ens, cvae = stacking_models
    n_blocks = 2 if env_id == "BlockStack2-v0" else 3
    base = BlockStackModelEnv(ens, data, batch_size=[16], seed=0)
    assert base.horizon == 25 and base.penalty == 50.0 and base.termination_fn is None
    env = TransformedEnv(base, Compose(SubGoalTracker(), LatentActionTransform(cvae.decoder, goal_key="sub_goal")))
    check_env_specs(env)
    td = env.rollout(30, break_when_any_done=False)
    nxt = td["next"]
    # rewards: the task's, from the predicted states, unless the step was penalised
    expect = G.goal_reward(nxt["achieved_goal"], td["desired_goal"]).unsqueeze(-1)
    expect = torch.where(nxt["penalized"], torch.full_like(expect, -50.0), expect)
    torch.testing.assert_close(nxt["reward"], expect)
    torch.testing.assert_close(nxt["sub_goals"], G.sub_goals(nxt["observation"], n_blocks))
    torch.testing.assert_close(nxt["achieved_goal"], G.achieved_goal_flags(nxt["observation"], n_blocks))
    # the decoder's goal is the tracked option's sub-goal; the desired goal stays within an episode
    rows = td["sub_goals"].gather(-2, td["option"][..., None, None].expand(*td["option"].shape, 1, td["sub_goal"].shape[-1])).squeeze(-2)
    torch.testing.assert_close(td["sub_goal"], rows)
    same_episode = ~td["next", "done"][:, :-1].squeeze(-1)
    assert torch.equal(td["desired_goal"][:, 1:][same_episode], td["desired_goal"][:, :-1][same_episode])
    assert (td["option"] <= td["desired_goal"].argmax(-1)).all()
    # episodes end at the horizon or on a penalty, never otherwise
    ends = nxt["done"].squeeze(-1)
    assert torch.equal(ends, (nxt["penalized"] | nxt["truncated"]).squeeze(-1))
    assert (nxt["model_step"][nxt["truncated"]] == 25).all()


def test_model_env_goal_draws_and_arguments(stacking_models):
    from torchrl_offhrl.envs import BlockStackModelEnv

    _, data, ens, _ = stacking_models
    n_goals = data.data["desired_goal"].shape[-1]
    env = BlockStackModelEnv(ens, data, batch_size=[3000], seed=0)
    counts = env.reset()["desired_goal"].sum(0)
    assert counts.sum() == 3000 and (counts > 3000 / n_goals * 0.8).all()
    only_last = BlockStackModelEnv(ens, data, batch_size=[50], seed=0, goal_probs=[0] * (n_goals - 1) + [1])
    assert (only_last.reset()["desired_goal"].argmax(-1) == n_goals - 1).all()
    with pytest.raises(ValueError, match="goal_probs"):
        BlockStackModelEnv(ens, data, goal_probs=[1.0])
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import DynamicsEnsemble

    toy = make_toy_dataset(num_episodes=3, episode_length=5)
    with pytest.raises(ValueError, match="block-stacking"):
        BlockStackModelEnv(DynamicsEnsemble.for_dataset(toy, num_models=2, hidden_sizes=(8,), learn_reward=False), toy)


def test_sub_goal_tracker_on_the_real_env_follows_the_collection_rule():
    from torchrl.envs.utils import check_env_specs

    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.envs import SubGoalTracker

    env = make_gym_env("BlockStack3-v0", num_envs=3, max_episode_steps=6).append_transform(SubGoalTracker())
    check_env_specs(env)
    td = env.rollout(14, break_when_any_done=False)
    goal = td["desired_goal"].argmax(-1)
    first = td["next", "done"].squeeze(-1).roll(1, dims=1)
    first[:, 0] = True
    assert torch.equal(td["option"][first], G.first_option(goal[first]))
    later = ~first[:, 1:]
    expect = G.next_option(td["option"][:, :-1], goal[:, :-1], td["next", "achieved_goal"][:, :-1])
    assert torch.equal(td["option"][:, 1:][later], expect[later])


def test_config_fits_goal_conditioned_models_and_builds_the_composed_envs(tmp_path, monkeypatch):
    """`env=blockstack2` composes the paper's goal-conditioned settings; the pipeline fits and composes from them."""
    from torchrl.envs.utils import check_env_specs

    from torchrl_offhrl.recipes.config import compose, model_config, model_env_config, resolve_dataset
    from torchrl_offhrl.recipes.pipeline import fit_or_load_models, make_model_env, make_real_env
    from torchrl_offhrl.recipes.schema import validate_config
    from torchrl_offhrl.utils import to_plain

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path))
    cfg = to_plain(compose("offline_train", ["env=blockstack2", "dataset=medium", "num_transitions=200", "dataset_num_envs=4",
                                             "ensemble.hidden_sizes=[16]", "ensemble.num_models=2", "cvae.hidden_sizes=[16]",
                                             "ensemble.fit.max_steps=20", "cvae.fit.max_steps=20"]))
    validate_config(cfg)
    assert cfg["model_env"]["horizon"] == 25 and cfg["cvae"]["goal_key"] == "sub_goal" and cfg["cvae"]["fit"]["batch_size"] == 128
    assert cfg["ensemble"]["learn_reward"] is False and cfg["env"]["pessimism"]["default"] == {"quantile": 0.99, "penalty": 50.0}
    hopper = to_plain(compose("offline_train", ["env=hopper"]))  # the locomotion settings are untouched
    assert hopper["model_env"]["horizon"] == "auto" and hopper["cvae"]["goal_key"] is None and hopper["ensemble"]["learn_reward"] is True
    data = resolve_dataset(cfg)
    ens, cvae, _ = fit_or_load_models(model_config(cfg), data, progress=False)
    assert ens.reward_net is None and cvae.goal_key == "sub_goal" and cvae.decoder.goal_dim == G.sub_goal_dim(2)
    menv, pess = model_env_config(cfg, data.metadata["level"], data)
    env = make_model_env({"env": {**menv, **pess}, "device": "cpu", "seed": 0}, ens, cvae, data, batch_size=4)
    check_env_specs(env)
    assert env.base_env.penalty == 50.0 and env.base_env.horizon == 25
    td = env.rollout(3)
    assert td["action"].shape == (4, 3, 4) and td["sub_goal"].shape == (4, 3, G.sub_goal_dim(2))
    real = make_real_env("BlockStack2-v0", cvae, num_envs=2)
    check_env_specs(real)


class _Oracle:
    """An 'ensemble' of K identical members that predict the recorded next states (exact lookup), or stand still."""

    def __init__(self, episodes, num_members=3, still=False):
        self.obs = episodes["observation"].reshape(-1, episodes["observation"].shape[-1]).float()
        self.nxt = episodes["next", "observation"].reshape(self.obs.shape).float()
        self.num_members, self.still = num_members, still

    def predict(self, observation, action):
        if self.still:
            nxt = observation
        else:
            idx = torch.cdist(observation, self.obs).argmin(-1)
            nxt = self.nxt[idx]
        nxt = nxt.expand(self.num_members, *nxt.shape)
        return {"next_observation": nxt, "delta": nxt - observation, "reward": None}

    @staticmethod
    def discrepancy_of(delta, kind="variance"):
        return delta.var(0, unbiased=False).sum(-1)


def test_open_loop_replay_of_an_exact_and_of_a_still_model():
    from torchrl_offhrl.data.stacking import collect_stacking
    from torchrl_offhrl.envs.goal_model import replay_open_loop

    ds = collect_stacking("BlockStack2-v0", 150, 0.0, 0.05, num_envs=3, seed=2, progress=False)
    episodes = ds.data.reshape(-1, 25)
    exact = replay_open_loop(_Oracle(episodes), episodes, 2, threshold=1e-9)
    assert exact["gripper_error"].abs().max() < 1e-6 and exact["block_error"].abs().max() < 1e-6
    assert torch.equal(exact["model_success"], exact["real_success"].expand(3, -1))
    assert (exact["cut_step"] == 26).all()  # identical members never disagree
    still = replay_open_loop(_Oracle(episodes, still=True), episodes, 2)
    start, real = episodes["observation"][:, 0], episodes["next", "observation"]
    expect = torch.linalg.vector_norm(real[..., 0:3] - start[:, None, 0:3], dim=-1).mean(0)
    torch.testing.assert_close(still["gripper_error"], expect)
    assert not still["model_success"].any()  # standing at the start reaches no goal


def test_renders_off_screen_with_egl():
    """`render_mode="rgb_array"` with MUJOCO_GL=egl (in a fresh process: the GL backend is chosen when mujoco is imported)."""
    import os
    import subprocess
    import sys

    code = ("import numpy as np, gymnasium as gym, torchrl_offhrl.blockstack\n"
            "env = gym.make('BlockStack3-v0', render_mode='rgb_array', width=64, height=48)\n"
            "env.reset(seed=0, options={'goal': 4})\n"
            "img = env.render()\n"
            "print(img.shape, img.dtype, float(img.std()) > 5)\n")
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, "MUJOCO_GL": "egl"}, capture_output=True, text=True, timeout=120)
    if out.returncode != 0 and ("EGL" in out.stderr or "egl" in out.stderr):
        pytest.skip(f"no EGL on this machine: {out.stderr.strip().splitlines()[-1]}")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "(48, 64, 3) uint8 True"


def test_fixed_goals_per_env_for_per_goal_evaluation():
    from torchrl_offhrl.blockstack import make_blockstack_env

    goals = [0, 0, 1, 2]
    env = make_blockstack_env("BlockStack2-v0", num_envs=4, goals=goals, max_episode_steps=3)
    td = env.rollout(7, break_when_any_done=False)  # crosses two resets
    assert torch.equal(td["desired_goal"].argmax(-1), torch.tensor(goals).unsqueeze(-1).expand(4, 7))
    with pytest.raises(ValueError, match="one goal per env"):
        make_blockstack_env("BlockStack2-v0", num_envs=2, goals=[0])
    import gymnasium as gym

    with pytest.raises(ValueError, match="goal must be"):
        gym.make("BlockStack2-v0", goal=3)
