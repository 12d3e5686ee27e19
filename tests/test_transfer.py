"""The transfer setting: backward tasks, the decoder discarded, a two-phase run (offline, then online) that resumes across the switch."""
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from torchrl_offhrl.envs import AffineActionMap, make_task_env, task_kwargs
from torchrl_offhrl.recipes import train as recipe_mod  # where the run builds its agent and models (recipes.train)
from torchrl_offhrl.recipes.config import config_fingerprint, transfer_config
from torchrl_offhrl.recipes.report import aggregate, transfer_stats
from torchrl_offhrl.recipes.schema import validate_config
from torchrl_offhrl.recipes.train import train

from test_recipes import ROOT, TINY, _cfg

TRANSFER = ["transfer.task=backward", "transfer.online_frames=256", "transfer.num_envs=2", "transfer.eval_every_frames=128"]


def _step_with_velocity(env_id: str, task: str, vx: float) -> tuple[float, dict]:
    env = gym.make(env_id, **task_kwargs(task))
    env.reset(seed=0)
    sim = env.unwrapped
    qvel = sim.data.qvel.copy()
    qvel[0] = vx  # the root's x velocity: forward > 0
    sim.set_state(sim.data.qpos.copy(), qvel)
    _, reward, _, _, info = env.step(np.zeros(env.action_space.shape))
    env.close()
    return float(reward), info


@pytest.mark.parametrize("env_id", ["Hopper-v5", "HalfCheetah-v5"])
def test_backward_task_rewards_moving_backwards(env_id):
    for vx in (2.0, -2.0):
        _, fwd = _step_with_velocity(env_id, "forward", vx)
        reward, back = _step_with_velocity(env_id, "backward", vx)
        # the forward-velocity term flips sign and keeps its size; the healthy reward and the control cost stay
        assert back["reward_forward"] == pytest.approx(-fwd["reward_forward"])
        assert np.sign(back["reward_forward"]) == -np.sign(vx)
        healthy = back.get("reward_survive", 0.0)
        assert reward == pytest.approx(back["reward_forward"] + back["reward_ctrl"] + healthy)
    # HalfCheetah has no healthy reward: a step forward costs, a step backward pays (zero action, no control cost)
    if env_id == "HalfCheetah-v5":
        assert _step_with_velocity(env_id, "backward", 2.0)[0] < 0 < _step_with_velocity(env_id, "backward", -2.0)[0]


def test_make_task_env_passes_the_task_and_names_bad_ones():
    env = make_task_env("Hopper-v5", "backward", num_envs=2)
    assert env.batch_size == torch.Size([2])
    assert env.base_env._env.envs[0].unwrapped._forward_reward_weight == -1.0
    env.close()
    with pytest.raises(ValueError, match="unknown task 'up'.*'forward', 'backward'"):
        make_task_env("Hopper-v5", "up")
    with pytest.raises(ValueError, match="Pendulum-v1 does not take the reward arguments"):
        make_task_env("Pendulum-v1", "backward")


def test_affine_action_map_is_the_box_to_box_affine_map():
    low, high = torch.tensor([-1.0, -0.4, 0.0]), torch.tensor([1.0, 0.4, 2.0])
    m = AffineActionMap(2.0, low, high)
    assert m.latent_dim == m.action_dim == 3
    z = torch.tensor([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0], [0.0, 1.0, -1.0]])
    a = m(None, z)
    torch.testing.assert_close(a[0], low)
    torch.testing.assert_close(a[1], high)
    torch.testing.assert_close(a[2], torch.tensor([0.0, 0.2, 0.5]))
    with pytest.raises(ValueError, match="low < high"):
        AffineActionMap(2.0, high, low)


def test_real_env_with_the_decoder_discarded_acts_through_the_map():
    from torchrl_offhrl.recipes.pipeline import make_real_env

    env = make_real_env("Hopper-v5", None, num_envs=2, latent_bound=2.0, task="backward", discard_decoder=True)
    spec = env.full_action_spec["latent_action"]
    assert spec.shape[-1] == 3 and float(spec.space.low.min()) == -2.0 and float(spec.space.high.max()) == 2.0
    td = env.reset()
    td["latent_action"] = torch.tensor([[2.0, -2.0, 1.0], [0.0, 0.0, 0.0]])
    td = env.step(td)
    torch.testing.assert_close(td["action"], torch.tensor([[1.0, -1.0, 0.5], [0.0, 0.0, 0.0]]))
    env.close()


def test_transfer_settings_are_validated_and_leave_offline_runs_as_they_were():
    with pytest.raises(ValueError) as err:
        validate_config({"transfer": {"task": "sideways", "online_frames": 0, "decoder": "drop", "from_scratch": "yes"}})
    for key in ("transfer.task", "transfer.online_frames", "transfer.decoder", "transfer.from_scratch"):
        assert key in str(err.value)
    base = {"algo": {"name": "moc"}, "seed": 0, "train": {"total_frames": 10}}
    off = {**base, "transfer": {"task": None, "online_frames": 300000}}
    # an offline-only run has the fingerprint it had before the transfer settings existed: its checkpoints still resume
    assert config_fingerprint(off) == config_fingerprint(base)
    on = {**base, "transfer": {"task": "backward", "online_frames": 1000}}
    assert config_fingerprint(on) != config_fingerprint(base)
    # the online budget may grow on resume; the task may not change
    assert config_fingerprint({**base, "transfer": {"task": "backward", "online_frames": 5000}}) == config_fingerprint(on)
    assert config_fingerprint({**base, "transfer": {"task": "forward", "online_frames": 1000}}) != config_fingerprint(on)


def test_dataset_agents_refuse_the_transfer_setting(hopper_file, cache, tmp_path):
    from hydra import compose, initialize_config_dir


    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base=None):
        cfg = compose("offline_train", overrides=["algo=bc", f"dataset={hopper_file}", f"out_root={tmp_path}", *TINY[:4], *TRANSFER])
    with pytest.raises(ValueError, match="learns from the dataset itself.*transfer.task null"):
        train(cfg, progress=False)


@pytest.fixture(scope="module")
def moc_transfer_run(hopper_file, cache, tmp_path_factory):
    out = tmp_path_factory.mktemp("transfer")
    return train(_cfg("moc", hopper_file, out, TRANSFER), progress=False)


def test_two_phase_run_evaluates_both_tasks_at_the_switch(moc_transfer_run):
    s = moc_transfer_run
    run = Path(s["run_dir"])
    assert run.name.endswith("-to-backward-seed0")
    evals = json.loads((run / "evals.json").read_text())
    assert [(e["frames"], e["phase"], e["task"]) for e in evals] == [
        (128, "offline", "forward"), (256, "offline", "forward"),  # offline: the old task, through the decoder
        (256, "online", "backward"),  # the switch: the same agent on the new task, decoder discarded
        (384, "online", "backward"), (512, "online", "backward"),
    ]
    # D4RL's normalisation is the forward task's: none on the backward task
    assert all(e["normalized_d4rl"] is not None for e in evals[:2]) and all(e["normalized_d4rl"] is None for e in evals[2:])
    assert s["transfer"]["switch_frame"] == 256 and s["frames"] == 512 and s["offline_final"]["frames"] == 256
    assert s["final"]["task"] == "backward"
    # the offline phase's last evaluation files are kept apart from the final ones
    assert (run / "offline" / "option_usage.png").is_file() and (run / "option_usage.png").is_file()
    # the eval log continues on one x-axis of frames across the switch
    logged = [int(line.split(",")[0]) for line in (run / "logs" / "scalars" / "eval" / "return_mean.csv").read_text().split()]
    assert logged == [128, 256, 384, 512]
    from torchrl_offhrl.recipes.evaluation import evaluate_run

    res = evaluate_run(run, episodes=2)
    assert res["task"] == "backward" and res["normalized_d4rl"] is None


def test_transfer_table_and_curves(moc_transfer_run, tmp_path):
    table = aggregate([moc_transfer_run["run_dir"]], tmp_path)
    assert "to-backward" in table and "at the switch" in table
    assert (tmp_path / "transfer.csv").is_file() and (tmp_path / "curves.png").is_file()


def test_transfer_stats_hand_computed():
    def rec(frames, phase, ret):
        return {"frames": frames, "phase": phase, "return_mean": ret}

    a = {"evals": [rec(0, "offline", 5.0), rec(100, "offline", 9.0), rec(100, "online", 1.0), rec(150, "online", 3.0), rec(200, "online", 2.0)]}
    b = {"evals": [rec(0, "offline", 7.0), rec(100, "offline", 11.0), rec(100, "online", 3.0), rec(152, "online", 5.0), rec(200, "online", 6.0)]}
    st = transfer_stats([a, b], marks=(50, 100, 300))
    assert st["seeds"] == 2 and st["online_frames"] == 100
    assert st["offline_final"] == (10.0, pytest.approx(2 ** 0.5), 2)
    # b evaluated at 52 frames after its switch, not 50: the first evaluation at or after the mark counts
    assert st["at_switch"][0] == 2.0 and st["at_50"][0] == 4.0 and st["at_100"][0] == 4.0
    assert st["at_300"] == (None, None, 0)  # no run got that far
    assert st["best"][0] == pytest.approx((3.0 + 6.0) / 2)
    # trapezoid area / length: a: (1+3)/2*50 + (3+2)/2*50 = 225 -> 2.25; b: (3+5)/2*52 + (5+6)/2*48 = 472 -> 4.72
    assert st["area"][0] == pytest.approx((2.25 + 4.72) / 2)


def _killing_agents(monkeypatch, kills) -> dict:
    """Make the run's agents raise KeyboardInterrupt (a kill) at each of ``kills`` in turn: ``"switch"`` (at the task switch,
    after the offline phase's last checkpoint, before the online one) and ``"online"`` (the third online batch of 64 frames,
    after the online evaluation and checkpoint at 384). Returns the counts of switches and online updates."""
    real_make_agent = recipe_mod.make_agent
    state = {"new_task": 0, "online_updates": 0, "kills": list(kills)}

    def killing_agent(*a, **k):
        agent = real_make_agent(*a, **k)
        real_update, real_new_task = agent.update, agent.new_task

        def new_task():
            state["new_task"] += 1
            if state["kills"][:1] == ["switch"]:
                state["kills"].pop(0)
                raise KeyboardInterrupt
            real_new_task()

        def update(batch):
            if state["new_task"]:
                state["online_updates"] += 1
                if state["kills"][:1] == ["online"] and state["online_updates"] == 3:
                    state["kills"].pop(0)
                    raise KeyboardInterrupt
            return real_update(batch)

        agent.new_task, agent.update = new_task, update
        return agent

    monkeypatch.setattr(recipe_mod, "make_agent", killing_agent)
    return state


def test_resumes_across_the_switch_after_a_kill(hopper_file, cache, tmp_path, monkeypatch):
    cfg = _cfg("moc", hopper_file, tmp_path, TRANSFER)
    state = _killing_agents(monkeypatch, ["switch", "online"])
    with pytest.raises(KeyboardInterrupt):
        train(cfg, progress=False)
    run = next(tmp_path.glob("moc-*"))
    assert [e["phase"] for e in json.loads((run / "evals.json").read_text())] == ["offline", "offline"]
    with pytest.raises(KeyboardInterrupt):
        train(cfg, progress=False)
    assert [(e["frames"], e["phase"]) for e in json.loads((run / "evals.json").read_text())] == [
        (128, "offline"), (256, "offline"), (256, "online"), (384, "online")]
    s = train(cfg, progress=False)
    evals = json.loads((run / "evals.json").read_text())
    # each evaluation once, the switch once, the online budget counted from the switch
    assert [(e["frames"], e["phase"]) for e in evals] == [(128, "offline"), (256, "offline"), (256, "online"), (384, "online"), (512, "online")]
    assert s["frames"] == 512 and s["transfer"]["switch_frame"] == 256
    assert state["new_task"] == 2  # the interrupted switch, then the resumed one; never again once the online phase had begun


@pytest.mark.fault("resume")
def test_a_run_killed_in_its_online_phase_resumes_to_the_records_of_an_uninterrupted_one(hopper_file, cache, tmp_path, monkeypatch):
    """The online phase's checkpoint keeps the real envs where they stood (each simulator's MuJoCo state, its time limit's
    step count and its reset RNG, beside the collector's carrier): killed after the evaluation at 384 frames and resumed,
    the run's later records equal those of the run made in one go, bit for bit (before, the real envs restarted their
    episodes on resume)."""
    straight = train(_cfg("moc", hopper_file, tmp_path / "a", TRANSFER), progress=False)
    cfg = _cfg("moc", hopper_file, tmp_path / "b", TRANSFER)
    state = _killing_agents(monkeypatch, ["online"])
    with pytest.raises(KeyboardInterrupt):
        train(cfg, progress=False)
    assert state["kills"] == []  # killed once; the resumed run goes on unharmed
    resumed = train(cfg, progress=False)
    a = json.loads((Path(straight["run_dir"]) / "evals.json").read_text())
    b = json.loads((Path(resumed["run_dir"]) / "evals.json").read_text())
    assert [(e["frames"], e["phase"]) for e in b] == [(128, "offline"), (256, "offline"), (256, "online"), (384, "online"), (512, "online")]
    for x, y in zip(a, b, strict=True):
        assert {k: v for k, v in x.items() if k != "wall_s"} == {k: v for k, v in y.items() if k != "wall_s"}


def test_sac_starts_a_fresh_buffer_on_the_new_task(hopper_file, cache, tmp_path, monkeypatch):
    seen = {}
    real_make_agent = recipe_mod.make_agent

    def watching_agent(*a, **k):
        agent = real_make_agent(*a, **k)
        real_new_task = agent.new_task

        def new_task():
            seen["before"] = (len(agent.replay_buffer), agent.frames)
            real_new_task()
            seen["after"] = (len(agent.replay_buffer), agent.frames)

        agent.new_task = new_task
        return agent

    monkeypatch.setattr(recipe_mod, "make_agent", watching_agent)
    short = ["train.total_frames=128", "transfer.online_frames=128"]
    s = train(_cfg("sac", hopper_file, tmp_path, [*TRANSFER, *short]), progress=False)
    assert seen["before"] == (128, 128) and seen["after"] == (0, 0)
    assert transfer_config({"transfer": s["transfer"]})["task"] == "backward"


def test_from_scratch_has_no_offline_phase_and_fits_no_model(hopper_file, cache, tmp_path, monkeypatch):
    def no_models(*a, **k):
        raise AssertionError("a from-scratch run without the decoder fits no model")

    monkeypatch.setattr(recipe_mod, "fit_or_load_models", no_models)
    s = train(_cfg("ppo", hopper_file, tmp_path, [*TRANSFER, "transfer.from_scratch=true"]), progress=False)
    evals = json.loads((Path(s["run_dir"]) / "evals.json").read_text())
    assert [(e["frames"], e["phase"]) for e in evals] == [(0, "online"), (128, "online"), (256, "online")]
    assert s["transfer"]["switch_frame"] == 0 and s["offline_final"] is None and Path(s["run_dir"]).name.endswith("-scratch-backward-seed0")


def test_offline_phase_is_the_offline_run_of_the_same_seed(moc_transfer_run, hopper_file, cache, tmp_path):
    # the online envs are built under a forked RNG: the transfer run's offline phase repeats the plain run draw for draw
    plain = train(_cfg("moc", hopper_file, tmp_path), progress=False)
    plain_evals = json.loads((Path(plain["run_dir"]) / "evals.json").read_text())
    offline = [e for e in json.loads((Path(moc_transfer_run["run_dir"]) / "evals.json").read_text()) if e["phase"] == "offline"]
    assert [(e["frames"], e["return_mean"]) for e in offline] == [(e["frames"], e["return_mean"]) for e in plain_evals]
