"""The offline rules (envs.rules) on hand-made models and data, the guard (recipes.selection), and how a config resolves them."""
import math

import pytest
import torch
from tensordict import TensorDict

from torchrl_offhrl.data import OfflineDataset, make_toy_dataset
from torchrl_offhrl.envs.rules import horizon_rule, latent_bound_rule, median_episode_length, offline_rules, open_loop_errors, penalty_rule, threshold_rule
from torchrl_offhrl.recipes.selection import PolicySelector, paired_gain_lcb


def _data(obs, act, nobs, reward, ends) -> OfflineDataset:
    n = obs.shape[0]
    td = TensorDict({"observation": obs, "action": act, "next": {
        "observation": nobs, "reward": reward.reshape(n, 1), "terminated": torch.zeros(n, 1, dtype=torch.bool),
        "truncated": ends.reshape(n, 1)}}, batch_size=[n])
    return OfflineDataset(td, {"env_id": "Toy-v0", "source": "hand-made"})


class DriftEnsemble(torch.nn.Module):
    """K members; member k predicts ``s' = s + drift_k`` (normalised residual = the drift, delta stats 0 / 1), any action."""

    def __init__(self, drifts, obs_dim=1):
        super().__init__()
        self.drifts = torch.as_tensor(drifts, dtype=torch.float32).reshape(-1, 1).expand(-1, obs_dim)
        self.num_members, self.observation_dim = self.drifts.shape[0], obs_dim
        self.dummy = torch.nn.Parameter(torch.zeros(1))
        self.delta_mean, self.delta_std = torch.zeros(obs_dim), torch.ones(obs_dim)

    def predict(self, observation, action, chunk=None):
        delta = self.drifts[:, None, :].expand(-1, observation.shape[0], -1)
        return {"next_observation": observation + delta, "reward": None, "delta": delta}

    def discrepancy(self, observation, action, kind="variance"):
        # a hand-made discrepancy: the action's first coordinate (so the threshold rule's pick is known)
        return action[:, 0].abs()


def test_threshold_is_the_largest_held_out_discrepancy_not_the_training_outlier():
    data = make_toy_dataset(num_episodes=10, episode_length=20, seed=3)
    train, held = data.split(0.2, seed=0)
    held_ids = set(held.data["episode"].tolist())
    act = data.data["action"]
    in_train = torch.tensor([e not in held_ids for e in data.data["episode"].tolist()])
    act[in_train.nonzero()[0, 0], 0] = 50.0  # an outlier among the training pairs: the rule must not read it
    ens = DriftEnsemble([0.0, 0.0], obs_dim=3)
    threshold, info = threshold_rule(ens, data.split(0.2, seed=0)[1])
    assert threshold == pytest.approx(float(act[~in_train, 0].abs().max()))
    assert threshold < 50.0 and info["held_out_pairs"] == int((~in_train).sum())


def test_penalty_is_the_returns_to_go_spread_plus_what_makes_ending_unattractive():
    # two episodes of two steps, gamma 0.5: returns-to-go [1 + 0.5*2, 2, -4 + 0.5*(-2), -2] = [2, 2, -5, -2]
    obs = torch.zeros(4, 1)
    data = _data(obs, torch.zeros(4, 1), obs, torch.tensor([1.0, 2.0, -4.0, -2.0]), torch.tensor([False, True, False, True]))
    g = torch.tensor([2.0, 2.0, -5.0, -2.0], dtype=torch.float64)
    penalty, info = penalty_rule(data, gamma=0.5)
    assert penalty == pytest.approx(float(g.std()) + 5.0)
    assert info["returns_to_go_min"] == pytest.approx(-5.0)
    positive = _data(obs, torch.zeros(4, 1), obs, torch.tensor([1.0, 2.0, 4.0, 2.0]), torch.tensor([False, True, False, True]))
    assert penalty_rule(positive, gamma=0.5)[0] == pytest.approx(float(torch.tensor([2.0, 2.0, 5.0, 2.0], dtype=torch.float64).std()))


def _still_episodes(num_episodes=8, length=60):
    """Episodes whose state never moves (each its own constant state): a model that drifts is wrong by h * drift after h steps."""
    values = torch.arange(num_episodes, dtype=torch.float32).repeat_interleave(length).reshape(-1, 1)
    ends = torch.zeros(num_episodes * length, dtype=torch.bool)
    ends[length - 1 :: length] = True
    return _data(values, torch.zeros_like(values), values.clone(), torch.ones(values.shape[0]), ends)


def test_open_loop_error_grows_as_the_drift_says_and_sets_the_horizon():
    data = _still_episodes()
    std = float(data.data["observation"].std(0))
    ens = DriftEnsemble([0.05, -0.05, 0.05])  # every member off by 0.05 per step
    curve = open_loop_errors(ens, data, length=40, max_starts=64)
    for h in (1, 10, 30):  # the error h steps ahead: h * 0.05 / std (windows that reach step h)
        assert curve[h - 1] == pytest.approx(h * 0.05 / std, rel=1e-4)
    tol = 0.5
    horizon, reset, info = horizon_rule(ens, data, episode_length=60, tolerance=tol, length=200, max_starts=64)
    assert horizon == math.floor(tol * std / 0.05) and reset == "any"  # within the tolerance for that many steps, shorter than an episode
    exact = DriftEnsemble([0.0, 0.0])  # a perfect model holds for whole episodes: the data's own start states and length
    horizon, reset, _ = horizon_rule(exact, data, episode_length=60, length=200, max_starts=64)
    assert (horizon, reset) == (60, "initial")


def test_latent_box_holds_99_percent_of_the_posterior_draws():
    class PriorCVAE(torch.nn.Module):  # a posterior equal to the prior: |z| is half-normal, its 99% quantile 2.576
        goal_key = None

        def __init__(self):
            super().__init__()
            self.dummy = torch.nn.Parameter(torch.zeros(1))

        def encode(self, observation, action, goal=None):
            return torch.zeros(observation.shape[0], 4), torch.ones(observation.shape[0], 4)

    data = make_toy_dataset(num_episodes=50, episode_length=100)
    bound, info = latent_bound_rule(PriorCVAE(), data)
    assert bound == pytest.approx(2.576, abs=0.05) and info["draws"] == 4 * len(data)


def test_offline_rules_report_on_fitted_models(tmp_path):
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble

    data = make_toy_dataset(num_episodes=20, episode_length=30)
    ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(16,)).fit(data, max_epochs=3, progress=False)
    cvae = ConditionalVAE.for_dataset(data, hidden_sizes=(16,)).fit(data, max_epochs=2, progress=False)
    rules = offline_rules(ens, data, cvae, val_ratio=0.2, split_seed=1)
    assert rules.threshold == pytest.approx(float(rules.held_out_discrepancy.max()))
    assert rules.horizon >= 5 and rules.latent_bound > 0 and rules.penalty > 0
    assert median_episode_length(data) == 30
    text = rules.summary()
    assert "pessimism threshold" in text and "latent box" in text and "model episodes" in text
    assert rules.plot(tmp_path / "calibration.png").stat().st_size > 0
    assert set(rules.settings()) == {"threshold", "penalty", "horizon", "reset_states", "latent_bound"}
    assert "not used" not in text
    # a run that sets its own (MOPO: no termination, 5-step rollouts): the report still states the rules, marked
    from torchrl_offhrl.recipes.config import compose, model_env_config, rules_not_used
    from torchrl_offhrl.utils import to_plain

    cfg = to_plain(compose("offline_train", ["algo=mopo", "model_env.reward_scale=1.0"]))
    settings, _ = model_env_config(cfg, "medium", data, rules=rules)
    not_used = rules_not_used(cfg, settings, rules)
    assert not_used == {"pessimism": "ablation.no_pessimism: no episode ends on the members' disagreement, no penalty",
                        "horizon": "model_env.horizon=5 (the config's)", "reset_states": "model_env.reset_states=any (the config's)"}
    rules.info["not_used"] = not_used
    lines = rules.summary().splitlines()
    assert sum("[not used by this run: ablation.no_pessimism" in line for line in lines) == 2  # the threshold and the penalty
    episodes = next(line for line in lines if "model episodes" in line)
    assert episodes.endswith("[not used by this run: model_env.horizon=5 (the config's); model_env.reset_states=any (the config's)]")
    assert "not used" not in next(line for line in lines if "latent box" in line)
    default = to_plain(compose("offline_train", ["model_env.reward_scale=1.0"]))  # the shipped default: every rule used
    assert rules_not_used(default, model_env_config(default, "medium", data, rules=rules)[0], rules) == {}
    paper = to_plain(compose("offline_train", ["preset=paper", "model_env.reward_scale=1.0"]))
    assert rules_not_used(paper, model_env_config(paper, "medium", data, rules=rules)[0], rules)["pessimism"].startswith("the paper preset's table")


# ----------------------------------------------------------------------------------------------------------- the guard
def _rec(returns, members=(0, 1, 0, 1)):
    return {"model_episode_returns": list(returns), "model_episode_members": list(members)}


class _Agent:
    def __init__(self, w):
        self.w = w

    def state_dict(self):
        return {"w": self.w}


def test_paired_gain_bound_uses_the_worst_member_and_its_standard_error():
    start = _rec([10, 10, 10, 10])
    # member 0 gains 4 and 2 (mean 3, sd sqrt(2), se 1), member 1 gains 1 and 1
    rec = _rec([14, 11, 12, 11])
    assert paired_gain_lcb(rec, start, z=1.0) == pytest.approx(min(3 - 1.0, 1.0))
    assert paired_gain_lcb(rec, _rec([10, 10, 10], (0, 1, 0))) is None  # episodes that do not pair up


def test_guard_returns_the_start_when_no_member_shows_a_gain():
    sel = PolicySelector("model_gain_lcb", guard=True)
    sel.consider(_rec([10, 10, 10, 10]), _Agent(0), step=0)
    sel.consider(_rec([30, 5, 30, 5]), _Agent(1), step=100)  # member 0 loves it, member 1 loses 5: bound < 0
    sel.consider(_rec([11, 9, 11, 9]), _Agent(2), step=200)
    v = sel.verdict()
    assert v["fired"] and v["gain_lcb"] < 0 and sel.start["agent"] == {"w": 0}
    sel.consider(_rec([13, 12, 13, 12]), _Agent(3), step=300)  # both members gain: selected and not guarded
    v = sel.verdict()
    assert not v["fired"] and v["gain_lcb"] == pytest.approx(2.0) and sel.selected["agent"] == {"w": 3}


@pytest.mark.fault("resume")
def test_guard_on_the_last_policy_and_across_a_resume():
    sel = PolicySelector("last", guard=True)
    sel.consider(_rec([10, 10, 10, 10]), _Agent(0), step=0)
    sel.consider(_rec([20, 20, 20, 20]), _Agent(1), step=100)
    state = sel.state_dict()
    again = PolicySelector("last", guard=True)
    again.load_state_dict(state)
    again.consider(_rec([8, 20, 8, 20]), _Agent(2), step=200)  # the last policy loses under member 0
    v = again.verdict()
    assert v["fired"] and v["gain_lcb"] == pytest.approx(-2.0)
    assert PolicySelector("last").verdict() is None  # no guard, no verdict


def test_a_guard_without_a_start_evaluation_says_so():
    sel = PolicySelector("last", guard=True)
    sel.consider(_rec([10, 10, 10, 10]), _Agent(1), step=100)
    v = sel.verdict()
    assert not v["fired"] and "eval.at_start" in v["reason"]


# ------------------------------------------------------------------------------------------------------ config resolution
def test_auto_keys_take_the_rules_and_given_values_win():
    from torchrl_offhrl.envs.rules import OfflineRules
    from torchrl_offhrl.recipes.config import model_env_config, needs_rules

    rules = OfflineRules(threshold=0.7, penalty=3.0, horizon=42, reset_states="any", latent_bound=1.7, discrepancy="variance", info={})
    data = make_toy_dataset(num_episodes=4, episode_length=10)
    cfg = {"env": {"name": "hopper"}, "algo": {"gamma": 0.99},
           "model_env": {"horizon": "auto", "reset_states": "auto", "latent_bound": "auto", "reward_scale": 1.0, "pessimism": None}}
    assert needs_rules(cfg)
    env, pess = model_env_config(cfg, "medium", data, rules=rules)
    assert (env["horizon"], env["reset_states"], env["latent_bound"], env["threshold"], env["penalty"]) == (42, "any", 1.7, 0.7, 3.0)
    cfg["model_env"].update(horizon=100, pessimism={"penalty": 9.0})
    env, pess = model_env_config(cfg, "medium", data, rules=rules)
    assert (env["horizon"], env["threshold"], env["penalty"]) == (100, 0.7, 9.0)
    cfg["model_env"]["pessimism"] = {"quantile": 0.999}  # a calibration asked for: the env calibrates, the rule's threshold is dropped
    env, _ = model_env_config(cfg, "medium", data, rules=rules)
    assert "threshold" not in env and env["quantile"] == 0.999


def test_the_paper_preset_restores_the_per_dataset_table_and_the_default_has_none():
    from torchrl_offhrl.recipes.config import compose, model_env_config, needs_rules, pessimism_table
    from torchrl_offhrl.utils import to_plain

    for env in ("hopper", "halfcheetah"):
        cfg = to_plain(compose("offline_train", [f"env={env}"]))
        assert pessimism_table(cfg) is None and "pessimism" not in cfg["env"] and needs_rules(cfg)
        assert all(cfg["model_env"][k] == "auto" for k in ("horizon", "reset_states", "latent_bound"))
    cfg = to_plain(compose("offline_train", ["env=hopper", "preset=paper"]))
    data = make_toy_dataset(num_episodes=4, episode_length=10)
    env, pess = model_env_config(cfg, "medium-expert", data)
    assert pess == {"fraction": 0.08, "penalty": 30.0} and env["horizon"] == 1000 and env["latent_bound"] == 2.0
    assert not needs_rules(cfg) and cfg["selection"] == {"criterion": "last", "include_start": False, "guard": False, "return_cap": "none",
                                                     "fallback": "start"}


# ------------------------------------------------------------------------------------------------ the guard's return cap
def _data_with_returns(returns_per_step: list[list[float]], unfinished=()):
    """A toy dataset whose episode ``i`` has the rewards ``returns_per_step[i]`` (lengths may differ)."""
    lengths = [len(r) for r in returns_per_step]
    ds = make_toy_dataset(num_episodes=1, episode_length=sum(lengths))
    ds.data.set("episode", torch.cat([torch.full((n,), i, dtype=ds.data.get("episode").dtype) for i, n in enumerate(lengths)]))
    ds.data.set(("next", "reward"), torch.tensor([x for r in returns_per_step for x in r]).reshape(ds.data.get(("next", "reward")).shape))
    ds.metadata["unfinished_episodes"] = list(unfinished)
    return ds


def test_the_return_cap_is_the_best_complete_episode_and_the_best_rate_for_longer_episodes():
    from torchrl_offhrl.recipes.selection import data_return_cap

    ds = _data_with_returns([[1.0, 1.0, 1.0, 1.0], [3.0, 3.0], [9.0, 9.0, 9.0]], unfinished=[2])  # episode 2 was cut short
    assert ds.episode_lengths().tolist() == [4, 2, 3] and ds.episode_lengths(complete_only=True).tolist() == [4, 2]
    assert data_return_cap(ds, max_steps=4) == pytest.approx(6.0)  # the unfinished 27 does not count; 6 > 4
    assert data_return_cap(ds, max_steps=3) == pytest.approx(6.0)  # shorter model episodes: the cap stays (a loose bound)
    assert data_return_cap(ds, max_steps=10) == pytest.approx(30.0)  # longer than any episode: 3 per step x 10
    all_cut = _data_with_returns([[1.0, 2.0]], unfinished=[0])  # nothing complete: every episode counts
    assert data_return_cap(all_cut, max_steps=2) == pytest.approx(3.0)


def test_the_capped_guard_counts_no_gain_above_the_datas_best():
    start, policy = _rec([10, 10, 20, 20]), _rec([12, 11, 30, 30])
    # capped at 15: member 0 gains 2 and 0, member 1 gains 1 and 0 (hand-computed means 1 and 0.5)
    assert paired_gain_lcb(policy, start, z=0.0, cap=15.0) == pytest.approx(0.5)
    assert paired_gain_lcb(policy, start, z=0.0) == pytest.approx(5.5)
    # the model pays the policy more than the start, everywhere above the data's best: no evidence, the guard fires
    hi_start, hi_policy = _rec([100, 100, 100, 100]), _rec([110, 112, 111, 113])
    for cap, fired in ((90.0, True), (None, False)):
        sel = PolicySelector("last", guard=True, return_cap=cap)
        sel.consider(hi_start, _Agent(0), step=0)
        sel.consider(hi_policy, _Agent(1), step=100)
        v = sel.verdict()
        assert v["fired"] is fired and v["return_cap"] == cap
        assert ("clipped at the data's best episode" in v["reason"]) is (cap is not None)
    # a gain below the cap still counts: the start's episode ended early (a penalty), the policy's did not
    sel = PolicySelector("last", guard=True, return_cap=90.0)
    sel.consider(_rec([-50, 80, -40, 85]), _Agent(0), step=0)
    sel.consider(_rec([95, 95, 95, 95]), _Agent(1), step=100)
    assert not sel.verdict()["fired"] and sel.verdict()["gain_lcb"] > 0


def test_the_return_cap_does_not_change_a_runs_fingerprint():
    from torchrl_offhrl.recipes.config import config_fingerprint

    cfg = {"algo": {"name": "moc"}, "selection": {"criterion": "last", "guard": True, "return_cap": "data"}}
    assert config_fingerprint(cfg) == config_fingerprint({**cfg, "selection": {**cfg["selection"], "return_cap": "none"}})
    assert config_fingerprint(cfg) != config_fingerprint({**cfg, "selection": {**cfg["selection"], "guard": False}})


def test_the_guard_judges_against_the_start_and_the_percentile_bc_and_falls_back_to_one_of_them():
    start, bc = _rec([10, 10, 10, 10]), _rec([12, 13, 12, 13])  # the start shows no gain over the BC (it loses 2 and 3)
    sel = PolicySelector("last", guard=True)
    sel.consider(start, _Agent(0), step=0)
    sel.consider(_rec([11, 11, 11, 11]), _Agent(1), step=100)  # beats the start by 1, loses to the BC by 1-2
    v = sel.verdict(fallback=bc)
    assert v["against"] == "bc" and v["fired"] and v["start_over_bc_lcb"] == pytest.approx(-3.0) and v["bc_over_start_lcb"] == pytest.approx(2.0)
    assert v["gain_lcb_over_start"] == pytest.approx(1.0) and v["gain_lcb"] == pytest.approx(-2.0) and "percentile BC is returned" in v["reason"]
    kept = PolicySelector("last", guard=True, prefer="start")  # the preference set once, as a run sets it from selection.fallback
    kept.load_state_dict(sel.state_dict())  # the same records: only the preference differs
    assert kept.verdict(fallback=bc)["against"] == "bc"  # the BC shows a gain over the start: either preference takes it
    assert not sel.verdict()["fired"] and sel.verdict()["against"] == "start"  # without the BC: judged against the start, passes
    # neither shows a gain over the other (member 0 prefers one, member 1 the other): the preference decides
    tie = _rec([12, 8, 12, 8])
    assert sel.verdict(fallback=tie)["against"] == "bc" and kept.verdict(fallback=tie)["against"] == "start"
    with pytest.raises(ValueError, match="prefer"):
        PolicySelector("last", guard=True, prefer="neither")
    # a start that beats the BC by 5 under every member: the fallback, and the policy must beat both
    v = sel.verdict(fallback=_rec([5, 5, 5, 5]))
    assert v["against"] == "start" and v["start_over_bc_lcb"] == pytest.approx(5.0) and not v["fired"] and v["gain_lcb"] == pytest.approx(1.0)
    # episodes that do not pair up: the BC is left out, and the reason says why
    v = sel.verdict(fallback=_rec([5, 5, 5], (0, 1, 0)))
    assert v["against"] == "start" and v["start_over_bc_lcb"] is None and "do not pair" in v["reason"]


def test_the_percentile_bc_fits_the_best_episodes_and_round_trips(tmp_path):
    from torchrl_offhrl.models import PercentileBC
    from torchrl_offhrl.models import ClonedPolicy

    data = make_toy_dataset(num_episodes=8, episode_length=20)
    obs = data.data["observation"]  # a behaviour that is a function of the state, for the cloner to learn
    data.data.set("action", 0.5 * torch.tanh(10 * obs[:, :2] - 5 * obs[:, 1:3]))
    bc = PercentileBC.for_dataset(data, hidden_sizes=(32,))
    with torch.no_grad():
        before = float(bc.loss(data.data))
    bc.fit(data, max_steps=2000, progress=False, seed=0, patience=50)
    with torch.no_grad():
        after = float(bc.loss(data.data))
        act = bc(data.data["observation"])
    assert after < 0.5 * before and bool(((act >= data.action_low - 1e-6) & (act <= data.action_high + 1e-6)).all())
    again = ClonedPolicy.from_state(ClonedPolicy(bc).state_dict())
    with torch.no_grad():
        assert torch.equal(again.bc(data.data["observation"]), act)
    bc.save(tmp_path / "bc.pt")
    with torch.no_grad():
        assert torch.equal(PercentileBC.load(tmp_path / "bc.pt")(data.data["observation"]), act)
