"""The SAC / PPO / MOC offline recipes end to end on tiny settings, resumption, aggregation."""
import json
import math
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from torchrl_offhrl.recipes import rundir
from torchrl_offhrl.recipes import train as recipe_mod  # where the run builds its agent and models (recipes.train)
from torchrl_offhrl.recipes.config import compose, model_config, pessimism_for
from torchrl_offhrl.recipes.report import aggregate
from torchrl_offhrl.recipes.train import train
from torchrl_offhrl.utils import to_plain

ROOT = Path(__file__).resolve().parents[1]
TINY = [
    "ensemble.hidden_sizes=[32,32]",
    "ensemble.fit.max_steps=40",
    "cvae.hidden_sizes=[32,32]",
    "cvae.fit.max_steps=40",
    "collector.num_envs=4",
    "train.total_frames=256",
    "eval.every_frames=128",
    "eval.episodes=2",
    "eval.max_steps=40",
    "algo.frames_per_batch=64",
    "eval.at_start=false",
]
ALGO_TINY = {"sac": ["algo.init_random_frames=64", "algo.utd_ratio=0.25", "algo.batch_size=32"], "ppo": ["algo.epochs=2"], "moc": ["algo.epochs=2"]}
# MOPO's rollout schedule, small: a rollout of 8 envs x 5 steps, then 16 gradient steps (configs/algo/mopo.yaml's 50,000 and 1,000)
ALGO_TINY["mopo"] = ["algo.batch_size=32", "algo.real_ratio=0.25", "algo.rollout_batch_size=8", "algo.rollout_freq=16"]


def _cfg(algo, data, out, extra=()):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base=None):
        return compose("offline_train", overrides=[f"algo={algo}", f"dataset={data}", f"out_root={out}", *TINY, *ALGO_TINY[algo], *extra])


def _interrupt_at_update(cfg, n: int, monkeypatch) -> None:
    """Train ``cfg`` until its agent's ``n``-th update, interrupted there (KeyboardInterrupt, as a kill); the agent factory
    is restored afterwards, so the next ``train(cfg)`` resumes the run."""
    real_make_agent = recipe_mod.make_agent
    calls = {"n": 0}

    def crashing_agent(*a, **k):
        agent = real_make_agent(*a, **k)
        real_update = agent.update

        def update(batch):
            calls["n"] += 1
            if calls["n"] == n:
                raise KeyboardInterrupt
            return real_update(batch)

        agent.update = update
        return agent

    monkeypatch.setattr(recipe_mod, "make_agent", crashing_agent)
    with pytest.raises(KeyboardInterrupt):
        train(cfg, progress=False)
    monkeypatch.setattr(recipe_mod, "make_agent", real_make_agent)


@pytest.mark.parametrize("algo", ["sac", "ppo", "moc"])
def test_recipe_end_to_end(algo, hopper_file, cache, tmp_path):
    summary = train(_cfg(algo, hopper_file, tmp_path), progress=False)
    run = Path(summary["run_dir"])
    # a file dataset: its stem plus a hash of its path
    assert re.fullmatch(rf"{algo}-hopper-hopper_random-[0-9a-f]{{6}}-seed0", run.name), run.name
    assert summary["frames"] == 256 and summary["updates"] > 0
    evals = json.loads((run / "evals.json").read_text())
    assert [e["frames"] for e in evals] == [128, 256]
    final = evals[-1]
    assert final["normalized_d4rl"] == pytest.approx(100 * (final["return_mean"] + 20.272305) / (3234.3 + 20.272305))
    for f in ("checkpoint.pt", "summary.json", "config.json", "learning_curve.png"):
        assert (run / f).is_file(), f
    assert (run / "logs" / "scalars" / "eval" / "return_mean.csv").is_file()
    cfg = json.loads((run / "config.json").read_text())
    # no table: the offline rules set the threshold and the penalty, and the run's calibration report says so
    cal = json.loads((run / "calibration.json").read_text())
    assert cfg["resolved_pessimism"] == {"threshold": cal["threshold"], "penalty": cal["penalty"]} and cfg["threshold"] == cal["threshold"]
    assert cfg["resolved_model_env"] == {k: cal[k] for k in ("horizon", "reset_states", "latent_bound")}
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["frames"] == 256
    if algo == "moc":
        usage = torch.load(run / "option_usage.pt")
        assert usage.shape[1] == cfg["algo"]["num_options"] == 2 and (run / "option_usage.png").is_file()
        # every step of a running episode has exactly one active option
        rows = usage[usage.sum(-1) > 0]
        torch.testing.assert_close(rows.sum(-1), torch.ones(rows.shape[0]))
        assert sum(final["option_usage_mean"]) == pytest.approx(1.0)


@pytest.mark.fault("resume")
def test_interrupted_run_resumes_from_checkpoint(hopper_file, cache, tmp_path, monkeypatch):
    cfg = _cfg("moc", hopper_file, tmp_path)
    _interrupt_at_update(cfg, 4, monkeypatch)  # after the checkpoint at 128 frames and the logged update at 192
    run = next(tmp_path.glob("moc-*"))
    first = json.loads((run / "evals.json").read_text())
    assert [e["frames"] for e in first] == [128]
    saved = torch.load(run / "checkpoint.pt", weights_only=True)["agent"]["loss"]

    loaded = {}
    real_load = recipe_mod.make_agent

    def spy_make_agent(*a, **k):
        agent = real_load(*a, **k)
        orig = agent.load_state_dict

        def load(state):
            orig(state)
            loaded.update({k: v.clone() for k, v in agent.loss.state_dict().items()})

        agent.load_state_dict = load
        return agent

    monkeypatch.setattr(recipe_mod, "make_agent", spy_make_agent)
    summary = train(cfg, progress=False)
    evals = json.loads((run / "evals.json").read_text())
    assert [e["frames"] for e in evals] == [128, 256]
    assert evals[0] == first[0]  # the record from before the interruption is kept
    assert summary["frames"] == 256
    for k, v in saved.items():  # the second run started from the checkpoint's weights
        torch.testing.assert_close(loaded[k], v)
    # the CSV logs hold each step once: rows logged after the checkpoint were dropped on resume
    logs = sorted((run / "logs").glob("**/*.csv"))
    assert logs
    for csv in logs:
        steps = [float(line.split(",")[0]) for line in csv.read_text().splitlines() if line]
        assert steps == sorted(set(steps)), (csv, steps)

    # the finished run called again (a results script rerun) trains nothing and keeps the timings it measured
    again = train(cfg, progress=False)
    assert again["frames"] == 256 and json.loads((run / "evals.json").read_text()) == evals
    timings = ("frames_per_s", "updates_per_s", "update_time_s", "data_s", "models_s", "total_s")
    assert {k: again[k] for k in timings} == {k: summary[k] for k in timings} and summary["frames_per_s"] is not None


def test_trim_csv_logs(tmp_path):
    (tmp_path / "scalars" / "train").mkdir(parents=True)
    f = tmp_path / "scalars" / "train" / "loss.csv"
    f.write_text("64,1.0\n128,2.0\n192,3.0\n")
    assert rundir.trim_csv_logs(tmp_path, 128) == 1
    assert f.read_text() == "64,1.0\n128,2.0\n"
    assert rundir.trim_csv_logs(tmp_path, 128) == 0


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_evaluation_at_start(algo, hopper_file, cache, tmp_path):
    """eval.at_start: the untrained agent is evaluated first; a resumed run does not do it again."""
    cfg = _cfg(algo, hopper_file, tmp_path, ["eval.at_start=true"])
    summary = train(cfg, progress=False)
    evals = json.loads((Path(summary["run_dir"]) / "evals.json").read_text())
    assert [(e["frames"], e["updates"]) for e in evals][:1] == [(0, 0)]
    assert [e["frames"] for e in evals] == [0, 128, 256]
    assert summary["initial"] == evals[0] and summary["final"] == evals[-1]
    more = train(_cfg(algo, hopper_file, tmp_path, ["eval.at_start=true", "train.total_frames=384"]), progress=False)
    assert [e["frames"] for e in json.loads((Path(more["run_dir"]) / "evals.json").read_text())] == [0, 128, 256, 384]
    assert more["initial"] == evals[0]
    assert train(_cfg(algo, hopper_file, tmp_path / "off"), progress=False)["initial"] is None


def test_ablation_no_cvae_acts_in_real_actions(hopper_file, cache, tmp_path):
    summary = train(_cfg("ppo", hopper_file, tmp_path, ["ablation.no_cvae=true", "ablation.no_pessimism=true"]), progress=False)
    run = Path(summary["run_dir"])
    assert run.name.endswith("-no_cvae-no_pessimism-seed0")
    assert summary["pessimism"] == {"threshold": float("inf"), "penalty": 0.0}
    assert summary["frames"] == 256


def test_pessimism_table_is_the_papers():
    """The paper's per-dataset table lives in the paper preset only (configs/preset/paper.yaml), keyed by env."""
    from omegaconf import OmegaConf

    from torchrl_offhrl.recipes.config import pessimism_table

    paper = OmegaConf.to_container(OmegaConf.load(ROOT / "configs" / "preset" / "paper.yaml"))
    hop = pessimism_table({**paper, "env": {"name": "hopper"}})
    hc = pessimism_table({**paper, "env": {"name": "halfcheetah"}})
    assert pessimism_for({}, "medium", table=hop) == {"fraction": 1.08, "penalty": 20.0}
    assert pessimism_for({}, "medium-expert", table=hop) == {"fraction": 0.08, "penalty": 30.0}
    assert pessimism_for({}, "medium", table=hc) == {"fraction": 0.1, "penalty": 20.0}
    assert pessimism_for({}, "medium-expert", table=hc) == {"fraction": 0.0101, "penalty": 20.0}
    assert pessimism_for({}, None, table=hop) == {"quantile": 0.99, "penalty": 20.0}
    # overrides: a penalty keeps the table's fraction; a quantile replaces it
    assert pessimism_for({}, "medium", {"penalty": 50.0}, table=hop) == {"fraction": 1.08, "penalty": 50.0}
    assert pessimism_for({}, "medium", {"quantile": 0.95, "fraction": None}, table=hop) == {"quantile": 0.95, "penalty": 20.0}
    for env in ("hopper", "halfcheetah"):  # no per-dataset numbers where the default reads
        assert "pessimism" not in OmegaConf.load(ROOT / "configs" / "env" / f"{env}.yaml")


def test_paper_hyperparameters_in_configs():
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base=None):
        moc = compose("offline_train", overrides=["algo=moc"]).algo
        ppo_h = compose("offline_train", overrides=["algo=ppo", "env=hopper"]).algo
        ppo_c = compose("offline_train", overrides=["algo=ppo", "env=halfcheetah"]).algo
    assert (moc.lr, moc.clip_epsilon, moc.eta, moc.gamma, moc.lmbda) == (1e-4, 0.2, 0.7, 0.99, 0.95)
    assert (ppo_h.lr, ppo_h.clip_epsilon, ppo_c.lr, ppo_c.clip_epsilon) == (9.80828e-05, 0.1, 3e-4, 0.2)
    assert (ppo_h.frames_per_batch, ppo_h.critic_coeff, ppo_h.entropy_coeff) == (2048, 0.835671, 0.00229519)


def test_aggregate_seeds(tmp_path):
    for seed, offset in ((0, 0.0), (1, 10.0)):
        d = tmp_path / f"moc-hopper-medium-seed{seed}"
        d.mkdir()
        evals = [{"frames": f, "return_mean": f / 10 + offset, "return_std": 1.0, "normalized_d4rl": f / 100 + offset} for f in (100, 200)]
        (d / "evals.json").write_text(json.dumps(evals))
        (d / "config.json").write_text(json.dumps({"algo": {"name": "moc"}, "env": {"env_id": "Hopper-v5"}, "dataset": "medium", "ablation": {},
                                                   "model_env": {"latent_origin": "best"}}))  # the default, not the paper preset
    table = aggregate(sorted(tmp_path.glob("moc-*")), tmp_path / "agg")
    # final returns 20 and 30: mean 25, std 7.07; scores 2 and 12: mean 7
    # best per seed: 2 and 12 (the last evaluation here); no frame-0 evaluation: untrained n/a; no summary: behaviour n/a
    # IQM of 2 values: their mean (nothing cut); the bootstrap CI of 2 values spans them; last 5 evaluations: 1.5 and 11.5;
    # no policy selection in these runs (no summary): —; no start: no change; seeds not in the configs: s?
    assert ("| moc | Hopper-v5 | medium | - | 2 | 200 frames | 25.0 ± 7.1 | 7.0 [2.0, 12.0] | 7.0 ± 7.1 | 6.5 [1.5, 11.5] | — | "
            "7.0 [2.0, 12.0] | n/a | n/a | n/a | s?: 2.0, s?: 12.0 |") in table
    assert (tmp_path / "agg" / "curves.png").is_file() and (tmp_path / "agg" / "results.csv").is_file()
    # a sweep's folder (its run directories beside Ray's files) stands for the runs in it
    sweep = tmp_path / "sweep"
    (sweep / "ray-experiment" / "trial_0").mkdir(parents=True)
    (sweep / "ray-experiment" / "tuner.pkl").write_text("")
    for d in sorted(tmp_path.glob("moc-*")):
        d.rename(sweep / d.name)
    assert aggregate([sweep], tmp_path / "agg2") == table.replace(str(tmp_path / "agg"), str(tmp_path / "agg2"))
    with pytest.raises(FileNotFoundError, match="ray-experiment has no evals.json: not a run directory"):
        aggregate([sweep / "ray-experiment"], tmp_path / "agg3")


def test_offline_train_script_cli(hopper_file, cache, tmp_path):
    """The user-facing script, through hydra's command line, runs the one training loop as `train` does: the same
    evaluation records (wall times aside) and the same returned policy as `train` on the same config."""
    script = tmp_path / "script"
    one_thread = ["torch_threads=1", "fit_threads=1"]  # both processes sum in the same order, whatever threads pytest runs with
    args = [sys.executable, str(ROOT / "examples" / "offline_train.py"), "algo=moc", f"dataset={hopper_file}", f"out_root={script}",
            *TINY, *ALGO_TINY["moc"], *one_thread]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=300, env={**os.environ})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "D4RL-normalised" in proc.stdout and "calibration report" in proc.stdout
    (by_script,) = script.glob("moc-hopper-hopper_random-*-seed0/summary.json")
    by_train = Path(train(_cfg("moc", hopper_file, tmp_path / "train", one_thread), progress=False)["run_dir"])
    a = json.loads((by_script.parent / "evals.json").read_text())
    b = json.loads((by_train / "evals.json").read_text())
    assert len(a) == len(b) > 1
    for x, y in zip(a, b):
        assert {k: v for k, v in x.items() if k != "wall_s"} == {k: v for k, v in y.items() if k != "wall_s"}
    sa, sb = json.loads(by_script.read_text()), json.loads((by_train / "summary.json").read_text())
    timeless = lambda d: {k: timeless(v) if isinstance(v, dict) else v for k, v in d.items() if k != "wall_s"}  # noqa: E731
    assert timeless(sa["selected"]) == timeless(sb["selected"]) and sa["guard"]["fired"] == sb["guard"]["fired"]


def test_option_usage_hand_computed():
    from tensordict import TensorDict

    from torchrl_offhrl.agents.moc import option_usage

    td = TensorDict(
        {
            "option": torch.tensor([[0, 0, 1, 1], [2, 2, 2, 3]]),
            "next": {"done": torch.tensor([[False, True, False, False], [False, False, True, False]]).unsqueeze(-1)},
        },
        batch_size=[2, 4],
    )
    usage = option_usage(td, 4)
    # env 0 runs steps 0-1 (option 0), env 1 steps 0-2 (option 2); step 3 belongs to no running episode
    expected = torch.tensor([[0.5, 0, 0.5, 0], [0.5, 0, 0.5, 0], [0, 0, 1, 0]])
    torch.testing.assert_close(usage, expected)


def test_resume_refuses_another_configuration(hopper_file, cache, tmp_path):
    train(_cfg("ppo", hopper_file, tmp_path), progress=False)
    with pytest.raises(ValueError, match="different configuration"):
        train(_cfg("ppo", hopper_file, tmp_path, ["algo.lr=0.01"]), progress=False)
    # a longer budget is a resumption, not another run
    summary = train(_cfg("ppo", hopper_file, tmp_path, ["train.total_frames=384"]), progress=False)
    assert summary["frames"] == 384


@pytest.mark.fault("resume")
def test_sac_resumes_with_its_replay_buffer(hopper_file, cache, tmp_path):
    train(_cfg("sac", hopper_file, tmp_path, ["algo.buffer_size=1000"]), progress=False)
    (run,) = tmp_path.glob("sac-*")
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert state["replay"] == "replay-256" and [p.name for p in run.glob("replay-*")] == ["replay-256"]
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    rb = ReplayBuffer(storage=LazyTensorStorage(1000))
    rb.loads(run / "replay-256")
    assert len(rb) == 256  # every collected frame is in the saved buffer
    summary = train(_cfg("sac", hopper_file, tmp_path, ["algo.buffer_size=1000", "train.total_frames=384"]), progress=False)
    assert summary["frames"] == 384
    rb = ReplayBuffer(storage=LazyTensorStorage(1000))
    rb.loads(run / "replay-384")
    assert len(rb) == 384  # the resumed run kept the first 256 frames and added 128
    assert [p.name for p in run.glob("replay-*")] == ["replay-384"]  # the old buffer is gone


def test_sac_target_entropy_is_per_env():
    """The default target entropy is -(latent action dim), not -(envs x dim)."""
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    env = make_model_env(
        {"env": {"threshold": 1.0}},
        DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)),
        ConditionalVAE.for_dataset(d, hidden_sizes=(8,)),
        d,
        batch_size=64,
    )
    agent = make_agent("sac", env, {"frames_per_batch": 64})
    assert float(agent.loss.target_entropy) == -2.0


def test_reward_scale_auto_is_one_over_the_datasets_return_std():
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.recipes.config import compose, model_env_config
    from torchrl_offhrl.utils import to_plain

    data = make_toy_dataset(num_episodes=6, episode_length=30, seed=1)
    cfg = to_plain(compose("offline_train", ["model_env.reward_scale=auto", "algo=ppo", "algo.gamma=0.9"]))
    menv, _ = model_env_config(cfg, "medium", data)
    assert menv["reward_scale"] == pytest.approx(1.0 / float(data.returns_to_go(0.9).std()))
    assert menv["reward_scale"] != pytest.approx(1.0 / float(data.returns_to_go(0.99).std()))  # the agent's gamma is used
    with pytest.raises(ValueError, match="pass data"):
        model_env_config(cfg, "medium")
    for bad in ("0", "-1", "'x'"):
        with pytest.raises(ValueError, match="reward_scale"):
            model_env_config(to_plain(compose("offline_train", [f"model_env.reward_scale={bad}"])), "medium", data)


def test_aggregate_reports_best_and_untrained_apart_from_final(tmp_path):
    """A seed whose best evaluation is not its last: final, best and the frame-0 score are three different columns."""
    for seed, scores in ((0, (5.0, 9.0, 3.0)), (1, (7.0, 8.0, 6.0))):
        d = tmp_path / f"ppo-hopper-medium-seed{seed}"
        d.mkdir()
        evals = [{"frames": f, "return_mean": 10 * s, "return_std": 0.0, "normalized_d4rl": s} for f, s in zip((0, 100, 200), scores)]
        (d / "evals.json").write_text(json.dumps(evals))
        (d / "config.json").write_text(json.dumps({"algo": {"name": "ppo"}, "env": {"env_id": "Hopper-v5"}, "dataset": "medium", "ablation": {},
                                                   "model_env": {"latent_origin": "best"}}))  # the default, not the paper preset
    table = aggregate(sorted(tmp_path.glob("ppo-*")), tmp_path / "agg")
    # final 3, 6 -> 4.5 ± 2.1; best 9, 8 -> 8.5; untrained 5, 7 -> 6.0; change over the start: -2 and -1 -> -1.5, 0 of 2 up
    row = next(line for line in table.splitlines() if line.startswith("| ppo |")).split(" | ")
    assert row[6:9] == ["45.0 ± 21.2", "4.5 [3.0, 6.0]", "4.5 ± 2.1"]
    assert row[11:14] == ["8.5 [8.0, 9.0]", "6.0", "-1.5 [-2.0, -1.0] (0/2)"]
    # a seed whose untrained start is its highest score: the best counts evaluations after training began only
    d = tmp_path / "ppo-hopper-medium-seed2"
    d.mkdir()
    evals = [{"frames": f, "return_mean": 10 * s, "return_std": 0.0, "normalized_d4rl": s} for f, s in zip((0, 100, 200), (20.0, 4.0, 5.0))]
    (d / "evals.json").write_text(json.dumps(evals))
    (d / "config.json").write_text((tmp_path / "ppo-hopper-medium-seed0" / "config.json").read_text())
    table = aggregate(sorted(tmp_path.glob("ppo-*")), tmp_path / "agg")
    # final 3, 6, 5 -> 4.67 ± 1.53; best 9, 8, 5 -> IQM (3 values, nothing cut) 7.33; untrained 5, 7, 20 -> 10.7
    row = next(line for line in table.splitlines() if line.startswith("| ppo |")).split(" | ")
    assert row[6] == "46.7 ± 15.3" and row[8] == "4.7 ± 1.5" and row[11].startswith("7.3 [") and row[12] == "10.7"


def test_logged_tail_mean_reads_the_csv_logs(tmp_path):
    from torchrl_offhrl.recipes.report import logged_tail_mean, read_scalar_logs

    d = tmp_path / "logs" / "scalars" / "train"
    d.mkdir(parents=True)
    (d / "termination_rate.csv").write_text("".join(f"{f},{v}\n" for f, v in zip(range(0, 700, 100), (9, 9, 1, 2, 3, 4, 5))))
    (d / "empty.csv").write_text("")
    assert logged_tail_mean(tmp_path, "termination_rate") == pytest.approx(3.0)  # mean of the last 5: 1..5
    assert logged_tail_mean(tmp_path, "termination_rate", n=2) == pytest.approx(4.5)
    assert logged_tail_mean(tmp_path, "missing") is None and logged_tail_mean(tmp_path, "empty") is None
    assert list(read_scalar_logs(tmp_path / "logs")) == ["train/termination_rate"]


@pytest.mark.fault("paths")
@pytest.mark.parametrize("name", ["../../outside", "/tmp", "replay-12/../..", 7])
def test_resume_refuses_a_replay_name_outside_the_run(tmp_path, name):
    """A checkpoint's replay folder is later removed with rmtree: a crafted name must not reach outside the run."""
    victim = tmp_path / "outside"
    victim.mkdir()
    run = rundir.RunDirectory(tmp_path / "a" / "run", "fp")
    torch.save({"agent": {}, "frames": 1, "updates": 1, "records": [], "rng": torch.get_rng_state(), "replay": name,
                "fingerprint": "fp"}, run.checkpoint_path)

    class Agent:
        replay_buffer = None

        def load_state_dict(self, state):
            pass

    with pytest.raises(ValueError, match="replay-<frames>"):
        run.resume(Agent())
    assert victim.is_dir()


def test_model_env_reset_states_from_the_config():
    """``model_env.reset_states`` reaches the env; an explicit argument (the evaluation's "initial") wins over it."""
    from torchrl_offhrl.data import make_toy_dataset
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble
    from torchrl_offhrl.recipes.pipeline import make_model_env

    d = make_toy_dataset(num_episodes=4, episode_length=10)
    ens, cvae = DynamicsEnsemble.for_dataset(d, num_models=2, hidden_sizes=(8,)), ConditionalVAE.for_dataset(d, hidden_sizes=(8,))
    cfg = {"env": {"threshold": 1.0, "reset_states": "any"}}
    anywhere = make_model_env(cfg, ens, cvae, d, batch_size=4).base_env
    assert anywhere.start_states.shape[0] == d.data.shape[0] == 40
    initial = make_model_env(cfg, ens, cvae, d, batch_size=4, reset_states="initial").base_env
    assert torch.equal(initial.start_states, d.initial_observations().float())
    assert initial.start_states.shape[0] == 4
    assert make_model_env({"env": {"threshold": 1.0}}, ens, cvae, d, batch_size=4).base_env.start_states.shape[0] == 4


def test_a_run_directory_holds_one_run_at_a_time(tmp_path):
    """A second run on a locked directory is refused (another process, or this one); a dead holder does not block."""
    run = rundir.RunDirectory(tmp_path / "run", "fp")
    with run.locked():
        with pytest.raises(RuntimeError, match=f"pid {os.getpid()}"):
            with rundir.RunDirectory(tmp_path / "run", "fp").locked():
                pass
        other = subprocess.run(
            [sys.executable, "-c", "import sys; from torchrl_offhrl.recipes.rundir import RunDirectory\n"
             "try:\n    RunDirectory(sys.argv[1], 'fp').locked().__enter__()\nexcept RuntimeError as e:\n    print(e); sys.exit(3)",
             str(tmp_path / "run")], capture_output=True, text=True)
        assert other.returncode == 3 and "in use by a run" in other.stdout
    with run.locked():  # released after the block
        pass
    # a holder killed with SIGKILL leaves the lock file, not the lock
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from torchrl_offhrl.recipes.rundir import RunDirectory\n"
         "cm = RunDirectory(sys.argv[1], 'fp').locked(); cm.__enter__(); print('locked', flush=True); time.sleep(60)", str(tmp_path / "run")],
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "locked"
    with pytest.raises(RuntimeError, match="in use"):
        with run.locked():
            pass
    holder.kill()
    holder.wait()
    with run.locked():
        pass


def test_a_dataset_replaced_at_the_same_path_is_not_mistaken_for_the_old_one(hopper_file, cache, tmp_path, capsys):
    """Issue 14's probe 1: another file of the same length at the same path gets new models and does not resume the old run."""
    import shutil

    from torchrl_offhrl.data import collect_dataset, load_dataset, save_dataset

    path = tmp_path / "mydata.hdf5"
    shutil.copyfile(hopper_file, path)
    first = train(_cfg("ppo", path, tmp_path / "runs"), progress=False)
    (run,) = (tmp_path / "runs").glob("ppo-*")
    old = load_dataset(path)
    save_dataset(collect_dataset("Hopper-v5", len(old), num_envs=4, seed=1, progress=False), path)  # same length, other data
    assert len(load_dataset(path)) == len(old)
    with pytest.raises(ValueError, match="holds a run trained on other data"):
        train(_cfg("ppo", path, tmp_path / "runs", ["train.total_frames=384"]), progress=False)
    out = capsys.readouterr().out
    assert f"the data at {path} is not what the cached models" in out and first["models"] in out
    # elsewhere, the new data trains with its own models
    second = train(_cfg("ppo", path, tmp_path / "runs2"), progress=False)
    assert second["models"] != first["models"]
    assert json.loads((run / "config.json").read_text())["data_hash"] == old.content_hash() != load_dataset(path).content_hash()


def test_tensorboard_logs_after_the_checkpoint_are_not_repeated_on_resume(tmp_path):
    """A resumed run re-logs the steps after its checkpoint; TensorBoard readers must see each step once, with the new value."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = rundir.RunDirectory(tmp_path / "run", "fp")
    first = run.logger("tensorboard")
    for step in (100, 200, 300, 400):
        first.log_scalar("x", float(step), step=step)
    first.experiment.close()
    run.frames = 200  # the checkpoint the run resumes from
    again = run.logger("tensorboard")
    for step in (300, 400, 500):
        again.log_scalar("x", -float(step), step=step)
    again.experiment.close()
    acc = EventAccumulator(again.experiment.log_dir)
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("x")] == [(100, 100.0), (200, 200.0), (300, -300.0), (400, -400.0), (500, -500.0)]


def test_a_refused_run_leaves_the_running_one_alone(tmp_path):
    """A run refused by the lock must not clean up the directory of the run that holds it, even while that one is still empty."""
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.utils import to_plain

    run = rundir.RunDirectory(tmp_path / "run", "fp")
    with run.locked():  # a run that has just started: nothing but its lock yet
        with pytest.raises(RuntimeError, match="in use by a run"):
            train(to_plain(compose("offline_train", [f"run_dir={tmp_path / 'run'}"])), progress=False)
        assert (tmp_path / "run" / ".lock").is_file()


@pytest.mark.parametrize("criterion", ["model_lcb", "model_mean"])
def test_offline_policy_selection_returns_the_policy_its_criterion_ranks_first(criterion, hopper_file, cache, tmp_path):
    """selected.pt holds the agent state of the evaluation with the best offline score (not a real-env one), checkpointed like the run."""
    from torchrl_offhrl.recipes.evaluation import load_run_agent
    from torchrl_offhrl.recipes.selection import CRITERIA

    extra = ["train.total_frames=384", "train.snapshot_frames=[128,256,384]", f"selection.criterion={criterion}", "eval.model_episodes=10"]
    summary = train(_cfg("moc", hopper_file, tmp_path, extra), progress=False)
    run = Path(summary["run_dir"])
    evals = json.loads((run / "evals.json").read_text())
    key = CRITERIA[criterion]
    # every member rolls out the same number of model episodes (10 = 2 per member): the worst member's mean is at most the mean
    assert all(e["model_return_min_member"] <= e["model_return_mean"] + 1e-6 for e in evals)
    best = max(evals, key=lambda e: e[key])  # ties: the first, as the selector keeps the earlier policy
    sel = summary["selected"]
    assert sel["frames"] == best["frames"] and sel["criterion"] == criterion and sel["offline_score"] == pytest.approx(best[key])
    assert sel["normalized_d4rl"] == best["normalized_d4rl"]  # its real-env score is the one measured when it was evaluated
    chosen = torch.load(run / "selected.pt", weights_only=True)
    snap = torch.load(run / f"snapshot-{best['frames']}.pt", weights_only=True)
    for k, v in snap["agent"]["loss"].items():
        torch.testing.assert_close(chosen["agent"]["loss"][k], v)
    # the run's returned policy is what `offhrl evaluate` loads by default; --policy last loads the checkpoint
    _, env, agent, state, _ = load_run_agent(run, num_envs=1, policy="selected")
    for k, v in agent.loss.state_dict().items():
        torch.testing.assert_close(v, snap["agent"]["loss"][k])
    env.close()
    assert state["frames"] == best["frames"]


def test_the_guard_returns_the_start_or_the_trained_policy_and_says_which(hopper_file, cache, tmp_path):
    """With model_gain_lcb and the guard on, selected.pt holds the policy the summary names: the start's weights
    when the guard fired, the candidate's otherwise; model episodes of the evaluations run the real episode's length whatever
    the training horizon (a model criterion then reads whole episodes)."""
    guarded = ["selection.criterion=model_gain_lcb", "selection.guard=true"]
    summary = train(_cfg("ppo", hopper_file, tmp_path / "g", ["seed=3", "model_env.horizon=20", "eval.at_start=true", "train.total_frames=256", *guarded]),
                    progress=False)
    run = Path(summary["run_dir"])
    guard, evals = summary["guard"], json.loads((run / "evals.json").read_text())
    assert summary["selected"]["criterion"] == "model_gain_lcb" and evals[0]["frames"] == 0
    assert all(len(e["model_episode_returns"]) == len(e["model_episode_members"]) > 0 for e in evals)
    from torchrl_offhrl.data import load_dataset
    from torchrl_offhrl.recipes.selection import data_return_cap, paired_gain_lcb

    cap = data_return_cap(load_dataset(hopper_file), 40)  # the default selection.return_cap=data; the tests' eval.max_steps=40
    assert guard["return_cap"] == pytest.approx(cap) and "clipped at the data's best episode" in guard["reason"]
    best = max((e for e in evals if e["frames"] > 0), key=lambda e: paired_gain_lcb(e, evals[0], cap=cap))
    assert guard["candidate_step"] == best["frames"]
    # the fallback (selection.fallback=bc_unless_start): the percentile BC, evaluated on the same model episodes as the start;
    # the trained policy is judged against the BC unless the start shows a gain over it
    fb = json.loads((run / "fallback.json").read_text())
    seed = json.loads((run / "config.json").read_text())["seed"]  # fitted from the run's seed (not the models' dataset seed)
    assert seed != 0 and (Path(summary["models"]) / f"percentile_bc_top0.1_seed{seed}.pt").is_file()
    assert fb["model_episode_members"] == evals[0]["model_episode_members"] and summary["fallback"]["normalized_d4rl"] == fb["normalized_d4rl"]
    start_over_bc = paired_gain_lcb(evals[0], fb, cap=cap)  # the default selection.fallback=bc_unless_start
    assert guard["start_over_bc_lcb"] == pytest.approx(start_over_bc) and guard["against"] == ("start" if start_over_bc > 0 else "bc")
    assert guard["gain_lcb"] == pytest.approx(min(paired_gain_lcb(best, evals[0], cap=cap), paired_gain_lcb(best, fb, cap=cap)))
    assert guard["fired"] == (not guard["gain_lcb"] > 0)
    assert guard["returned"] == ((guard["against"] if guard["fired"] else "trained"))
    saved = torch.load(run / "selected.pt", weights_only=True)
    if guard["returned"] == "bc":
        assert saved["policy"] == "percentile_bc" and summary["selected"]["policy"] == "percentile_bc"
        assert summary["selected"]["normalized_d4rl"] == fb["normalized_d4rl"]
    else:
        assert saved["step"] == (0 if guard["fired"] else best["frames"]) == summary["selected"]["frames"]
    # the run's evaluation model env rebuilt from its folder (recipes.evaluation.run_models, what the diagnostics use)
    # gives the start the model episodes its evaluation recorded
    from torchrl_offhrl.recipes.evaluation import load_run_agent, run_models
    from torchrl_offhrl.recipes.train import eval_seed
    from torchrl_offhrl.rollouts import evaluate_policy

    _, env_r, agent_r, state_r, cvae_r = load_run_agent(run)
    env_r.close()
    agent_r.load_state_dict(state_r["selection"]["start"]["agent"])
    menv = agent_r.attach(run_models(run).model_env(cvae_r))
    rets = evaluate_policy(menv, agent_r.eval_policy, len(evals[0]["model_episode_returns"]), max_steps=40, deterministic=True, seed=eval_seed(3))  # the run's seed
    assert rets.double().tolist() == pytest.approx(evals[0]["model_episode_returns"], abs=1e-3)
    # a returned percentile BC acts in real actions: `offhrl evaluate` rolls it out as it is
    from torchrl_offhrl.recipes.evaluation import evaluate_run
    from torchrl_offhrl.models import ClonedPolicy
    from torchrl_offhrl.recipes.fallback import fit_or_load_bc

    bc = fit_or_load_bc(to_plain(_cfg("ppo", hopper_file, tmp_path / "g")), load_dataset(hopper_file), None, 0.1, 0, progress=False)
    from torchrl_offhrl.utils import save_torch_file

    save_torch_file({"policy": "percentile_bc", "bc": ClonedPolicy(bc).state_dict(), "step": 0, "criterion": "last", "record": fb}, run / "selected.pt")
    res = evaluate_run(run, episodes=2)
    assert res["frames"] == 0 and len(res["returns"]) == 2
    with warnings.catch_warnings(record=True) as seen:  # without the start's evaluation there is nothing to guard against: it says so
        warnings.simplefilter("always")
        s2 = train(_cfg("ppo", hopper_file, tmp_path / "noguard", ["train.total_frames=128", *guarded]), progress=False)
    assert any("eval.at_start=false" in str(w.message) for w in seen) and s2["guard"]["fired"] is None


def test_policy_selection_without_a_model_env_returns_the_last_policy(hopper_file, cache, tmp_path):
    summary = train(_cfg("ppo", hopper_file, tmp_path, ["eval.model_env=false"]), progress=False)
    assert summary["selected"]["criterion"] == "last" and summary["selected"]["frames"] == summary["final"]["frames"]
    assert not (Path(summary["run_dir"]) / "selected.pt").is_file()  # the checkpoint is the returned policy


def test_policy_selector_resumes_and_refuses_another_criterion():
    from torchrl_offhrl.recipes.selection import PolicySelector

    class Agent:
        w = 0

        def state_dict(self):
            return {"w": self.w}

    a, sel = Agent(), PolicySelector("model_lcb")
    a.w = 1
    assert not sel.consider({"model_discounted_min_member": 5000.0}, a, step=0)  # the untrained agent is no candidate by default
    assert sel.consider({"model_discounted_min_member": 10.0}, a, step=100)
    a.w = 2
    assert not sel.consider({"model_discounted_min_member": 10.0}, a, step=200)  # a tie keeps the earlier policy
    again = PolicySelector("model_lcb")
    again.load_state_dict(sel.state_dict())
    a.w = 3
    assert again.consider({"model_discounted_min_member": 11.0}, a, step=300)
    assert again.selected["index"] == 3 and again.selected["agent"] == {"w": 3}
    with pytest.raises(ValueError, match="same selection.criterion"):
        PolicySelector("model_mean").load_state_dict(sel.state_dict())
    with pytest.raises(ValueError, match="selection.criterion must be one of"):
        PolicySelector("real_env")
    start = PolicySelector("model_lcb", include_start=True)
    assert start.consider({"model_discounted_min_member": 1.0}, a, step=0)


def test_sampled_evaluation_is_reported_beside_the_deterministic_one_and_changes_nothing(hopper_file, cache, tmp_path):
    """eval.sampled=true adds the sampled policy's return on the same start states to every record; the deterministic
    records, and so the training, are exactly those of the same run without it."""
    plain = train(_cfg("moc", hopper_file, tmp_path / "a", ["eval.at_start=true"]), progress=False)
    both = train(_cfg("moc", hopper_file, tmp_path / "b", ["eval.at_start=true", "eval.sampled=true"]), progress=False)
    ra = json.loads((Path(plain["run_dir"]) / "evals.json").read_text())
    rb = json.loads((Path(both["run_dir"]) / "evals.json").read_text())
    assert len(ra) == len(rb) == 3
    for a, b in zip(ra, rb):
        assert "return_mean_sampled" not in a
        assert {k: v for k, v in b.items() if not k.endswith("_sampled") and k != "wall_s"} == {k: v for k, v in a.items() if k != "wall_s"}
        assert b["normalized_d4rl_sampled"] == pytest.approx(100 * (b["return_mean_sampled"] + 20.272305) / (3234.3 + 20.272305))
        assert b["return_std_sampled"] >= 0
    # the sampled policy is another policy: on these runs its returns differ from the deterministic ones somewhere
    assert any(b["return_mean_sampled"] != b["return_mean"] for b in rb)


def test_bad_snapshot_frames_are_named_before_any_data_work(tmp_path):
    """train.snapshot_frames off the evaluation grid or past the budget: a ValueError before the dataset is even read
    (here it does not exist), and no run directory is left behind."""
    missing = tmp_path / "nowhere.hdf5"
    for snaps, match in (("[100]", r"each must be a multiple of eval.every_frames \(128\)"), ("[512]", r"past the budget train.total_frames=256")):
        with pytest.raises(ValueError, match=match):
            train(_cfg("moc", missing, tmp_path / "out", [f"train.snapshot_frames={snaps}"]), progress=False)
    assert not any((tmp_path / "out").glob("*/checkpoint.pt"))


def test_each_config_is_exactly_one_setting():
    from torchrl_offhrl.recipes.train import DatasetSetting, ModelEnvSetting, OnlineSetting, TransferSetting, setting_of

    def kind(*overrides):
        return type(setting_of(to_plain(compose("offline_train", list(overrides)))))

    assert kind("algo=moc") is ModelEnvSetting
    assert kind("algo=ppo", "ablation.no_cvae=true") is ModelEnvSetting
    assert kind("algo=uof", "env=blockstack2") is ModelEnvSetting  # block stacking: the same setting, its own evaluator
    assert kind("algo=iql") is DatasetSetting and kind("algo=bc") is DatasetSetting
    assert kind("algo=ppo", "train.online=true") is OnlineSetting
    assert kind("algo=moc", "transfer.task=backward") is TransferSetting
    assert kind("algo=ppo", "transfer.task=backward", "transfer.from_scratch=true") is TransferSetting
    # what no setting defines is refused, with what to do
    for bad, match in ((("algo=iql", "transfer.task=backward"), "leave transfer.task null"),
                       (("algo=ppo", "train.online=true", "transfer.task=backward"), "leave train.online false"),
                       (("algo=moc", "env=blockstack2"), "not goal-conditioned"),
                       (("algo=uof",), "block-stacking tasks only"),
                       (("algo=iql", "ablation.no_cvae=true"), "leave them false")):
        with pytest.raises(ValueError, match=match):
            kind(*bad)
    # the models are fitted only where the setting uses them
    cfg = to_plain(compose("offline_train", ["algo=ppo", "transfer.task=backward", "transfer.from_scratch=true"]))
    assert not TransferSetting.needs_models(cfg)
    cfg["transfer"]["decoder"] = "keep"
    assert TransferSetting.needs_models(cfg) and ModelEnvSetting.needs_models(cfg) and not DatasetSetting.needs_models(cfg)


def test_mopo_config_is_sac_on_penalised_short_rollouts(toy_data, fitted_gaussian_ensemble):
    from torchrl_offhrl.recipes.config import model_env_config
    from torchrl_offhrl.recipes.pipeline import make_model_env

    cfg = to_plain(compose("offline_train", ["algo=mopo", "model_env.reward_scale=1.0"]))
    assert cfg["algo"]["name"] == "mopo" and cfg["algo"]["label"] == "mopo" and cfg["ablation"] == {"no_cvae": True, "no_pessimism": True}
    assert cfg["algo"]["real_ratio"] == 0.05 and cfg["algo"]["utd_ratio"] == 1.0  # the SAC group's settings, inherited
    # MOPO's model: 7 Gaussian members, 5 elites; its penalty: the largest norm of their predicted std
    assert (cfg["ensemble"]["loss"], cfg["ensemble"]["num_models"], cfg["ensemble"]["num_elites"]) == ("nll", 7, 5)
    assert cfg["model_env"]["discrepancy"] == "aleatoric"
    settings, pess = model_env_config(cfg, "medium")
    env = make_model_env({"env": settings}, fitted_gaussian_ensemble, None, toy_data, batch_size=8, latent=False).base_env
    assert env.reward_penalty == 5.0 and env.horizon == 5 and env.threshold == float("inf") and env.penalty == 0.0
    td = env.rollout(5, break_when_any_done=False)
    assert not td["next", "penalized"].any() and td["next", "truncated"][:, -1].all()  # MOPO never ends an episode by disagreement


@pytest.mark.parametrize("env,dataset,horizon,penalty", [
    ("hopper", "medium", 5, 5.0), ("hopper", "medium-expert", 5, 1.0),          # MOPO's official d4rl configs
    ("halfcheetah", "medium", 1, 1.0), ("halfcheetah", "medium-expert", 5, 5.0),
    ("hopper", "random", 5, 5.0), ("halfcheetah", "/data/robot_logs.hdf5", 5, 5.0),  # no entry: the config's defaults
])
def test_mopo_takes_its_papers_rollout_length_and_penalty_per_dataset(env, dataset, horizon, penalty):
    from torchrl_offhrl.recipes.config import config_fingerprint

    cfg = to_plain(compose("offline_train", ["algo=mopo", f"env={env}", f"dataset={dataset}"]))
    assert (cfg["model_env"]["horizon"], cfg["model_env"]["reward_penalty"]) == (horizon, penalty)
    assert isinstance(cfg["model_env"]["horizon"], int) and isinstance(cfg["model_env"]["reward_penalty"], float)
    mine = to_plain(compose("offline_train", ["algo=mopo", f"env={env}", f"dataset={dataset}", "model_env.horizon=3",
                                              "model_env.reward_penalty=0.5"]))
    assert (mine["model_env"]["horizon"], mine["model_env"]["reward_penalty"]) == (3, 0.5)  # the command line wins
    # the table is not part of a run's identity, what the run took from it is: a run made before the table existed resumes
    before = {**cfg, "env": {k: v for k, v in cfg["env"].items() if k != "mopo"}}
    assert config_fingerprint(before) == config_fingerprint(cfg) != config_fingerprint(mine)


def test_on_record_sees_every_evaluation_after_its_checkpoint(hopper_file, cache, tmp_path):
    seen = []

    def on_record(rec):  # the record is already in the run's checkpoint when it is handed over (a stopped trial resumes from it)
        state = torch.load(Path(rec_dir[0]) / "checkpoint.pt", weights_only=True)
        seen.append((rec["frames"], state["frames"]))

    cfg = _cfg("ppo", hopper_file, tmp_path, ["eval.at_start=true"])
    from torchrl_offhrl.recipes.config import default_run_dir

    rec_dir = [default_run_dir(to_plain(cfg))]
    summary = train(cfg, progress=False, on_record=on_record)
    evals = json.loads((Path(summary["run_dir"]) / "evals.json").read_text())
    assert [f for f, _ in seen] == [e["frames"] for e in evals] == [0, 128, 256]
    assert all(f == ckpt for f, ckpt in seen)


def test_mopo_mixes_real_ratio_of_each_minibatch_from_the_scaled_dataset(toy_data, fitted_gaussian_ensemble):
    """MOPOAgent: of a 40-row minibatch, round(40 * 0.25) = 10 rows come from the dataset (marked here by a reward of 7,
    which the model env never gives), with the reward scale the env's rewards get (x 0.5 -> 3.5); the rest from the model
    rollouts' replay. An agent in latent actions is refused with the fix named; its hyper-parameters include SAC's."""
    from torchrl_offhrl.agents import agent_defaults, make_agent
    from torchrl_offhrl.recipes.config import model_env_config
    from torchrl_offhrl.recipes.pipeline import make_model_env

    cfg = to_plain(compose("offline_train", ["algo=mopo", "model_env.reward_scale=1.0"]))
    settings, _ = model_env_config(cfg, "medium")
    env = make_model_env({"env": settings}, fitted_gaussian_ensemble, None, toy_data, batch_size=8, latent=False)
    agent = make_agent("mopo", env, action_key="action", hidden_sizes=[16], batch_size=40, real_ratio=0.25, init_random_frames=0)
    assert {"real_ratio", "utd_ratio", "batch_size"} <= set(agent_defaults("mopo"))
    marked = toy_data[:].clone()
    marked.set(("next", "reward"), torch.full_like(marked.get(("next", "reward")), 7.0))
    agent.use_dataset(marked, reward_scale=0.5)
    with torch.no_grad():
        batch = env.rollout(10, agent.policy, break_when_any_done=False)
    agent.replay_buffer.extend(batch.reshape(-1))
    mb = agent.minibatch()
    assert mb.batch_size == torch.Size([40])
    assert int((mb["next", "reward"] == 3.5).sum()) == 10
    out = agent.update(batch)
    assert out["updates"] == batch.numel()
    with pytest.raises(ValueError, match="ablation.no_cvae=true"):
        make_agent("mopo", env, action_key="action", hidden_sizes=[16]).use_dataset(marked.exclude("action"))


def test_mopo_rolls_out_as_its_code_does_every_env_once_then_rollout_freq_steps(toy_data, fitted_gaussian_ensemble):
    """MOPO's schedule (algo.rollout_freq): each collected batch is one rollout of every env (6 envs x horizon 5 = 30 frames),
    followed by rollout_freq = 12 gradient steps; the replay keeps model_retain_rollouts = 2 rollouts (60 frames); SAC's
    schedule keys it sets are refused when given, and so are random first frames and a model env of another size."""
    from torchrl_offhrl.agents import make_agent
    from torchrl_offhrl.recipes.config import model_env_config
    from torchrl_offhrl.recipes.pipeline import make_model_env

    cfg = to_plain(compose("offline_train", ["algo=mopo", "model_env.reward_scale=1.0"]))
    assert (cfg["algo"]["rollout_batch_size"], cfg["algo"]["rollout_freq"], cfg["algo"]["model_retain_rollouts"]) == (50000, 1000, 5)
    assert cfg["train"]["total_frames"] == 205 * 50000 * 5 and cfg["eval"]["every_frames"] == 41 * 50000 * 5  # hopper-medium: h 5
    settings, _ = model_env_config(cfg, "medium")
    env = make_model_env({"env": {**settings, "horizon": 5}}, fitted_gaussian_ensemble, None, toy_data, batch_size=6, latent=False)
    assert (env.base_env.member_mode, env.base_env.sample) == ("step", True)  # MOPO's step: a random elite, sampled
    from torchrl_offhrl.recipes.pipeline import make_eval_model_env

    evaluation = make_eval_model_env({"env": settings}, fitted_gaussian_ensemble, None, toy_data, 4, 20, threshold=float("inf"), latent=False)
    assert (evaluation.base_env.member_mode, evaluation.base_env.sample) == ("episode", False)  # the guard's bound is per member
    kw = dict(action_key="action", hidden_sizes=[16], batch_size=8, real_ratio=0.25, init_random_frames=0)
    agent = make_agent("mopo", env, rollout_freq=12, model_retain_rollouts=2, rollout_batch_size=6, **kw)
    assert agent.frames_per_batch == 30 and agent.utd_ratio == pytest.approx(12 / 30) and agent.replay_buffer.storage.max_size == 60
    agent.use_dataset(toy_data[:], reward_scale=1.0)
    for _ in range(3):
        with torch.no_grad():
            batch = env.rollout(5, agent.policy, break_when_any_done=False)
        assert agent.update(batch)["updates"] == 12
    assert len(agent.replay_buffer) == 60  # three rollouts of 30 frames, the last two kept
    for bad, match in (({"utd_ratio": 2.0}, "algo.utd_ratio"), ({"buffer_size": 10}, "algo.buffer_size")):
        with pytest.raises(ValueError, match=match):
            make_agent("mopo", env, rollout_freq=12, **bad, **kw)
    with pytest.raises(ValueError, match="init_random_frames=0"):
        make_agent("mopo", env, rollout_freq=12, **{**kw, "init_random_frames": 5})
    with pytest.raises(ValueError, match="rollout_batch_size=7: the model env has 6 envs"):
        make_agent("mopo", env, rollout_freq=12, rollout_batch_size=7, **kw)


def test_mopo_trains_end_to_end_with_the_dataset_in_its_minibatches(hopper_file, cache, tmp_path):
    """algo=mopo through `train`: the model env's setting hands the agent the dataset (a quarter of each of its 32-row
    minibatches here), it trains, evaluates and writes its summary like any model-env run."""
    summary = train(_cfg("mopo", hopper_file, tmp_path), progress=False)
    run = Path(summary["run_dir"])
    assert run.name.startswith("mopo-hopper-hopper_random-") and run.name.endswith("-no_cvae-no_pessimism-seed0")
    assert summary["updates"] > 0 and summary["final"]["return_mean"] > 0
    # `offhrl evaluate` rebuilds the agent to act in the real env, whose envs are not MOPO's rollout batch: its schedule's
    # keys are left out (Agent.training_only_keys): the agent is rebuilt from the run's config, its last checkpoint
    # loads (the run's frames), and it acts in the real env (was: ValueError before any episode)
    from torchrl_offhrl.recipes.evaluation import evaluate_run, load_run_agent

    cfg = json.loads((run / "config.json").read_text())
    assert cfg["algo"]["rollout_batch_size"] != 3 and cfg["algo"]["rollout_freq"] is not None
    _, env, agent, state, _ = load_run_agent(run, num_envs=3, policy="last")
    env.close()
    assert type(agent).__name__ == "MOPOAgent" and state["frames"] == summary["frames"]
    again = evaluate_run(run, episodes=2, policy="last")
    assert math.isfinite(again["return_mean"])


@pytest.mark.fault("resume")
@pytest.mark.parametrize("algo", ["moc", "ppo", "sac"])
def test_a_killed_and_resumed_run_gives_the_records_of_an_uninterrupted_one(algo, hopper_file, cache, tmp_path, monkeypatch):
    """Interrupted after its checkpoint at 128 frames and resumed, a run's later evaluations equal, bit for bit, those of the
    same run made in one go: the checkpoint keeps the model envs where they stood (the collector's carrier, the env's RNG)
    and the RNG is set again right before the first batch (recipes.loop.source_state / restore_source). The dataset
    agents' counterpart: test_offline_agents.py::test_an_interrupted_dataset_run_resumes_to_the_same_agent."""
    straight = train(_cfg(algo, hopper_file, tmp_path / "a"), progress=False)
    cfg = _cfg(algo, hopper_file, tmp_path / "b")
    _interrupt_at_update(cfg, 4, monkeypatch)  # the fourth batch of 64 frames: after the checkpoint at 128
    resumed = train(cfg, progress=False)
    a = json.loads((Path(straight["run_dir"]) / "evals.json").read_text())
    b = json.loads((Path(resumed["run_dir"]) / "evals.json").read_text())
    assert [e["frames"] for e in a] == [e["frames"] for e in b] == [128, 256]
    for x, y in zip(a, b):
        assert {k: v for k, v in x.items() if k != "wall_s"} == {k: v for k, v in y.items() if k != "wall_s"}


@pytest.mark.fault("data")
def test_a_percentile_bc_that_fails_leaves_the_start_as_the_guards_fallback(hopper_file, cache, tmp_path, monkeypatch):
    """The BC is fitted and evaluated at the run's end: if that fails, the run still finishes, guarded against the start alone,
    and says why (the trained policies and their evaluations are never lost to it)."""
    def broken(p, evaluator, threshold):
        def run():
            raise RuntimeError("no complete episode among the best ones")
        return run

    monkeypatch.setattr(recipe_mod, "_fallback", broken)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        summary = train(_cfg("ppo", hopper_file, tmp_path, ["eval.at_start=true", "train.total_frames=128"]), progress=False)
    run = Path(summary["run_dir"])
    assert any("percentile BC could not be fitted" in str(w.message) for w in seen)
    assert summary["guard"]["against"] == "start" and "percentile BC could not be fitted" in summary["guard"]["reason"]
    assert "fallback" not in summary and not (run / "fallback.json").exists()
    assert summary["guard"]["returned"] in ("start", "trained") and (run / "checkpoint.pt").is_file()


def test_the_percentile_bc_is_fitted_and_cached_once_per_run_seed(hopper_file, cache, tmp_path):
    """Runs of different seeds return independently fitted cloners (a table's seeds must not score one network several
    times: the models' config carries the dataset's seed, the same for every run, so the run's seed is what counts); a run
    of the same seed loads its own cloner back unchanged."""
    from torchrl_offhrl.data import load_dataset
    from torchrl_offhrl.recipes.fallback import bc_path, fit_or_load_bc

    data = load_dataset(hopper_file)
    pcfg = model_config(_cfg("ppo", hopper_file, tmp_path / "runs"))
    nets = {seed: fit_or_load_bc(pcfg, data, tmp_path, 0.1, seed, progress=False) for seed in (1, 2)}
    assert sorted(p.name for p in tmp_path.glob("percentile_bc_*.pt")) == ["percentile_bc_top0.1_seed1.pt", "percentile_bc_top0.1_seed2.pt"]
    w1, w2 = (torch.cat([p.detach().flatten() for p in nets[s].parameters()]) for s in (1, 2))
    assert not torch.equal(w1, w2)
    again = fit_or_load_bc(pcfg, data, tmp_path, 0.1, 2, progress=False)
    assert torch.equal(torch.cat([p.detach().flatten() for p in again.parameters()]), w2)


def test_building_a_setting_leaves_the_config_and_its_parts_as_given(hopper_file, cache, tmp_path):
    """The setting resolves the P-MDP's settings into new parts (Parts.with_model_env) and its own config: the caller's
    config gains no key, and the run's config.json holds what was resolved."""
    import copy
    import time

    from torchrl_offhrl.recipes.train import build_setting

    cfg = to_plain(_cfg("ppo", hopper_file, tmp_path))
    given = copy.deepcopy(cfg)
    s = build_setting(cfg, tmp_path, time.time(), progress=False)
    try:
        assert cfg == given
        resolved = s.cfg["resolved_model_env"]
        assert set(resolved) == {"horizon", "reset_states", "latent_bound"} and s.parts.cfg is s.cfg
        assert s.parts.pcfg["env"]["horizon"] == resolved["horizon"] and s.rules is s.parts.rules and s.rules is not None
        assert {k: v for k, v in s.cfg.items() if k != "resolved_model_env"} == given
    finally:
        s.close()
