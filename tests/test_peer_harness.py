"""The harness that runs OfflineRL-Kit's MOPO on our data (experiments/peers/offlinerlkit_mopo.py): the parts that do
not need the kit, which is not shipped (the side-by-side itself is an experiment, not a test)."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from experiments.peers.offlinerlkit_mopo import OldApiEnv, final_evaluation, main, stand_in_modules, transitions  # noqa: E402


def test_the_old_api_env_steps_as_pre_gymnasium_gym_and_normalises_on_the_data_references():
    env = OldApiEnv("Pendulum-v1", ref=(-100.0, 300.0))
    env.seed(3)
    first = env.reset()
    env.seed(3)
    assert np.array_equal(env.reset(), first)  # seed() applies to the next reset
    obs, reward, done, info = env.step(env.action_space.sample() * 0)
    assert obs.shape == first.shape and isinstance(done, bool) and isinstance(info, dict)
    assert env.get_normalized_score(100.0) == pytest.approx(0.5)
    dones = [env.step(np.zeros(1, dtype=np.float32))[2] for _ in range(199)]
    assert dones[-1] and not any(dones[:-1])  # Pendulum's time limit (200 steps) ends the episode: done


def test_our_transitions_become_the_kits_arrays_with_true_terminations_only(hopper_file):
    from torchrl_offhrl.data import load_dataset

    data = load_dataset(hopper_file)
    d = transitions(data)
    n = len(data)
    assert {k: v.shape[0] for k, v in d.items()} == dict.fromkeys(("observations", "actions", "next_observations", "rewards", "terminals"), n)
    assert d["rewards"].ndim == 1 and d["terminals"].dtype == np.float32
    assert np.array_equal(d["terminals"], data.data["next", "terminated"].reshape(-1).numpy().astype(np.float32))
    assert np.array_equal(d["next_observations"], data.data["next", "observation"].numpy())


def test_the_stand_in_modules_give_the_names_the_kit_reads(monkeypatch):
    import types

    for name in ("gym", "gym.envs", "gym.envs.mujoco", "d4rl"):  # whatever is there comes back after the test, and no stand-in stays
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    stand_in_modules(lambda task, **kw: ("made", task))
    import gym
    from gym.envs.mujoco import mujoco_env

    assert gym.make("hopper-medium-v2") == ("made", "hopper-medium-v2") and mujoco_env.MujocoEnv is object
    assert gym.spaces.Space is object and gym.Env is object and "d4rl" in sys.modules


def test_a_folder_that_is_not_the_kit_is_refused_with_what_to_do(tmp_path, hopper_file):
    with pytest.raises(SystemExit, match="is not a checkout of OfflineRL-Kit .* fetch https://github.com/yihaosun1124/OfflineRL-Kit"):
        main(["--kit", str(tmp_path), "--dataset", str(hopper_file), "--task", "hopper-random-v2", "--out", str(tmp_path / "o")])


def test_our_evaluation_of_the_kits_policy_replays_seeded_episodes_and_normalises_their_mean():
    import gymnasium

    class ZeroPolicy:  # the kit's policy interface: eval(), select_action(obs [1, d], deterministic) -> [1, a]
        def eval(self):
            self.evaluated = True

        def select_action(self, obs, deterministic=False):
            assert obs.shape == (1, 3) and deterministic
            return np.zeros((1, 1), dtype=np.float32)

    policy = ZeroPolicy()
    out = final_evaluation(policy, "Pendulum-v1", ref=(-2000.0, 0.0), seed=4, episodes=2)
    assert policy.evaluated and out["lengths"] == [200, 200]
    expected = []
    for i in range(2):  # the same episodes by hand: reset with eval_seed(4) + i = 4007 + i, zero torque
        env = gymnasium.make("Pendulum-v1")
        env.reset(seed=4007 + i)
        expected.append(sum(float(env.step(np.zeros(1, dtype=np.float32))[1]) for _ in range(200)))
    assert out["returns"] == pytest.approx(expected)
    assert expected[0] != pytest.approx(expected[1])  # two different start states
    assert out["normalized_mean"] == pytest.approx(100 * (np.mean(expected) + 2000.0) / 2000.0)


def test_the_mopo_side_by_side_reads_both_sides_runs_and_compares_them_at_the_same_points(tmp_path):
    """Hand-made run folders: ours (summary + evaluations) and the kit's (our final evaluation + its progress CSV)."""
    import json

    from experiments.peers.mopo_side_by_side import kit_runs, main, our_runs
    from torchrl_offhrl.stats import iqm

    ours, kit = tmp_path / "ours", tmp_path / "kit"
    for seed, (last, ret, evals) in {4: (30.0, 40.0, [10.0, 50.0, 30.0]), 5: (20.0, 20.0, [25.0, 20.0])}.items():
        d = ours / f"mopo-hopper-medium-seed{seed}"
        d.mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps({"seed": seed, "final": {"normalized_d4rl": last, "updates": 204800},
                                                    "selected": {"normalized_d4rl": ret}, "behaviour_normalized_d4rl": 35.9}))
        (d / "evals.json").write_text(json.dumps([{"step": 0, "normalized_d4rl": 99.0}]  # the untrained start: not "best"
                                                 + [{"step": 10_250_000 * (i + 1), "updates": 41_000 * (i + 1), "normalized_d4rl": v}
                                                    for i, v in enumerate(evals)]))
    (ours / "mopo-hopper-medium-seed6").mkdir()  # unfinished: no summary, left out
    for seed, final in {4: 12.0, 6: 18.0}.items():
        d = kit / "hopper-medium" / f"seed{seed}"
        rec = d / "log" / "hopper-medium-v2" / "mopo&x" / f"seed_{seed}&t" / "record"
        rec.mkdir(parents=True)
        (d / "final_eval.json").write_text(json.dumps({"seed": seed, "normalized_mean": final, "episodes": 30}))
        # its own evaluations every epoch of 1024 updates: epochs 40 and 80 are the nearest to our points (41,000 and 82,000
        # updates; the third point's, 123,000, is epoch 80 too), epochs 1 and 79 are not
        rows = [(1024, 70.0), (40960, 15.0 + seed), (79 * 1024, 90.0), (81920, 5.0)]
        (rec / "policy_training_progress.csv").write_text("eval/normalized_episode_reward,timestep\n"
                                                           + "".join(f"{v},{t}\n" for t, v in rows))
    (kit / "hopper-medium" / "seed5").mkdir()  # unfinished: no final evaluation, left out
    o = our_runs(ours, "hopper-medium")
    k = kit_runs(kit, "hopper-medium", sorted({p for r in o.values() for p in r["points"]}))
    assert sorted(o) == [4, 5] and o[4] == {"last": 30.0, "returned": 40.0, "best": 50.0, "data": 35.9, "updates": 204800,
                                            "points": [41_000, 82_000, 123_000]}
    assert kit_runs(kit, "hopper-medium")[4]["own_best"] is None  # no points of ours: no "best" at them
    assert sorted(k) == [4, 6] and k[4] == {"last": 12.0, "own_last": 5.0, "own_best": 19.0, "updates": 81920, "episodes": 30}
    assert k[6]["own_best"] == 21.0  # the best at our points only (90 at epoch 79 and 70 at epoch 1 are not)
    out = tmp_path / "page.md"
    assert main(["--ours", str(ours), "--kit", str(kit), "--datasets", "hopper-medium", "--out", str(out)]) == 0
    table = json.loads(out.with_suffix(".json").read_text())
    row = next(r for r in table if r["who"] == "OfflineRL-Kit" and r["key"] == "last")
    assert row["seeds"] == [4, 6] and row["values"] == [12.0, 18.0] and row["iqm_ci"][0] == iqm([12.0, 18.0])
    assert "| ours | last policy, 30 episodes | 4 5 | 25.0 [" in out.read_text() and "the data: 35.9" in out.read_text()


def test_the_kit_runs_on_our_data_and_schedule_fit_once_resume_by_seed_and_are_archived(tmp_path, monkeypatch):
    """``mopo_side_by_side.py run --who kit``: the kit's arguments are our config's (hand-checked against configs/algo/mopo.yaml
    and the env tables: hopper-medium h 5 lambda 5, halfcheetah-medium h 1 lambda 1, 205 rollouts of 50,000 states, one per
    1,000 updates), the first seed fits the dynamics and the others load them, a finished seed is skipped, an unfinished
    one starts again, and each finished run's page files are archived."""
    import json

    from experiments.peers import mopo_side_by_side as sbs

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))  # the data file below is made there, not in a real cache
    hop, hc = sbs.kit_settings("hopper-medium"), sbs.kit_settings("halfcheetah-medium")
    assert hop["file"].is_relative_to(tmp_path / "cache")
    arg = lambda s, name: s["args"][s["args"].index(name) + 1]  # noqa: E731
    assert (arg(hop, "--rollout-length"), arg(hop, "--penalty-coef")) == ("5", "5.0")
    assert (arg(hc, "--rollout-length"), arg(hc, "--penalty-coef")) == ("1", "1.0")
    for s in (hop, hc):
        assert (arg(s, "--epoch"), arg(s, "--step-per-epoch"), arg(s, "--rollout-freq")) == ("205", "1000", "1000")
        assert (arg(s, "--rollout-batch-size"), arg(s, "--real-ratio"), arg(s, "--model-retain-epochs")) == ("50000", "0.05", "5")
    assert hop["file"].name.startswith("hopper-medium-100000-seed0") and hop["task"] == "hopper-medium-v2"

    checkout = tmp_path / "kit"
    (checkout / "run_example").mkdir(parents=True)
    (checkout / "run_example" / "run_mopo.py").write_text("")
    hop["file"].parent.mkdir(parents=True, exist_ok=True)
    hop["file"].touch()  # the data exist: nothing is generated
    root, archive = tmp_path / "runs", tmp_path / "archive"
    (root / "hopper-medium" / "seed5" / "log").mkdir(parents=True)  # seed 5: an unfinished run, started again from nothing
    (root / "hopper-medium" / "seed5" / "log" / "stale.txt").write_text("x")
    done = root / "hopper-medium" / "seed6"
    done.mkdir(parents=True)
    (done / "final_eval.json").write_text("{}")  # seed 6: finished, skipped
    calls = []

    def fake_kit(cmd, check):  # what offlinerlkit_mopo.py leaves: its logs (the fitted dynamics on a fitting run) and our evaluation
        out, seed = Path(cmd[cmd.index("--out") + 1]), int(cmd[cmd.index("--seed") + 1])
        calls.append((seed, cmd[cmd.index("--load-dynamics-path") + 1] if "--load-dynamics-path" in cmd else None, sorted(p.name for p in out.rglob("*"))))
        run = out / "log" / "hopper-medium-v2" / "mopo&x" / f"seed_{seed}&t"
        (run / "record").mkdir(parents=True)
        (run / "record" / "policy_training_progress.csv").write_text("eval/normalized_episode_reward,timestep\n1.0,1000\n")
        if "--load-dynamics-path" not in cmd:
            (run / "model").mkdir()
            (run / "model" / "dynamics.pth").write_text("weights")
        (out / "final_eval.json").write_text(json.dumps({"seed": seed}))

    monkeypatch.setattr(sbs.subprocess, "run", fake_kit)
    sbs.run(checkout, ["hopper-medium"], [4, 5, 6], "kit", root, archive)
    fitted = root / "hopper-medium" / "seed4" / "log" / "hopper-medium-v2" / "mopo&x" / "seed_4&t" / "model"
    assert calls == [(4, None, []), (5, str(fitted), [])]  # seed 5's stale folder was removed first; seed 6 not run
    for seed in (4, 5):
        kept = archive / "hopper-medium" / f"seed{seed}"
        assert json.loads((kept / "final_eval.json").read_text()) == {"seed": seed}
        assert len(list(kept.glob("log/*/*/*/record/policy_training_progress.csv"))) == 1
        assert not list(kept.rglob("dynamics.pth"))  # the page's files only
    assert (archive / "hopper-medium" / "seed6" / "final_eval.json").is_file()  # a run finished before is archived too
    # a run killed after its fit (the kit saves the dynamics before training the policy) is started again on that fit
    for f in (root / "hopper-medium" / "seed4" / "final_eval.json", root / "hopper-medium" / "seed5" / "final_eval.json"):
        f.unlink()
    calls.clear()
    sbs.run(checkout, ["hopper-medium"], [4, 5], "kit", root, archive)
    kept = root / "hopper-medium" / "dynamics"
    assert calls == [(4, str(kept), []), (5, str(kept), [])] and (kept / "dynamics.pth").read_text() == "weights"
    with pytest.raises(SystemExit, match="not a checkout of OfflineRL-Kit"):
        sbs.run(tmp_path / "nowhere", ["hopper-medium"], [4], "kit", root, archive)


def test_the_kits_fit_is_archived_once_and_a_fresh_machine_loads_it_instead_of_fitting_again(tmp_path, monkeypatch):
    """The first seed's fit (``dynamics.pth``, ``mu.npy``, ``std.npy``) is kept in the archive with SHA-256s; on a machine
    with no runs (an empty ``kit_root``) the next seed loads that fit, copied beside the runs; a damaged archived file
    stops the run with what to do, instead of a different fit."""
    import json

    from experiments.peers import mopo_side_by_side as sbs

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    hop = sbs.kit_settings("hopper-medium")
    hop["file"].parent.mkdir(parents=True, exist_ok=True)
    hop["file"].touch()
    checkout = tmp_path / "kit"
    (checkout / "run_example").mkdir(parents=True)
    (checkout / "run_example" / "run_mopo.py").write_text("")
    calls = []

    def fake_kit(cmd, check):
        out, seed = Path(cmd[cmd.index("--out") + 1]), int(cmd[cmd.index("--seed") + 1])
        calls.append((seed, cmd[cmd.index("--load-dynamics-path") + 1] if "--load-dynamics-path" in cmd else None))
        if "--load-dynamics-path" not in cmd:
            model = out / "log" / "hopper-medium-v2" / "mopo&x" / f"seed_{seed}&t" / "model"
            model.mkdir(parents=True)
            for f, text in (("dynamics.pth", "weights"), ("mu.npy", "mu"), ("std.npy", "std")):
                (model / f).write_text(text)
        out.mkdir(parents=True, exist_ok=True)
        (out / "final_eval.json").write_text(json.dumps({"seed": seed}))

    monkeypatch.setattr(sbs.subprocess, "run", fake_kit)
    archive = tmp_path / "archive"
    sbs.run(checkout, ["hopper-medium"], [4], "kit", tmp_path / "machine1", archive)
    kept = archive / "hopper-medium" / "dynamics"
    assert calls == [(4, None)]
    assert {p.name for p in kept.iterdir()} == {"dynamics.pth", "mu.npy", "std.npy", "dynamics.pth.sha256", "mu.npy.sha256",
                                                 "std.npy.sha256"}
    calls.clear()
    fresh = tmp_path / "machine2"  # nothing of machine 1's runs
    sbs.run(checkout, ["hopper-medium"], [5], "kit", fresh, archive)
    assert calls == [(5, str(fresh / "hopper-medium" / "dynamics"))]
    assert (fresh / "hopper-medium" / "dynamics" / "dynamics.pth").read_text() == "weights"
    (kept / "mu.npy").write_text("damaged")
    with pytest.raises(SystemExit, match="damaged or incomplete \\(mu.npy\\)"):
        sbs.run(checkout, ["hopper-medium"], [6], "kit", tmp_path / "machine3", archive)


def test_our_side_runs_only_the_seeds_not_yet_archived(tmp_path, monkeypatch):
    """``run --who ours``: a seed archived by ``table1 run`` (its run folder may be gone with an earlier machine) is not run
    again; the others go to ``offhrl results table1 run --scale demo --algos mopo``, one seed per call (resumable)."""
    from experiments.peers import mopo_side_by_side as sbs

    monkeypatch.setattr(sbs, "OURS_ARCHIVE", tmp_path / "runs")
    (tmp_path / "runs" / "mopo-hopper-medium-seed4").mkdir(parents=True)
    (tmp_path / "runs" / "mopo-hopper-medium-seed4" / "summary.json").write_text("{}")
    calls = []
    monkeypatch.setattr(sbs.subprocess, "run", lambda cmd, check, cwd: calls.append((cmd[cmd.index("-m") + 1:], cwd)))
    sbs.run(tmp_path / "no-kit-needed", ["hopper-medium"], [4, 5], "ours", tmp_path / "kit")
    assert calls == [(["experiments.results", "table1", "run", "--scale", "demo", "--envs", "hopper", "--datasets", "medium",
                       "--algos", "mopo", "--seeds", "5"], sbs.ROOT)]  # from the checkout's root, wherever it is called from


def test_the_side_by_side_page_shows_the_model_comparison_kept_beside_the_kits_runs(tmp_path):
    """``<kit archive>/<dataset>/models.json`` (``mopo_models.py --out``) becomes the dataset's model section: one row per
    model and set, falls as 'share of count', and the closed-loop lengths per policy; without it the page has none."""
    import json

    from experiments.peers.mopo_side_by_side import model_results, page, rows

    r = {"transitions": 10, "error_mean": 0.5, "error_q90": 1.0, "penalty_mean": 0.25, "penalty_q90": 0.5, "spearman": 0.8,
         "error_above_penalty": 0.4, "reward_bias": 0.1, "reward_abs_error": 0.2, "reward_mean": 1.0, "real_falls": 4,
         "falls_predicted": 0.75, "false_falls": 0.0}
    result = {"env_id": "Hopper-v5", "sets": {"behaviour": "fresh", "policy run-a": "a run"},
              "models": {"ours": {"behaviour": r, "policy run-a": r, "closed_loop": {"policy run-a": {"lengths": [3, 5, 9], "returns": [1.0, 2.0, 3.0]}}}},
              "real_episodes": {"policy run-a": {"lengths": [2, 4, 6], "returns": [1.0, 1.5, 2.0]}},
              "critic": {"policy run-a": {"q_start": 200.0, "real_discounted_return_start": 14.0, "q_before_fall": 250.0, "reward_at_fall": 0.5,
                                          "q_dataset_states": 260.0}}}
    (tmp_path / "kit" / "hopper-medium").mkdir(parents=True)
    table = rows(tmp_path / "ours", tmp_path / "kit", ["hopper-medium"])
    assert "the models on real transitions" not in page(table, model_results(tmp_path / "kit", ["hopper-medium"]))
    (tmp_path / "kit" / "hopper-medium" / "models.json").write_text(json.dumps(result))
    text = page(table, model_results(tmp_path / "kit", ["hopper-medium"]))
    assert "### hopper-medium: the models on real transitions neither saw" in text
    assert "| ours | policy run-a | 10 | 0.500, 1.000 | 0.250, 0.500 | 0.80 | 0.40 | 1.00, +0.100, 0.200 | 0.75 of 4 | 0.000 |" in text
    assert "| policy run-a | 4 [2, 6], 1.5 | 5 [3, 9], 2.0 |" in text
    assert "| policy run-a | 200.0 | 14.0 | 250.0 | 0.50 | 260.0 |" in text


def test_the_critic_row_says_so_where_no_real_episode_fell():
    """HalfCheetah never terminates: with no first episode ended by termination there is no 'one step before the fall',
    and the row says so instead of printing the time limit's last step as a fall."""
    from experiments.peers.mopo_models import markdown_tables

    result = {"sets": {}, "models": {}, "critic": {"policy run-b": {"q_start": 90.0, "real_discounted_return_start": 300.0, "falls": 0,
                                                                   "q_before_fall": None, "reward_at_fall": None, "q_dataset_states": 95.0}}}
    assert "| policy run-b | 90.0 | 300.0 | n/a (no real fall) | n/a | 95.0 |" in markdown_tables(result)


def test_a_model_measured_on_fewer_sets_says_not_measured_instead_of_failing():
    """The kit's model added to a result after the runs' folders were gone (the behaviour set only): its rows for the other
    sets and its closed-loop cells read "not measured"; the other model's rows are unchanged."""
    from experiments.peers.mopo_models import markdown_tables

    r = {"transitions": 10, "error_mean": 0.5, "error_q90": 1.0, "penalty_mean": 0.25, "penalty_q90": 0.5, "spearman": 0.8,
         "error_above_penalty": 0.4, "reward_bias": 0.1, "reward_abs_error": 0.2, "reward_mean": 1.0}
    result = {"sets": {"behaviour": "fresh", "policy run-a": "a run"},
              "models": {"ours": {"behaviour": r, "policy run-a": r, "closed_loop": {"policy run-a": {"lengths": [3, 5, 9], "returns": [1.0, 2.0, 3.0]}}},
                         "kit": {"behaviour": r}},
              "real_episodes": {"policy run-a": {"lengths": [2, 4, 6], "returns": [1.0, 1.5, 2.0]}}}
    lines = markdown_tables(result)
    assert "| kit | policy run-a | not measured | | | | | | | |" in lines
    assert "| kit | behaviour | 10 | 0.500, 1.000 | 0.250, 0.500 | 0.80 | 0.40 | 1.00, +0.100, 0.200 | n/a | n/a |" in lines
    assert "| policy run-a | 4 [2, 6], 1.5 | 5 [3, 9], 2.0 | not measured |" in lines
