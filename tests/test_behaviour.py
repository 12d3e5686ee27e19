"""The behaviour-policy trainer (SAC / CrossQ in the real env): outputs, resume, refusals, shipping."""
import json

import pytest
import torch
from torchrl.data import LazyTensorStorage, ReplayBuffer

import torchrl_offhrl.recipes.behaviour as beh
from torchrl_offhrl.rollouts import evaluate_policy
from torchrl_offhrl.data import load_policy, ship_policy

TINY = {"init_random_steps": 60, "eval_every": 100, "eval_episodes": 2, "eval_max_steps": 30, "batch_size": 16, "hidden": (8,), "frames_per_batch": 50, "progress": False}


def _buffer(state_dir, capacity):
    rb = ReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=4)
    rb.loads(state_dir / "replay")
    return rb


@pytest.mark.parametrize("algorithm", ["sac", "crossq"])
def test_train_resume_and_extend(tmp_path, algorithm):
    out = tmp_path / algorithm
    records = beh.train_behaviour("Hopper-v5", out, algorithm=algorithm, total_steps=200, **TINY)
    assert [r["steps"] for r in records] == [100, 200]
    info = json.loads((out / "evals.json").read_text())
    assert info["algorithm"] == algorithm and info["env_id"] == "Hopper-v5" and info["hidden"] == [8]
    assert (out / "curve.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # the learning curve, refreshed at each evaluation
    state = torch.load(out / "state" / "state.pt", weights_only=False)
    assert state["steps"] == 200 and state["capacity"] == 200
    # the first batch (50 steps) is below init_random_steps=60: no updates; then one per step
    assert state["learner"]["updates"] == 150
    first = _buffer(out / "state", 200)
    assert len(first) == 200
    # the snapshot of the last evaluation is the saved actor
    actor_200 = torch.load(out / "actor_200.pt", weights_only=True)
    saved = {k: v for k, v in state["learner"]["loss"].items() if k.startswith("actor_network_params")}
    assert any(torch.equal(v, actor_200["module.0.module.0.0.weight"]) for v in saved.values())

    # asking for what is already done trains nothing
    again = beh.train_behaviour("Hopper-v5", out, algorithm=algorithm, total_steps=200, **TINY)
    assert again == records
    if algorithm == "sac":  # the Polyak tau of SAC's target critics belongs to the run
        with pytest.raises(ValueError, match=r"'tau': \(0\.005, 0\.01\)"):
            beh.train_behaviour("Hopper-v5", out, algorithm=algorithm, total_steps=300, tau=0.01, **TINY)
    else:  # CrossQ has no target critics: tau plays no part, so it is not checked
        assert beh.train_behaviour("Hopper-v5", out, algorithm=algorithm, total_steps=200, tau=0.01, **TINY) == records

    # a longer run continues: earlier records kept, buffer grown with the old transitions first
    more = beh.train_behaviour("Hopper-v5", out, algorithm=algorithm, total_steps=300, **TINY)
    assert [r["steps"] for r in more] == [100, 200, 300]
    assert more[:2] == records
    state = torch.load(out / "state" / "state.pt", weights_only=False)
    assert state["steps"] == 300 and state["learner"]["updates"] == 250
    grown = _buffer(out / "state", 300)
    assert len(grown) == 300
    torch.testing.assert_close(grown.storage[:200]["observation"], first.storage[:200]["observation"])
    assert not torch.equal(torch.load(out / "actor_300.pt", weights_only=True)["module.0.module.0.0.weight"], actor_200["module.0.module.0.0.weight"])
    assert not (out / "state.tmp").exists() and not (out / "state.old").exists()


def test_refuses_a_different_run(tmp_path):
    beh.train_behaviour("Hopper-v5", tmp_path, algorithm="crossq", total_steps=100, **TINY)
    with pytest.raises(ValueError, match=r"algorithm.*'crossq', 'sac'"):
        beh.train_behaviour("Hopper-v5", tmp_path, algorithm="sac", total_steps=200, **TINY)
    with pytest.raises(ValueError, match="hidden"):
        beh.train_behaviour("Hopper-v5", tmp_path, algorithm="crossq", total_steps=200, **{**TINY, "hidden": (16,)})
    with pytest.raises(ValueError, match=r"'lr': \(0\.001, 0\.0005\)"):
        beh.train_behaviour("Hopper-v5", tmp_path, algorithm="crossq", total_steps=200, lr=5e-4, **TINY)
    with pytest.raises(ValueError, match=r"'batch_size': \(16, 32\)"):
        beh.train_behaviour("Hopper-v5", tmp_path, algorithm="crossq", total_steps=200, **{**TINY, "batch_size": 32})
    # passing the algorithm's default lr explicitly is the same run
    assert len(beh.train_behaviour("Hopper-v5", tmp_path, algorithm="crossq", total_steps=200, lr=1e-3, **TINY)) == 2
    with pytest.raises(ValueError, match="algorithm must be one of"):
        beh.train_behaviour("Hopper-v5", tmp_path / "x", algorithm="td3", total_steps=100, **TINY)


def test_states_saved_before_the_settings_were_recorded_still_resume(tmp_path):
    """Runs saved by older versions hold no training settings: they resume, checked on the rest."""
    beh.train_behaviour("Hopper-v5", tmp_path, total_steps=100, **TINY)
    path = tmp_path / "state" / "state.pt"
    state = torch.load(path, weights_only=False)
    state["identity"] = {k: state["identity"][k] for k in ("env_id", "algorithm", "hidden", "critic_hidden", "seed")}
    torch.save(state, path)
    assert [r["steps"] for r in beh.train_behaviour("Hopper-v5", tmp_path, total_steps=200, lr=1e-4, **TINY)] == [100, 200]
    # the optimisers' saved lr is the one in use, and now recorded
    assert torch.load(path, weights_only=False)["identity"]["lr"] == 3e-4
    assert json.loads((tmp_path / "evals.json").read_text())["lr"] == 3e-4
    with pytest.raises(ValueError, match="seed"):
        beh.train_behaviour("Hopper-v5", tmp_path, total_steps=300, seed=5, **TINY)


def test_state_swap_survives_a_crash(tmp_path):
    """A crash while the new state is written leaves the previous one usable."""
    assert beh.latest_state(tmp_path) is None
    rb = ReplayBuffer(storage=LazyTensorStorage(4), batch_size=2)
    rb.extend(torch.arange(3.0).unsqueeze(-1))
    beh.save_state(tmp_path, rb, {"steps": 3})
    assert beh.latest_state(tmp_path) == tmp_path / "state"
    # crash mid-swap: the current state was moved aside, the new one never renamed in
    (tmp_path / "state").rename(tmp_path / "state.old")
    (tmp_path / "state.tmp").mkdir()  # incomplete: no state.pt
    assert beh.latest_state(tmp_path) == tmp_path / "state.old"
    beh.save_state(tmp_path, rb, {"steps": 4})
    assert beh.latest_state(tmp_path) == tmp_path / "state"
    assert torch.load(tmp_path / "state" / "state.pt")["steps"] == 4
    assert not (tmp_path / "state.old").exists() and not (tmp_path / "state.tmp").exists()


def test_ship_a_crossq_run(tmp_path):
    run = tmp_path / "run"
    beh.train_behaviour("Hopper-v5", run, algorithm="crossq", total_steps=100, critic_hidden=(16,), **TINY)
    pt = ship_policy(run, "hopper-medium", "medium", steps=100, dest=tmp_path / "pol", max_steps=30, note="resumed once")
    _actor, card = load_policy(pt)
    assert card["note"] == "resumed once"
    assert card["train_wall_s"] == json.loads((run / "evals.json").read_text())["evals"][0]["wall_s"] > 0
    assert card["algorithm"] == "CrossQ (torchrl CrossQLoss)"
    assert "--algorithm crossq --critic-hidden 16 --steps 100" in card["command"]
    assert card["hidden"] == [8]


def test_evaluations_do_not_depend_on_the_previous_one():
    """Envs are reset to their seeded start for every evaluation, whatever state the previous one left.

    The hard case for TorchRL's gym vector envs: a rollout that ends exactly
    when some envs end their episode (done at the last step) and others do
    not; a plain reset then hands the first their auto-reset state.
    """
    from tensordict.nn import TensorDictModule

    from torchrl_offhrl.data import make_gym_env

    # full torque on every joint: Hopper falls within a few dozen steps
    policy = TensorDictModule(lambda obs: torch.ones(*obs.shape[:-1], 3), in_keys=["observation"], out_keys=["action"])
    env = make_gym_env("Hopper-v5", num_envs=3)
    _, probe = evaluate_policy(env, policy, 3, max_steps=120, seed=7, return_rollout=True)
    first_done = probe["next", "done"].flatten(1).float().argmax(1)  # step of each env's first done
    assert bool(probe["next", "done"].any(1).all()) and len(set(first_done.tolist())) > 1
    horizon = int(first_done.min()) + 1  # the earliest env ends exactly at the last step, the others run on
    runs = [evaluate_policy(env, policy, 3, max_steps=horizon, seed=7, return_rollout=True) for _ in range(3)]
    assert bool(runs[0][1]["next", "done"][:, -1].any()) and not bool(runs[0][1]["next", "done"][:, -1].all())
    fresh = evaluate_policy(make_gym_env("Hopper-v5", num_envs=3), policy, 3, max_steps=horizon, seed=7)
    for rets, td in runs[1:]:
        torch.testing.assert_close(td["observation"][:, 0], runs[0][1]["observation"][:, 0])
        torch.testing.assert_close(rets, runs[0][0])
    torch.testing.assert_close(fresh, runs[0][0])


def test_behaviour_curve_draws_the_records_and_the_d4rl_levels(tmp_path, capsys):
    from torchrl_offhrl.data.policies.__main__ import main
    from torchrl_offhrl.data.policies.plots import behaviour_figure

    records = [{"steps": 10_000 * (i + 1), "stochastic": {"mean": m, "std": 10.0 * i}, "deterministic": {"mean": m + 50.0, "std": 0.0}}
               for i, m in enumerate([100.0, 900.0, 2800.0])]
    run = {"env_id": "Hopper-v5", "algorithm": "sac", "seed": 3, "evals": records}
    fig = behaviour_figure(run)
    ax = fig.axes[0]
    lines = {ln.get_label(): ln for ln in ax.get_lines()}
    assert list(lines["stochastic (as collected)"].get_ydata()) == [100.0, 900.0, 2800.0]
    assert list(lines["deterministic"].get_xdata()) == [10_000, 20_000, 30_000]
    # level lines at the D4RL returns: -20.272305 + s / 100 * (3234.3 + 20.272305), by hand
    levels = sorted(ln.get_ydata()[0] for ln in ax.get_lines() if ln.get_linestyle() == ":")
    assert levels == pytest.approx([956.099387, 1607.013848, 2746.114154], abs=1e-5)
    assert ax.get_title() == "sac Hopper-v5 seed 3"
    # an env without D4RL references: no level lines
    fig = behaviour_figure({**run, "env_id": "Pendulum-v1"})
    assert not [ln for ln in fig.axes[0].get_lines() if ln.get_linestyle() == ":"]

    (tmp_path / "evals.json").write_text(json.dumps(run))
    assert main(["plot", str(tmp_path)]) == 0
    assert (tmp_path / "curve.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["plot", str(tmp_path / "missing")]) == 1
    assert "no evals.json" in capsys.readouterr().err
    (tmp_path / "evals.json").write_text(json.dumps({**run, "evals": []}))
    assert main(["plot", str(tmp_path)]) == 1
    assert "no evaluation records yet" in capsys.readouterr().err


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")
def test_cuda_without_a_gpu_is_refused_up_front(tmp_path):
    with pytest.raises(ValueError, match="sees no CUDA GPU"):
        beh.train_behaviour("Hopper-v5", tmp_path / "run", total_steps=100, device="cuda", **TINY)
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_train_and_resume_on_cuda(tmp_path):
    records = beh.train_behaviour("Hopper-v5", tmp_path, total_steps=100, device="cuda", **TINY)
    more = beh.train_behaviour("Hopper-v5", tmp_path, total_steps=200, device="cuda", **TINY)
    assert more[:1] == records and [r["steps"] for r in more] == [100, 200]
    actor = torch.load(tmp_path / "actor_200.pt", weights_only=True)
    assert all(v.device.type == "cpu" for v in actor.values())
    state = torch.load(tmp_path / "state" / "state.pt", weights_only=False)
    assert state["cuda_rng"] is not None and state["learner"]["updates"] == 150
