"""UOF and the goal-conditioned baselines: the low-level loss by hand, the option policy's rules, HER keys, per-goal evaluation, the recipe."""
from __future__ import annotations

import json
import math
from importlib import import_module
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from torchrl_offhrl.blockstack import goals as G
from torchrl_offhrl.objectives import TwinDDPGLoss


# ------------------------------------------------------------------------------------------ the low-level loss
class Const(torch.nn.Module):
    """An affine map of its last input (the action) with one bias: Q(s, g, a) = w . a + b."""

    def __init__(self, dim):
        super().__init__()
        self.lin = torch.nn.Linear(dim, 1)

    def forward(self, obs, goal, action):
        return self.lin(action)


def twin_loss(q_bias, target_q_bias, target_action, **kwargs):
    actor = TensorDictModule(torch.nn.Linear(2, 1), in_keys=["observation"], out_keys=["action"])
    critic = TensorDictModule(Const(1), in_keys=["observation", "goal", "action"], out_keys=["state_action_value"])
    loss = TwinDDPGLoss(actor, critic, **kwargs)
    with torch.no_grad():
        for p in (loss.actor_network_params, loss.target_actor_network_params):
            p["module", "weight"].data.zero_()
            p["module", "bias"].data.zero_()
        loss.target_actor_network_params["module", "bias"].data.fill_(target_action)
        for params, b in ((loss.qvalue_network_params, q_bias), (loss.target_qvalue_network_params, target_q_bias)):
            params["module", "lin", "weight"].data.fill_(1.0)  # Q = a + b_j
            params["module", "lin", "bias"].data.copy_(torch.tensor(b).unsqueeze(-1))
    return loss


def low_batch(action, reward, done):
    n = len(action)
    return TensorDict({"observation": torch.randn(n, 2), "goal": torch.randn(n, 3), "action": torch.tensor(action).unsqueeze(-1),
                       "next": {"observation": torch.randn(n, 2), "goal": torch.randn(n, 3), "reward": torch.tensor(reward).unsqueeze(-1),
                                "done": torch.tensor(done).unsqueeze(-1)}}, batch_size=[n])


def test_twin_ddpg_targets_losses_and_gradients_by_hand():
    # critics Q_j(s, g, a) = a + b_j; targets: b' = (-3, -5), the target actor's action 1 -> min Q' = 1 - 5 = -4
    loss = twin_loss([0.5, -1.0], [-3.0, -5.0], 1.0)
    td = low_batch(action=[0.0, 2.0, -1.0], reward=[-1.0, 0.0, -1.0], done=[False, True, False])
    y = torch.tensor([-1.0 + 0.98 * -4.0, 0.0, -1.0 + 0.98 * -4.0])
    torch.testing.assert_close(loss.target(td), y)
    out = loss(td)
    q1 = torch.tensor([0.5, 2.5, -0.5])
    q2 = torch.tensor([-1.0, 1.0, -2.0])
    torch.testing.assert_close(out["loss_qvalue"], ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean())
    # the actor (action 0 from its zero weights and bias 0) is scored by min_j Q_j(s, g, 0) = min(0.5, -1) = -1
    torch.testing.assert_close(out["loss_actor"], torch.tensor(1.0))
    out["loss_actor"].backward()
    assert loss.actor_network_params["module", "bias"].grad is not None
    assert loss.qvalue_network_params["module", "lin", "bias"].grad is None  # the critics do not learn from the actor's loss
    loss.zero_grad()
    out = loss(td)
    out["loss_qvalue"].backward()
    assert loss.qvalue_network_params["module", "lin", "bias"].grad.abs().sum() > 0
    assert loss.actor_network_params["module", "bias"].grad is None or loss.actor_network_params["module", "bias"].grad.abs().sum() == 0


def test_twin_ddpg_targets_are_clamped_to_uofs_range():
    loss = twin_loss([0.0, 0.0], [30.0, 40.0], 0.0)
    td = low_batch(action=[0.0, 0.0], reward=[-1.0, -30.0], done=[False, True])
    torch.testing.assert_close(loss.target(td), torch.tensor([0.0, -25.0]))  # -1 + 0.98 * 30 > 0 -> 0; -30 -> -25
    free = twin_loss([0.0, 0.0], [30.0, 40.0], 0.0, target_range=None)
    torch.testing.assert_close(free.target(td), torch.tensor([-1.0 + 0.98 * 30.0, -30.0]))
    with pytest.raises(ValueError, match="target_range"):
        twin_loss([0.0, 0.0], [0.0, 0.0], 0.0, target_range=(0.0, -1.0))


# ------------------------------------------------------------------------------------------ HER keys for the low level
def test_low_level_annotation_rewards_penalty_segments_and_done():
    from torchrl_offhrl.agents.her import LOW_DONE, LOW_REWARD, SEGMENT_END, low_level_done, prepare_low_level

    E, T, d = 2, 3, 11
    sub = torch.zeros(E, T, d)
    achieved = torch.ones(E, T, d)
    achieved[0, 1] = 0.0  # env 0 meets its sub-goal at s' of step 1
    flags = torch.zeros(E, T, 3)
    flags[0, 1, 1] = 1.0  # ... which is option 1's
    penalized = torch.zeros(E, T, 1, dtype=torch.bool)
    penalized[1, 0] = True
    td = TensorDict({"sub_goal": sub, "option": torch.ones(E, T, dtype=torch.long),
                     "next": {"achieved_sub_goal": achieved, "achieved_goal": flags, "penalized": penalized,
                              "reward": torch.where(penalized, torch.full((E, T, 1), -50.0), torch.full((E, T, 1), -1.0)),
                              "done": penalized.clone(), "terminated": penalized.clone()}}, batch_size=[E, T])
    prepare_low_level(td)
    torch.testing.assert_close(td[LOW_REWARD].squeeze(-1), torch.tensor([[-1.0, 0.0, -1.0], [-50.0, -1.0, -1.0]]))
    # segments end where the option's sub-goal is met, at an episode's end, and at each env's last step of the batch
    assert td[SEGMENT_END].squeeze(-1).tolist() == [[False, True, True], [True, False, True]]
    assert torch.equal(td["next", "sub_goal"], td["sub_goal"])
    assert td["next", "option_done"].squeeze(-1).tolist() == [[False, True, False], [False, False, False]]
    low_level_done(td)
    assert td[LOW_DONE].squeeze(-1).tolist() == [[False, True, False], [True, False, False]]
    # SB3's HER (SAC + HER, terminal_on_success=False): the met sub-goal does not stop the bootstrap, the penalty still does
    low_level_done(td, on_success=False)
    assert td[LOW_DONE].squeeze(-1).tolist() == [[False, False, False], [True, False, False]]


# ------------------------------------------------------------------------------------------ the option policy
@pytest.fixture(scope="module")
def stacking_env():
    from torchrl_offhrl.data.stacking import collect_stacking
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    data = collect_stacking("BlockStack2-v0", 200, 0.1, 0.1, num_envs=4, seed=1, progress=False)
    ens = DynamicsEnsemble.for_dataset(data, num_models=2, hidden_sizes=(16,), learn_reward=False).fit(data, max_epochs=1, progress=False)
    cvae = ConditionalVAE.for_dataset(data, goal_key="sub_goal", hidden_sizes=(16,)).fit(data, max_epochs=1, progress=False)
    cfg = {"env": {"penalty": 50.0, "quantile": 0.99, "horizon": 25}, "seed": 0}
    return data, lambda n: make_model_env(cfg, ens, cvae, data, batch_size=n)


def make_uof(env, data, **kw):
    from torchrl_offhrl.agents import make_agent

    stats = data.stats()
    agent = make_agent("uof", env, {"hidden_sizes": [16], "batch_size": 8, "frames_per_batch": 40, **kw}, obs_loc=stats.obs_mean,
                       obs_scale=stats.obs_std, goal_key="sub_goal")
    agent.attach(env)
    return agent


def test_uof_options_persist_until_their_sub_goal_is_met(stacking_env):
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    data, make_env = stacking_env
    env = make_env(8)
    agent = make_uof(env, data, demo_ratio=0.0)
    agent.policy.epsilon = 1.0  # every pick at random: an option can only stay by the rule
    torch.manual_seed(0)
    td = env.rollout(25, agent.policy, break_when_any_done=False)
    option, start = td["option"], td["option_start"]
    met_before = G.option_met(option[:, :-1], td["next", "achieved_goal"][:, :-1])
    # a new pick happens exactly at episode starts and where the running option's sub-goal was met at s
    expect = td["is_init"][:, 1:].squeeze(-1) | met_before
    assert torch.equal(start[:, 1:], expect) and start[:, 0].all()
    assert torch.equal(option[:, 1:][~expect], option[:, :-1][~expect])
    assert torch.equal(td["next", "prev_option"], option)  # carried to the next step
    rows = td["sub_goals"].gather(-2, option[..., None, None].expand(*option.shape, 1, 11)).squeeze(-2)
    assert torch.equal(td["sub_goal"], rows)  # the low level (and the decoder) pursue the option's sub-goal
    # greedy at test: the first target network's best option
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.rollout(3, agent.policy, break_when_any_done=False)
    picked = td["option_start"]
    assert torch.equal(td["option"][picked], agent.policy.option_values(td).argmax(-1)[picked])


def test_uof_demonstration_episodes_follow_the_abstract_demonstration(stacking_env):
    data, make_env = stacking_env
    env = make_env(8)
    agent = make_uof(env, data, demo_ratio=1.0)
    torch.manual_seed(1)
    td = env.rollout(25, agent.policy, break_when_any_done=False)
    assert td["next", "demo_episode"].all()  # decided at each episode start, carried to the next steps
    goal = td["desired_goal"].argmax(-1)
    first = td["is_init"].squeeze(-1)
    assert torch.equal(td["option"][first], G.first_option(goal[first]))
    nxt = G.next_option(td["option"][:, :-1], goal[:, :-1], td["next", "achieved_goal"][:, :-1])
    cont = ~first[:, 1:]
    assert torch.equal(td["option"][:, 1:][cont], nxt[cont])


def test_uof_oracle_options_follow_the_demonstration_at_test_and_only_when_asked(stacking_env):
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    data, make_env = stacking_env
    env = make_env(8)
    agent = make_uof(env, data, demo_ratio=0.0)
    goal_of = lambda td: td["desired_goal"].argmax(-1)  # noqa: E731
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        torch.manual_seed(2)
        greedy = env.rollout(25, agent.policy, break_when_any_done=False)
        agent.policy.oracle_options = True
        torch.manual_seed(2)
        oracle = env.rollout(25, agent.policy, break_when_any_done=False)
    # the oracle run's options are the env's demonstration: the goal's first option, then the next one each time it is met
    first = oracle["is_init"].squeeze(-1)
    assert torch.equal(oracle["option"][first], G.first_option(goal_of(oracle)[first]))
    nxt = G.next_option(oracle["option"][:, :-1], goal_of(oracle)[:, :-1], oracle["next", "achieved_goal"][:, :-1])
    assert torch.equal(oracle["option"][:, 1:][~first[:, 1:]], nxt[~first[:, 1:]])
    assert oracle["next", "demo_episode"].all() and not greedy["next", "demo_episode"].any()
    # without the switch the same policy picks greedily (its untrained values are not the demonstration everywhere)
    picked = greedy["option_start"]
    assert torch.equal(greedy["option"][picked], agent.policy.option_values(greedy).argmax(-1)[picked])
    # and in training (RANDOM) the switch changes nothing: demonstrations stay at demo_ratio (0 here)
    with set_exploration_type(ExplorationType.RANDOM):
        td = env.rollout(5, agent.policy, break_when_any_done=False)
    assert not td["next", "demo_episode"].any()


def test_uof_update_learns_both_levels_and_counts_episodes(stacking_env):
    from torchrl.collectors import Collector

    data, make_env = stacking_env
    env = make_env(4)
    agent = make_uof(env, data)
    before = {k: v.clone() for k, v in agent.loss.state_dict().items()}
    col = Collector(env, agent.policy, frames_per_batch=100, total_frames=200, auto_register_policy_transforms=False)
    for batch in col:
        out = agent.update(batch)
    col.shutdown()
    assert out["updates"] == 10 and agent.episodes >= 4  # 0.1 updates per frame; 4 envs started their episodes
    assert 0 < agent.policy.epsilon < 1
    after = agent.loss.state_dict()
    for part in ("high.value_network_params", "low.actor_network_params", "low.qvalue_network_params", "low.target_qvalue_network_params"):
        moved = [k for k in after if k.startswith(part) and not torch.equal(after[k], before[k])]
        assert moved, part
    assert len(agent.replay_buffer["high"]) == len(agent.replay_buffer["low"]) == 200
    # the high level's reward: the env's only where the running option is the goal's (or a penalty), else -1
    sample = agent.replay_buffer["high"][:]
    own = sample["option"] == sample["desired_goal"].argmax(-1)
    assert (sample["next", "high_reward"][~own] == -1).all() or (sample["next", "high_reward"][~own] <= -1).all()


def test_uof_exploration_ema_follows_the_evaluation_success(stacking_env):
    data, make_env = stacking_env
    agent = make_uof(make_env(2), data)
    E, T = 4, 3
    reward = torch.full((E, T, 1), -1.0)
    reward[0, 2] = 0.0  # goal 0: one of two episodes succeeds
    rollout = TensorDict({"desired_goal": torch.nn.functional.one_hot(torch.tensor([0, 0, 1, 1]), 3).float().unsqueeze(1).expand(E, T, 3),
                          "option": torch.zeros(E, T, dtype=torch.long), "next": {"reward": reward}}, batch_size=[E, T])
    out = agent.evaluation_metrics(rollout, torch.ones(E, T, dtype=torch.bool))
    torch.testing.assert_close(agent.policy.success_ema, torch.tensor([0.025, 0.0, 0.0]))  # goal 2 had no episode: unchanged
    assert out["option_usage_mean"] == [1.0, 0.0, 0.0]


# ------------------------------------------------------------------------------------------ the recipe
TINY = ["eval.episodes=2", "ensemble.hidden_sizes=[16]", "ensemble.num_models=2", "ensemble.fit.max_steps=30", "cvae.hidden_sizes=[16]",
        "cvae.fit.max_steps=30", "algo.batch_size=16", "algo.hidden_sizes=[16]"]


@pytest.fixture(scope="module")
def stacking_file(tmp_path_factory):
    from torchrl_offhrl.data import save_dataset
    from torchrl_offhrl.data.stacking import generate_stacking_dataset

    path = tmp_path_factory.mktemp("bs") / "bs2.hdf5"
    save_dataset(generate_stacking_dataset("BlockStack2-v0", "medium", 800, seed=0, progress=False), path)
    return path


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.mark.parametrize("algo,budget", [("uof", ["train.total_frames=800", "eval.every_frames=400", "algo.buffer_size=5000"]),
                                         ("sac_her", ["train.total_frames=800", "eval.every_frames=400", "algo.buffer_size=5000", "algo.utd_ratio=0.1"]),
                                         ("bc", ["train.total_updates=40", "eval.every_updates=20"])])
def test_goal_conditioned_agents_train_evaluate_per_goal_and_resume(algo, budget, stacking_file, shared_cache, tmp_path, monkeypatch):
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.utils import to_plain

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(shared_cache))  # the models are fitted once for the three agents
    over = [f"algo={algo}", "env=blockstack2", f"dataset={stacking_file}", f"run_dir={tmp_path / 'run'}", *TINY]
    summary = train(to_plain(compose("offline_train", [*over, *budget])), progress=False)
    run = Path(summary["run_dir"])
    evals = json.loads((run / "evals.json").read_text())
    assert len(evals) == 3
    for e in evals:  # 2 episodes of each of the 3 goals: success shares in {0, 0.5, 1}, at horizons 25 and 50
        assert len(e["success_per_goal"]) == len(e["success_per_goal_h50"]) == 3
        assert all(x in (0.0, 0.5, 1.0) for x in e["success_per_goal"] + e["success_per_goal_h50"])
        assert all(a <= b for a, b in zip(e["success_per_goal"], e["success_per_goal_h50"]))
        assert e["normalized_d4rl"] is None and -25 <= e["return_mean"] <= 0
    assert (run / "success.png").is_file()
    if algo == "uof":
        assert (run / "option_usage.png").is_file()
        usage = torch.load(run / "option_usage.pt")
        assert usage.shape[0] == 3 and usage.shape[2] == 3 and torch.allclose(usage.sum(-1), torch.ones(usage.shape[:2]))
    # a saved run is rebuilt goal-conditioned and evaluated by `offhrl evaluate`
    from torchrl_offhrl.recipes.evaluation import evaluate_run

    res = evaluate_run(run, episodes=3)
    assert len(res["success_per_goal"]) == 3 and 0.0 <= res["success_rate"] <= 1.0
    # resume: a larger budget continues from the checkpoint (the replay buffers included)
    more = [b.replace("800", "1200").replace("=40", "=60") for b in budget]
    again = train(to_plain(compose("offline_train", [*over, *more])), progress=False)
    assert again["step"] in (1200, 60) and len(json.loads((run / "evals.json").read_text())) == 4


def test_flat_agents_are_refused_on_block_stacking_before_any_work(tmp_path):
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.train import train

    for algo in ("ppo", "moc", "iql"):
        cfg = compose("offline_train", [f"algo={algo}", "env=blockstack2", f"run_dir={tmp_path / algo}"])
        with pytest.raises(ValueError, match="not goal-conditioned"):
            train(cfg)
        assert not (tmp_path / algo).exists()
    for algo in ("uof", "sac_her"):  # and the goal-conditioned ones on the locomotion tasks
        cfg = compose("offline_train", [f"algo={algo}", "env=hopper", f"run_dir={tmp_path / algo}"])
        with pytest.raises(ValueError, match="block-stacking tasks only"):
            train(cfg)
        assert not (tmp_path / algo).exists()


def test_online_uof_trains_in_the_real_env_and_its_shipped_policy_collects(stacking_file, tmp_path, monkeypatch):
    """train.online: UOF in the real env (no models); a snapshot ships as a small policy that acts as the agent did and collects data."""
    from tensordict import TensorDict

    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.blockstack import goals as G
    from torchrl_offhrl.cli import main
    from torchrl_offhrl.data import load_dataset
    from torchrl_offhrl.data.stacking import collect_stacking
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.pipeline import make_real_env
    from torchrl_offhrl.recipes.train import train
    from torchrl_offhrl.recipes.uof_policies import is_uof_policy, load_uof_policy, ship_uof_policy, uof_route_dataset
    from torchrl_offhrl.utils import to_plain

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    run = tmp_path / "run"
    over = ["algo=uof", "env=blockstack2", f"dataset={stacking_file}", f"run_dir={run}", "train.online=true", "train.total_frames=800",
            "eval.every_frames=400", "train.snapshot_frames=[400]", "algo.buffer_size=5000", "eval.episodes=2", "algo.batch_size=16",
            "algo.hidden_sizes=[16]"]
    train(to_plain(compose("offline_train", over)), progress=False)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["model_dir"] is None and cfg["resolved_pessimism"] is None and not (tmp_path / "cache" / "models").exists()
    assert [e["step"] for e in json.loads((run / "evals.json").read_text())] == [0, 400, 800]
    assert (run / "snapshot-400.pt").is_file() and not (run / "snapshot-800.pt").exists()
    from torchrl_offhrl.recipes.evaluation import evaluate_run  # `offhrl evaluate`: an online run acts in real actions, no decoder
    assert math.isfinite(evaluate_run(run, episodes=2, policy="last")["return_mean"])
    snap = torch.load(run / "snapshot-400.pt", weights_only=False)

    pt = ship_uof_policy(run, 400, name="bs2-test", dest=tmp_path / "pol")
    card = json.loads(pt.with_suffix(".json").read_text())
    assert card["kind"] == "uof" and card["frames"] == 400 and card["eval"]["success_per_goal"] == snap["record"]["success_per_goal"]
    assert "train.online=true" in card["command"] and is_uof_policy(pt)
    # what is shipped: the actor and one target Q-network (the agent's state holds both levels, twin critics, targets, optimiser)
    shipped = torch.load(pt, weights_only=True)
    assert all(k.startswith(("actor.", "diol.target_value_network_params.")) for k in shipped)
    ctrl = load_uof_policy(pt)
    env = make_real_env("BlockStack2-v0", None, num_envs=4)
    agent = make_agent("uof", env, cfg["algo"], action_key="action", goal_key="sub_goal")
    agent.load_state_dict(snap["agent"])
    td = env.reset()
    obs = {k: td[k] for k in ("observation", "desired_goal", "achieved_goal")}
    assert torch.equal(ctrl.policy.option_values(td), agent.policy.option_values(td))
    option = ctrl.select_option(obs, None)
    assert torch.equal(option, agent.policy.option_values(td).argmax(-1))
    sub_goal = td["sub_goals"].gather(-2, option[:, None, None].expand(-1, 1, td["sub_goals"].shape[-1])).squeeze(-2)
    want = agent.policy.actor(TensorDict({"observation": td["observation"], "sub_goal": sub_goal}, batch_size=[4]))["action"]
    assert torch.allclose(ctrl(td["observation"], option), want)  # the controller's sub-goal is the env's
    env.close()

    ds = collect_stacking("BlockStack2-v0", 100, num_envs=2, controller=ctrl, progress=False, seed=3)
    assert ds.metadata["policy"] == "bs2-test" and ds.metadata["policy_card"]["kind"] == "uof"
    opt, met = ds.data["option"].reshape(-1, 25), G.option_met(ds.data["option"], ds.data["next", "achieved_goal"]).reshape(-1, 25)
    switched = opt[:, 1:] != opt[:, :-1]
    assert not (switched & ~met[:, :-1]).any()  # an option runs until its sub-goal is met
    # the CLI: collect with the shipped policy into a file that `offhrl train dataset=<file>` reads
    out = tmp_path / "uof-data.hdf5"
    assert main(["collect", "blockstack2", "--policy", str(pt), "-n", "50", "--num-envs", "2", "--out", str(out)]) == 0
    back = load_dataset(out)
    assert len(back) == 50 and back.metadata["policy"] == "bs2-test"
    # without --out: into the datasets cache, the noise in the name (greedy and noisy collections never share a file)
    assert main(["collect", "blockstack2", "--policy", str(pt), "-n", "50", "--num-envs", "2", "--random-prob", "0.1"]) == 0
    assert [p.name for p in (tmp_path / "cache" / "datasets").glob("*.hdf5")] == ["blockstack2-bs2-test-50-seed0-envs2-rp0.1-ns0.hdf5"]
    # the results' data route finds that file (same policy, size, noise) and does not collect again
    cached = tmp_path / "cache" / "datasets" / "blockstack2-bs2-test-50-seed0-envs2-rp0.1-ns0.hdf5"
    stamp = cached.stat().st_mtime_ns
    assert uof_route_dataset("blockstack2", pt, 50, num_envs=2, random_prob=0.1) == cached and cached.stat().st_mtime_ns == stamp
    other = uof_route_dataset("blockstack2", pt, 50, num_envs=2, random_prob=0.1, noise_std=0.1)  # other noise: collected anew
    assert other != cached and len(load_dataset(other)) == 50 and load_dataset(other).metadata["noise_std"] == 0.1
    # a shipped UOF policy is listed apart and refused by the behaviour-policy loader with what to use instead
    import torchrl_offhrl.data.policies as pol

    monkeypatch.setattr(pol, "POLICY_DIR", tmp_path / "pol")
    assert pol.list_policies() == [] and pol.list_policies(kind="uof") == ["bs2-test"]
    with pytest.raises(ValueError, match="load_uof_policy"):
        pol.load_policy("bs2-test")

    from torchrl_offhrl.recipes.config import config_fingerprint

    offline = to_plain(compose("offline_train", [o for o in over if o != "train.online=true"]))
    assert config_fingerprint(offline) != config_fingerprint(to_plain(compose("offline_train", over)))  # never resumed as the other
    assert config_fingerprint(to_plain(compose("offline_train", [*over, "train.total_frames=1200"]))) == config_fingerprint(to_plain(compose("offline_train", over)))
    with pytest.raises(FileNotFoundError, match="snapshot-800.pt does not exist"):
        ship_uof_policy(run, 800, dest=tmp_path / "pol")
    with pytest.raises(ValueError, match="multiple of"):
        train(to_plain(compose("offline_train", [*over[:-8], "train.snapshot_frames=[300]", f"run_dir={tmp_path / 'r2'}", "train.online=true",
                                                 "train.total_frames=800", "eval.every_frames=400"])), progress=False)
    with pytest.raises(ValueError, match="learns from the dataset itself"):
        train(to_plain(compose("offline_train", ["algo=bc", "env=blockstack2", f"dataset={stacking_file}", "train.online=true",
                                                 f"run_dir={tmp_path / 'r3'}"])), progress=False)


def test_blockstack_report_reads_archived_runs_and_keeps_lost_groups_from_the_earlier_page(tmp_path, monkeypatch):
    """experiments/results/blockstack.py: a finished run is archived and reported; a group with no archived run is the earlier page's text."""
    mod = import_module("experiments.results.blockstack")
    monkeypatch.setattr(mod, "BASE", tmp_path / "outputs")
    monkeypatch.setattr(mod, "OUT", tmp_path / "docs")
    monkeypatch.setattr(mod, "ARCHIVE", tmp_path / "docs" / "blockstack" / "runs")
    (tmp_path / "docs" / "blockstack").mkdir(parents=True)
    old = "## blockstack2, medium-expert\n\n| agent | seeds | final, horizon 25 |\n|---|---|---|\n| BC | 3 | 1.00 / 1.00 / 0.69 |\n"
    (tmp_path / "docs" / "blockstack" / "legacy.json").write_text(json.dumps({
        "sections": {"blockstack2, medium-expert": old},
        "runs": {"bc-blockstack2-medium-expert-seed4": "1.00 / 1.00 / 0.40 at 20000 updates",
                 "bc-blockstack2-medium-seed4": "0.50 / 0.00 / 0.00 at 20000 updates"}}))
    for seed, last in ((4, [1.0, 0.5, 0.0]), (5, [1.0, 0.7, 0.2])):  # two finished BC runs on task 1 medium
        run = tmp_path / "outputs" / f"bc-blockstack2-medium-seed{seed}"
        run.mkdir(parents=True)
        evals = [{"step": s, "frames": 0, "return_mean": -20.0, "success_per_goal": v, "success_per_goal_h50": v, "success_rate": sum(v) / 3}
                 for s, v in ((0, [0.0, 0.0, 0.0]), (20000, last))]
        (run / "evals.json").write_text(json.dumps(evals))
        (run / "config.json").write_text(json.dumps({"algo": {"name": "bc"}, "env": {"env_id": "BlockStack2-v0"}, "dataset": "medium"}))
        (run / "summary.json").write_text(json.dumps({"unit": "updates", "behaviour_success_per_goal": [0.9, 0.6, 0.3]}))
    text = mod.report()
    assert (tmp_path / "docs" / "blockstack" / "runs" / "bc-blockstack2-medium-seed4" / "evals.json").is_file()
    medium = text.split("## blockstack2, medium\n")[1].split("## ")[0]
    assert ("| BC | 2 | 1.00 [1.00, 1.00] / 0.60 [0.50, 0.70] / 0.10 [0.00, 0.20] | 1.00 [1.00, 1.00] / 0.60 [0.50, 0.70] / 0.10 [0.00, 0.20] | "
            "0.57 [0.50, 0.63] |") in medium and "| data (behaviour) | | 0.90 / 0.60 / 0.30 |" in medium
    assert "## blockstack2, medium-expert *(earlier page)*" in text and "| BC | 3 | 1.00 / 1.00 / 0.69 |" in text
    assert "- `bc-blockstack2-medium-expert-seed4`: 1.00 / 1.00 / 0.40 at 20000 updates (earlier page)" in text
    assert "0.50 / 0.00 / 0.00" not in text  # a lost run rerun since: the archived run's line replaces it
    assert "- `bc-blockstack2-medium-seed4`: 1.00 / 0.50 / 0.00 at 20000 updates\n" in text
    # a rerun of an agent in a group of the earlier page: the earlier section stays, the new runs follow in their own section
    run = tmp_path / "outputs" / "bc-blockstack2-medium-expert-seed7"
    run.mkdir()
    for f in ("evals.json", "config.json", "summary.json"):
        (run / f).write_bytes((tmp_path / "outputs" / "bc-blockstack2-medium-seed5" / f).read_bytes())
    text = mod.report()
    assert "## blockstack2, medium-expert *(earlier page)*" in text and "| BC | 3 | 1.00 / 1.00 / 0.69 |" in text
    assert "| BC | 1 | 1.00 / 0.70 / 0.20 |" in text.split("## blockstack2, medium-expert\n")[1].split("## ")[0]
    # the paper's data route: `--datasets uof-epoch20` is the file the shipped epoch-20 policy collects with the medium noise,
    # and its runs form their own group
    asked = []
    monkeypatch.setattr("torchrl_offhrl.recipes.uof_policies.uof_route_dataset", lambda *a, **k: asked.append((a, k)) or tmp_path / "e20.hdf5")
    assert mod.dataset_spec("blockstack2", "medium", 100) == "medium" and not asked
    assert mod.dataset_spec("blockstack2", "uof-epoch20", 100) == str(tmp_path / "e20.hdf5")
    assert asked == [(("blockstack2", "blockstack2-uof-epoch20", 100), {"random_prob": 0.1, "noise_std": 0.1})]
    run = tmp_path / "outputs" / mod.run_name("blockstack2", "uof-epoch20", "bc", 4)
    run.mkdir()
    for f in ("evals.json", "config.json", "summary.json"):
        (run / f).write_bytes((tmp_path / "outputs" / "bc-blockstack2-medium-seed5" / f).read_bytes())
    route = mod.report().split("## blockstack2, uof-epoch20\n")[1].split("## ")[0]
    assert "| BC | 1 | 1.00 / 0.70 / 0.20 |" in route
    # task 2 beside the paper's Table II, goal by goal (IQM over seeds: two seeds, so their mean)
    for seed, last in ((4, [1.0, 0.9, 0.1, 1.0, 0.8, 0.2]), (5, [1.0, 0.7, 0.3, 1.0, 1.0, 0.0])):
        run = tmp_path / "outputs" / f"bc-blockstack3-medium-expert-seed{seed}"
        run.mkdir()
        (run / "evals.json").write_text(json.dumps([{"step": 20000, "frames": 0, "success_per_goal": last, "success_per_goal_h50": last,
                                                      "success_rate": sum(last) / 6}]))
        (run / "config.json").write_text(json.dumps({"algo": {"name": "bc"}, "env": {"env_id": "BlockStack3-v0"}, "dataset": "medium-expert"}))
        (run / "summary.json").write_text(json.dumps({"unit": "updates"}))
    text = mod.report()
    assert ("| BC | 2 | 1.00 (paper 0.99) | 0.80 (paper 0.50) | 0.20 (paper 0.00) | 1.00 (paper 0.99) | 0.90 (paper 0.20) | "
            "0.10 (paper 0.00) |") in text.split("Table II against")[1]
    # the earlier page's BC row rerun on as many seeds (3): its section goes, the group prints once, in its own section
    for seed in (8, 9):
        run = tmp_path / "outputs" / f"bc-blockstack2-medium-expert-seed{seed}"
        run.mkdir()
        for f in ("evals.json", "config.json", "summary.json"):
            (run / f).write_bytes((tmp_path / "outputs" / "bc-blockstack2-medium-seed5" / f).read_bytes())
    text = mod.report()
    assert "## blockstack2, medium-expert *(earlier page)*" not in text and "| BC | 3 | 1.00 [1.00, 1.00] / 0.70 [0.70, 0.70] / 0.20 [0.20, 0.20] |" in text
    assert text.count("## blockstack2, medium-expert") == 1


def test_blockstack_variants_run_uof_with_their_setting_under_their_own_name(tmp_path, monkeypatch):
    """`offhrl results blockstack run --variants latent05 --no-main`: UOF on every task x dataset x seed with the variant's
    override, named so that the report groups it apart (and parses the dataset back)."""
    import torchrl_offhrl.recipes.train as train_mod

    mod = import_module("experiments.results.blockstack")
    monkeypatch.setattr(mod, "BASE", tmp_path / "outputs")
    monkeypatch.setattr(mod, "archive", lambda: [])
    seen = []
    monkeypatch.setattr(train_mod, "train", lambda cfg: seen.append(cfg) or {"final": {}})
    mod.main(["run", "--tasks", "blockstack2", "--datasets", "medium", "medium-expert", "--variants", "latent05", "--no-main",
              "--seeds", "4", "5"])
    names = [Path(c["run_dir"]).name for c in seen]
    assert names == ["uof-blockstack2-medium-latent05-seed4", "uof-blockstack2-medium-latent05-seed5",
                     "uof-blockstack2-medium-expert-latent05-seed4", "uof-blockstack2-medium-expert-latent05-seed5"]
    assert all(c["algo"]["name"] == "uof" and c["model_env"]["latent_bound"] == 0.5 for c in seen)
    assert [mod.split_run_name(n)[1:] for n in names[1:3]] == [("medium", "uof-latent05"), ("medium-expert", "uof-latent05")]
    assert mod.label("uof-latent05") == "UOF, latent box ±0.5"
    with pytest.raises(SystemExit):  # an unknown variant is refused by the parser, before any run
        mod.main(["run", "--variants", "latent9", "--no-main"])
