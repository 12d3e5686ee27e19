"""D4RL-protocol dataset generation and the behaviour policies it samples.

No trained policy needs to be shipped: a throwaway "run" (two small actor
checkpoints and an evals.json, as scripts/train_behaviour.py writes them) is
shipped into a temporary folder, which stands in for the policies folder.
"""
import json
import math
import os
import re

import pytest
import torch
from tensordict import TensorDict

import torchrl_offhrl.data.generate as gen
import torchrl_offhrl.data.policies as pol
from torchrl_offhrl.data import (
    OfflineDataset,
    PolicyNotFoundError,
    generate_dataset,
    list_policies,
    load_dataset,
    load_policy,
    named_dataset,
    save_dataset,
    ship_policy,
)
from torchrl_offhrl.data.catalog import dataset_path
from torchrl_offhrl.data.policies.actors import make_behaviour_actor
from torchrl_offhrl.rollouts import evaluate_policy
from torchrl_offhrl.utils import one_thread

HOPPER = ("Hopper-v5", 11, 3)
EVAL_STEPS = 40  # evaluation episodes capped for speed (real shipping uses 1000)


def _fake_run(root):
    """Two checkpoints of a "SAC run" in Hopper-v5 with training-time returns 10 and 20."""
    root.mkdir(parents=True, exist_ok=True)
    records = []
    for i, steps in enumerate((100, 200)):
        torch.manual_seed(100 + i)
        actor = make_behaviour_actor(11, 3, -torch.ones(3), torch.ones(3), hidden=(16,))
        torch.save(actor.state_dict(), root / f"actor_{steps}.pt")
        records.append({"steps": steps, "wall_s": 1.0, "stochastic": {"mean": 10.0 * (i + 1), "std": 1.0},
                        "deterministic": {"mean": 5.0, "std": 0.0}})
    (root / "evals.json").write_text(json.dumps({"env_id": "Hopper-v5", "seed": 7, "hidden": [16], "evals": records}))
    return root


@pytest.fixture(scope="module")
def shipped(tmp_path_factory):
    """A policies folder with hopper-medium (100 steps) and hopper-expert (the best, 200 steps)."""
    base = tmp_path_factory.mktemp("behaviour")
    run = _fake_run(base / "run")
    dest = base / "policies"
    ship_policy(run, "hopper-medium", "medium", steps=100, dest=dest, max_steps=EVAL_STEPS)
    ship_policy(run, "hopper-expert", "expert", dest=dest, max_steps=EVAL_STEPS)
    return {"run": run, "dir": dest, "medium": dest / "hopper-medium.pt", "expert": dest / "hopper-expert.pt"}


@pytest.fixture
def policies_here(shipped, monkeypatch, tmp_path):
    """The throwaway policies stand for the shipped ones; the cache is private to the test."""
    monkeypatch.setattr(pol, "POLICY_DIR", shipped["dir"])
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    return shipped


@pytest.fixture(scope="module")
def medium_a(shipped):
    return generate_dataset("hopper", "medium", 300, seed=3, num_envs=2, progress=False,
                            policy=shipped["medium"], ref_episodes=0)


def _equal(a: OfflineDataset, b: OfflineDataset) -> bool:
    keys = set(a.data.keys(True, True))
    assert keys == set(b.data.keys(True, True))
    return all(torch.equal(a.data[k], b.data[k]) for k in keys)


def _stub_refs(calls):
    def refs(env_id, short, expert, episodes, seed):
        calls.append((env_id, seed))
        return {"ref_min_return": -1.0, "ref_max_return": 99.0, "ref_episodes": episodes, "ref_seed": seed,
                "ref_policy": expert[1]["name"] if expert else None, "ref_note": "stub"}
    return refs


# ---------------------------------------------------------------- policies
def test_ship_policy_card_and_reevaluation(shipped):
    actor, card = load_policy(shipped["expert"])
    assert card["name"] == "hopper-expert" and card["level"] == "expert"
    assert card["train_steps"] == 200 and card["seed"] == 7  # the best checkpoint of the run
    assert card["algorithm"] == "SAC (torchrl SACLoss)" and card["hidden"] == [16]
    assert (card["obs_dim"], card["act_dim"]) == (11, 3)
    assert card["action_low"] == [-1.0] * 3 and card["action_high"] == [1.0] * 3
    assert set(card["versions"]) >= {"torch", "torchrl", "gymnasium", "mujoco"}
    assert "train_behaviour.py Hopper-v5" in card["command"] and "--steps 200" in card["command"]
    ev = card["eval"]
    assert ev["episodes"] == 10
    from torchrl_offhrl.scores import normalized_score

    assert ev["normalized_d4rl"] == pytest.approx(normalized_score("Hopper-v5", ev["stochastic"]["mean"]))
    # the state dict is the checkpoint's
    ckpt = torch.load(shipped["run"] / "actor_200.pt", weights_only=True)
    assert all(torch.equal(v, ckpt[k]) for k, v in actor.state_dict().items())
    # the card's numbers are a fresh evaluation of this actor (not the training-time 20.0), reproducible
    from torchrl_offhrl.data import make_gym_env

    env = make_gym_env("Hopper-v5", num_envs=10)
    for det, tag in ((False, "stochastic"), (True, "deterministic")):
        with torch.random.fork_rng(), one_thread():
            torch.manual_seed(ev["seed"])
            rets = evaluate_policy(env, actor, 10, max_steps=EVAL_STEPS, deterministic=det, seed=ev["seed"])
        assert float(rets.mean()) == pytest.approx(ev[tag]["mean"], rel=1e-5), tag
    env.close()
    assert ev["stochastic"]["mean"] != 20.0
    _, med = load_policy(shipped["medium"])
    assert med["train_steps"] == 100 and med["level"] == "medium"
    assert not [p for p in os.listdir(shipped["dir"]) if p.endswith(".tmp")]


def test_ship_policy_rejects_bad_requests(shipped, tmp_path):
    with pytest.raises(ValueError, match=r"no checkpoint at 150 steps; evaluated steps are \[100, 200\]"):
        ship_policy(shipped["run"], "hopper-medium", "medium", steps=150, dest=tmp_path)
    with pytest.raises(ValueError, match="at least 10 episodes"):
        ship_policy(shipped["run"], "hopper-medium", "medium", episodes=5, dest=tmp_path)
    with pytest.raises(ValueError, match="level must be one of"):
        ship_policy(shipped["run"], "hopper-x", "good", dest=tmp_path)
    assert os.listdir(tmp_path) == []


def test_ship_cli_fraction_and_list(shipped, tmp_path, monkeypatch, capsys):
    from torchrl_offhrl.data.policies.__main__ import main

    # a third of the best (20) is closest to the 100-step checkpoint (10)
    main(["ship", str(shipped["run"]), "hopper-medium", "--level", "medium", "--fraction", "0.33",
          "--dest", str(tmp_path), "--max-steps", str(EVAL_STEPS)])
    assert list_policies(tmp_path) == ["hopper-medium"]
    _, card = load_policy(tmp_path / "hopper-medium.pt")
    assert card["train_steps"] == 100 and "--max-steps 40" in card["command"]
    monkeypatch.setattr(pol, "POLICY_DIR", tmp_path)
    capsys.readouterr()
    main(["list"])
    assert capsys.readouterr().out.startswith("hopper-medium ")


def test_unknown_policy_name_error(monkeypatch, tmp_path):
    monkeypatch.setattr(pol, "POLICY_DIR", tmp_path)
    (tmp_path / "hopper-medium.pt").write_bytes(b"")
    (tmp_path / "hopper-medium.json").write_text("{}")
    with pytest.raises(PolicyNotFoundError) as err:
        load_policy("halfcheetah-expert")
    msg = str(err.value)
    assert "'halfcheetah-expert'" in msg and "['hopper-medium']" in msg
    # steps enough for HalfCheetah's expert (the shipped one came at 1.26M)
    assert "python scripts/train_behaviour.py HalfCheetah-v5 --steps 1500000 --out outputs/behaviour/halfcheetah" in msg
    assert "python -m torchrl_offhrl.data.policies ship" in msg and "--level expert" in msg
    with pytest.raises(FileNotFoundError, match="missing"):
        load_policy(tmp_path / "absent.pt")


def test_load_shipped_policies():
    names = list_policies()
    if not names:
        pytest.skip("no behaviour policy is shipped in torchrl_offhrl/data/policies yet")
    import gymnasium as gym
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    for name in names:
        actor, card = load_policy(name)
        assert card["name"] == name and card["level"] in ("medium", "expert")
        assert card["eval"]["episodes"] >= 10
        env = gym.make(card["env_id"])
        assert env.observation_space.shape == (card["obs_dim"],) and env.action_space.shape == (card["act_dim"],)
        obs, _ = env.reset(seed=0)
        td = TensorDict(observation=torch.as_tensor(obs, dtype=torch.float32)[None], batch_size=[1])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            a = actor(td)["action"][0]
        assert ((a >= torch.tensor(card["action_low"])) & (a <= torch.tensor(card["action_high"]))).all()
        env.close()


@pytest.mark.parametrize("name", pol.list_policies())
def test_shipped_cards_meet_the_d4rl_levels_and_match_their_weights(name):
    """The card's stochastic return is what its weights give (re-run with the
    card's seeds), and it lies in D4RL's band for its level (medium 30-50,
    expert >= 85), normalised with D4RL's constants (not the card's own field)."""
    from torchrl_offhrl.data import make_gym_env
    from torchrl_offhrl.scores import normalized_score

    actor, card = load_policy(name)
    ev = card["eval"]
    score = normalized_score(card["env_id"], ev["stochastic"]["mean"])
    assert (30 <= score <= 50) if card["level"] == "medium" else score >= 85, (name, score)
    env = make_gym_env(card["env_id"], num_envs=ev["episodes"])
    try:
        rets = pol.card_returns(actor, env, ev["seed"], ev["max_steps"])
    finally:
        env.close()
    # The same torch/MuJoCo builds on the same CPU give the card's numbers. On another CPU the actor's float rounding
    # differs, MuJoCo's dynamics amplify it, and the seeded episodes are a fresh sample of the same policy (measured:
    # HalfCheetah's cards on an Intel AVX-512 machine, mean within 0.3% of the card, std 0.55x of it). So the card and
    # this run are compared as two samples of n episodes: the means within 2% or three standard errors of their
    # difference, the variances within the 99% band of their ratio (log variance ratio ~ N(0, 4 / (n - 1)), the
    # normal approximation of F(n - 1, n - 1); for n = 10 the stds within 0.42x-2.36x). Weights of another level, or a
    # policy whose spread is not the card's, still fail.
    n, mean, std = ev["episodes"], float(rets.mean()), float(rets.std())
    card_mean, card_std = ev["stochastic"]["mean"], ev["stochastic"]["std"]
    se_diff = math.sqrt((card_std ** 2 + std ** 2) / n)
    assert abs(mean - card_mean) <= max(0.02 * abs(card_mean), 3 * se_diff), (name, mean, card_mean, se_diff)
    log_var_ratio = 2 * math.log(max(std, 1e-6) / max(card_std, 1e-6))
    assert abs(log_var_ratio) <= 2.576 * math.sqrt(4 / (n - 1)) or abs(std - card_std) <= 5.0, (name, std, card_std)


# -------------------------------------------------------------- generation
def test_same_seed_same_tensors_other_seed_differs(shipped, medium_a):
    again = generate_dataset("hopper", "medium", 300, seed=3, num_envs=2, progress=False,
                             policy=str(shipped["medium"]), ref_episodes=0)
    assert len(medium_a) == 300 and _equal(medium_a, again)
    other = generate_dataset("Hopper-v5", "medium", 300, seed=4, num_envs=2, progress=False,
                             policy=shipped["medium"], ref_episodes=0)
    assert not torch.equal(medium_a.data["observation"], other.data["observation"])
    assert not torch.equal(medium_a.data["action"], other.data["action"])


def test_actions_are_sampled_from_the_policy(shipped, medium_a):
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    actor, _ = load_policy(shipped["medium"])
    td = TensorDict(observation=medium_a.data["observation"], batch_size=[len(medium_a)])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        out = actor(td)
    act = medium_a.data["action"]
    assert (act != out["action"]).all()  # not the deterministic mean
    # action = tanh(loc + scale * eps): the implied eps are standard normal
    eps = (torch.atanh(act.clamp(-1 + 1e-6, 1 - 1e-6)) - out["loc"]) / out["scale"]
    assert abs(float(eps.mean())) < 0.2 and abs(float(eps.std()) - 1.0) < 0.15
    # and transitions chain within episodes
    same = medium_a.data["episode"][1:] == medium_a.data["episode"][:-1]
    assert torch.equal(medium_a.data["next", "observation"][:-1][same], medium_a.data["observation"][1:][same])


def test_return_statistics_match_stored_rewards(medium_a):
    rew = medium_a.data["next", "reward"].squeeze(-1).double().tolist()
    done = medium_a.data["next", "done"].squeeze(-1).tolist()
    term = medium_a.data["next", "terminated"].squeeze(-1).tolist()
    # 2 streams of 150 steps, far below Hopper's 1000-step limit: an episode is
    # complete iff it ends with terminated; the others were cut by the budget
    returns, cut, acc = [], 0, 0.0
    for r, d, t in zip(rew, done, term):
        acc += r
        if d:
            if t:
                returns.append(acc)
            else:
                cut += 1
            acc = 0.0
    assert done[-1] and 1 <= cut <= 2
    rets = torch.tensor(returns, dtype=torch.float64)
    st = medium_a.metadata["returns"]
    assert st["episodes"] == len(returns) == medium_a.num_episodes - cut
    assert st["unfinished"] == cut == len(medium_a.metadata["unfinished_episodes"]) and st["complete"]
    torch.testing.assert_close(medium_a.episode_returns(complete_only=True), rets)
    assert st["mean"] == pytest.approx(float(rets.mean()), rel=1e-9)
    assert st["std"] == pytest.approx(float(rets.std()), rel=1e-9)
    assert (st["min"], st["max"]) == pytest.approx((float(rets.min()), float(rets.max())))


def test_metadata_round_trip(shipped, medium_a, tmp_path):
    path = save_dataset(medium_a, tmp_path / "m.hdf5")
    again = load_dataset(path, env_id="Hopper-v5")
    assert _equal(medium_a, again)
    meta = again.metadata
    assert meta["level"] == "medium" and meta["dataset"] == "hopper-medium" and meta["seed"] == 3
    assert meta["policy"] == "hopper-medium" and meta["policy_card"]["train_steps"] == 100
    assert meta["policy_card"]["eval"]["episodes"] == 10
    assert meta["ref_min_return"] is None and meta["ref_max_return"] is None and "ref_episodes=0" in meta["ref_note"]
    assert set(meta["versions"]) >= {"torch", "torchrl", "gymnasium", "mujoco"}
    assert meta["returns"] == medium_a.metadata["returns"]
    assert meta["score"]["d4rl"] == pytest.approx(100 * (meta["returns"]["mean"] + 20.272305) / (3234.3 + 20.272305))


def test_random_level_and_reference_returns(shipped, monkeypatch, tmp_path):
    from torchrl_offhrl.data import make_gym_env

    monkeypatch.setattr(pol, "POLICY_DIR", shipped["dir"])
    ds = generate_dataset("hopper", "random", 200, seed=5, num_envs=2, progress=False, ref_episodes=2)
    meta = ds.metadata
    assert meta["level"] == "random" and meta["policy"] == "uniform-random" and meta["policy_card"] is None
    act = ds.data["action"]
    assert (act.abs() <= 1).all() and float(act.std()) > 0.5  # uniform on [-1, 1]: std 0.577
    assert meta["ref_policy"] == "hopper-expert" and meta["ref_episodes"] == 2
    # the references are evaluate_policy's numbers, reproducible from the recorded seed
    env = make_gym_env("Hopper-v5", num_envs=2)
    expert, _ = load_policy("hopper-expert")
    for policy, key in ((None, "ref_min_return"), (expert, "ref_max_return")):
        with torch.random.fork_rng(), one_thread():
            torch.manual_seed(meta["ref_seed"])
            rets = evaluate_policy(env, policy, 2, deterministic=False, seed=meta["ref_seed"])
        assert meta[key] == pytest.approx(float(rets.mean()), rel=1e-5), key
    env.close()
    lo, hi = meta["ref_min_return"], meta["ref_max_return"]
    assert meta["score"]["own_refs"] == pytest.approx(100 * (meta["returns"]["mean"] - lo) / (hi - lo))
    # with no expert shipped: null and said so
    monkeypatch.setattr(pol, "POLICY_DIR", tmp_path)
    ds = generate_dataset("hopper", "random", 100, seed=5, num_envs=2, progress=False, ref_episodes=2)
    assert ds.metadata["ref_max_return"] is None and ds.metadata["ref_min_return"] == pytest.approx(lo)
    assert "no shipped expert policy 'hopper-expert'" in ds.metadata["ref_note"]
    with pytest.raises(ValueError, match="takes no policy"):
        generate_dataset("hopper", "random", 100, policy=shipped["medium"])


def test_medium_expert_is_the_concatenation(shipped, medium_a, tmp_path):
    both = generate_dataset("hopper", "medium-expert", 300, seed=3, num_envs=2, progress=False,
                            policy=(shipped["medium"], shipped["expert"]), ref_episodes=0)
    expert = generate_dataset("hopper", "expert", 300, seed=3, num_envs=2, progress=False,
                              policy=shipped["expert"], ref_episodes=0)
    assert len(both) == len(medium_a) + len(expert) == 600
    assert both.num_episodes == medium_a.num_episodes + expert.num_episodes
    for key in ("observation", "action", ("next", "reward"), ("next", "observation")):
        assert torch.equal(both.data[key], torch.cat([medium_a.data[key], expert.data[key]])), key
    # the boundary ends an episode: the parts' episodes are not merged
    ep = both.data["episode"]
    assert both.data["next", "done"][299].item() and ep[300] == ep[299] + 1
    assert set(ep[:300].tolist()).isdisjoint(ep[300:].tolist())
    again = load_dataset(save_dataset(both, tmp_path / "me.hdf5"))
    assert again.num_episodes == both.num_episodes
    assert again.episode_returns().tolist() == pytest.approx(
        medium_a.episode_returns().tolist() + expert.episode_returns().tolist())
    meta = again.metadata
    assert meta["level"] == "medium-expert" and set(meta["policy_card"]) == {"medium", "expert"}
    assert meta["parts"]["medium"]["returns"] == medium_a.metadata["returns"]
    # the parts' unfinished episodes, the expert's renumbered after the medium's
    shift = medium_a.num_episodes
    assert meta["unfinished_episodes"] == medium_a.metadata["unfinished_episodes"] + [e + shift for e in expert.metadata["unfinished_episodes"]]
    assert meta["returns"]["episodes"] == medium_a.metadata["returns"]["episodes"] + expert.metadata["returns"]["episodes"]
    assert meta["returns"]["episodes"] + meta["returns"]["unfinished"] == both.num_episodes
    torch.testing.assert_close(again.episode_returns(complete_only=True), torch.cat(
        [medium_a.episode_returns(complete_only=True), expert.episode_returns(complete_only=True)]))


# ------------------------------------------------------------ named + cache
def test_named_dataset_cache_hit(policies_here, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(gen, "_reference_returns", _stub_refs(calls))
    ds = named_dataset("hopper-medium", num_transitions=200, seed=1, num_envs=2)
    path = dataset_path("hopper-medium", 200, seed=1, num_envs=2)
    assert re.fullmatch(r"hopper-medium-200-seed1-envs2-p[0-9a-f]{8}\.hdf5", path.name) and path.parent.name == "datasets"
    assert path.is_file() and ds.metadata["source"] == str(path)
    err = capsys.readouterr().err
    assert "not cached" in err and "generating it now" in err and "estimated" in err
    mtime = path.stat().st_mtime_ns

    def no_generation(*a, **k):
        raise AssertionError("generated again instead of loading the cache")

    monkeypatch.setattr(gen, "generate_dataset", no_generation)
    monkeypatch.setattr(gen, "collect_dataset", no_generation)
    again = named_dataset("hopper-medium-200", seed=1, num_envs=2)
    assert _equal(ds, again) and path.stat().st_mtime_ns == mtime
    assert again.metadata["ref_max_return"] == 99.0 and again.metadata["policy_card"]["name"] == "hopper-medium"
    assert "not cached" not in capsys.readouterr().err
    assert len(calls) == 1


def test_named_medium_expert_reuses_cached_parts(policies_here, monkeypatch, shipped):
    monkeypatch.setattr(gen, "_reference_returns", _stub_refs([]))
    me = named_dataset("hopper-medium-expert", num_transitions=100, seed=2, num_envs=2, progress=False)
    parts = [load_dataset(dataset_path(f"hopper-{lv}", 100, 2, 2)) for lv in ("medium", "expert")]
    assert len(me) == 200 and me.num_episodes == parts[0].num_episodes + parts[1].num_episodes
    assert torch.equal(me.data["action"], torch.cat([p.data["action"] for p in parts]))
    assert dataset_path("hopper-medium-expert", 100, 2, 2).is_file()
    assert me.metadata["level"] == "medium-expert" and me.metadata["ref_max_return"] == 99.0
    direct = generate_dataset("hopper", "medium-expert", 100, seed=2, num_envs=2, progress=False)
    assert _equal(me, direct)  # same data as generating it in one go


def test_interrupted_write_leaves_nothing_loadable(policies_here, monkeypatch):
    import h5py

    monkeypatch.setattr(gen, "_reference_returns", _stub_refs([]))
    real = h5py.File.create_dataset
    written = []

    def fail_midway(self, name, *a, **k):
        if len(written) == 3:
            raise KeyboardInterrupt  # e.g. Ctrl-C while writing
        written.append(name)
        return real(self, name, *a, **k)

    monkeypatch.setattr(h5py.File, "create_dataset", fail_midway)
    with pytest.raises(KeyboardInterrupt):
        named_dataset("hopper-random", num_transitions=100, seed=0, num_envs=2, progress=False)
    assert written == ["observations", "actions", "next_observations"]
    path = dataset_path("hopper-random", 100, 0, 2)
    assert not path.exists()
    assert os.listdir(path.parent) == []  # the temporary file is gone too
    monkeypatch.setattr(h5py.File, "create_dataset", real)
    ds = named_dataset("hopper-random", num_transitions=100, seed=0, num_envs=2, progress=False)
    assert path.is_file() and len(load_dataset(path)) == len(ds) == 100


def test_missing_policy_and_bad_names(monkeypatch, tmp_path):
    monkeypatch.setattr(pol, "POLICY_DIR", tmp_path / "none")
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    with pytest.raises(PolicyNotFoundError) as err:
        named_dataset("hopper-medium-expert", 100)
    msg = str(err.value)
    assert "'hopper-medium'" in msg and "none yet" in msg
    assert "python scripts/train_behaviour.py Hopper-v5 --steps 300000 --out outputs/behaviour/hopper" in msg
    assert "ship outputs/behaviour/hopper hopper-medium --level medium" in msg
    assert not (tmp_path / "cache" / "datasets").exists() or not os.listdir(tmp_path / "cache" / "datasets")
    with pytest.raises(PolicyNotFoundError, match="'hopper-expert'"):
        generate_dataset("hopper", "expert", 100)
    with pytest.raises(ValueError, match="expected '<env>-<level>'"):
        named_dataset("hopper-good")
    with pytest.raises(ValueError, match="says 2000 transitions but num_transitions=300"):
        named_dataset("hopper-random-2k", num_transitions=300)
    assert dataset_path("halfcheetah-medium-expert-1m").name == "halfcheetah-medium-expert-1000000-seed0.hdf5"


def test_export_minari_round_trip(medium_a, tmp_path, monkeypatch):
    pytest.importorskip("minari")
    from torchrl_offhrl.data import export_minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    ds = OfflineDataset(medium_a.data.clone(), dict(medium_a.metadata, ref_min_return=-1.0, ref_max_return=50.0))
    with pytest.warns(UserWarning):  # minari warns about the author e-mail we do not invent
        mds = export_minari(ds, "offhrl/hopper/medium-test-v0")
    assert mds.total_episodes == ds.num_episodes and mds.total_steps == len(ds)
    assert mds.storage.metadata["ref_min_score"] == -1.0 and mds.storage.metadata["ref_max_score"] == 50.0
    back = load_dataset("offhrl/hopper/medium-test-v0")
    for key in ("observation", "action", ("next", "observation"), ("next", "reward"),
                ("next", "terminated"), ("next", "truncated"), "episode"):
        assert torch.equal(back.data[key], ds.data[key]), key



def test_cache_key_follows_the_policy_weights(policies_here, monkeypatch, tmp_path):
    """Other shipped weights under the same name give another cache file (never a stale dataset)."""
    import shutil

    copy = tmp_path / "policies_copy"
    shutil.copytree(pol.POLICY_DIR, copy)
    monkeypatch.setattr(pol, "POLICY_DIR", copy)
    before = dataset_path("hopper-medium", 200, seed=1, num_envs=2)
    weights = pol.POLICY_DIR / "hopper-medium.pt"
    state = torch.load(weights, weights_only=True)
    state = {k: v + 1.0 for k, v in state.items()}
    torch.save(state, weights)
    after = dataset_path("hopper-medium", 200, seed=1, num_envs=2)
    assert before != after and before.name.split("-p")[0] == after.name.split("-p")[0]
    assert dataset_path("hopper-random", 200, seed=1).name == "hopper-random-200-seed1.hdf5"


def test_a_seeded_stochastic_evaluation_repeats_and_leaves_the_rng_alone():
    """evaluate_policy(deterministic=False, seed=s): the same sampled returns each time; the caller's torch RNG stream is untouched."""
    import torch

    from torchrl_offhrl.data import load_policy, make_gym_env
    from torchrl_offhrl.rollouts import evaluate_policy

    actor, _ = load_policy("hopper-medium")
    env = make_gym_env("Hopper-v5", num_envs=3)
    torch.manual_seed(0)
    state = torch.get_rng_state()
    a = evaluate_policy(env, actor, 3, max_steps=60, deterministic=False, seed=5)
    assert torch.equal(torch.get_rng_state(), state)
    b = evaluate_policy(env, actor, 3, max_steps=60, deterministic=False, seed=5)
    c = evaluate_policy(env, actor, 3, max_steps=60, deterministic=False, seed=6)
    d = evaluate_policy(env, actor, 3, max_steps=60, deterministic=True, seed=5)
    assert torch.equal(a, b) and not torch.equal(a, c) and not torch.equal(a, d)
