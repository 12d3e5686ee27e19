"""offhrl tune / offhrl sweep on Ray Tune: the paper's search space, a tiny search and sweep on local Ray, resuming an interrupted sweep."""
from __future__ import annotations

import fcntl
import json
import os
import shlex
from pathlib import Path

import pytest

from torchrl_offhrl.recipes.tune import load_search, search_grid


def test_models_preset_is_the_papers_search_space():
    spec = load_search("models")
    assert spec["kind"] == "models" and spec["num_samples"] == 10
    grid = spec["grid"]
    assert sorted(grid["ensemble.fit.lr"]) == sorted([1e-3, 1e-4, 1e-5, 2e-4, 5e-4])
    assert [w[0] for w in grid["ensemble.hidden_sizes"]] == [128, 256, 512, 1024]
    assert [w[0] for w in grid["ensemble.reward_hidden_sizes"]] == [128, 256, 512, 1024]
    assert [w[0] for w in grid["cvae.hidden_sizes"]] == [256, 512, 720, 1024]
    assert spec["tie"] == {"cvae.fit.lr": "ensemble.fit.lr"}
    trials = search_grid(spec)
    # 10 distinct combinations of the 5 x 4 x 4 x 4 = 320, the same for the same sample_seed, one learning rate per trial
    assert len(trials) == 10 and len({json.dumps(t, sort_keys=True) for t in trials}) == 10
    assert trials == search_grid(spec)
    assert all(t["cvae.fit.lr"] == t["ensemble.fit.lr"] for t in trials)
    assert len(search_grid({**spec, "num_samples": None})) == 320


def test_every_preset_composes_and_bad_descriptions_are_named(tmp_path):
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.tune import _override

    for name in ("models", "pessimism", "moc"):
        spec = load_search(name)
        for point in search_grid(spec)[:2]:  # every trial's overrides are valid hydra overrides of the config
            cfg = compose("offline_train", [*spec["overrides"], *(_override(k, v) for k, v in point.items())])
            assert cfg is not None
    with pytest.raises(FileNotFoundError, match="moc, models, pessimism"):
        load_search("nonexistent")
    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: nope\ngrid: {a: []}\ntie: {b: c}\n")
    with pytest.raises(ValueError, match="kind must be one of.*grid must map.*tie b"):
        load_search(str(bad))


def test_missing_ray_points_at_the_extra(monkeypatch):
    import builtins

    from torchrl_offhrl.cli import main

    real = builtins.__import__

    def no_ray(name, *args, **kwargs):
        if name == "ray" or name.startswith("ray."):
            raise ImportError("No module named 'ray'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    assert main(["tune", "models"]) == 2  # one line naming the extra, no traceback


# ------------------------------------------------------------------------------------------ on local Ray
@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 1024 * 1024, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def hopper_file(tmp_path_factory):
    from torchrl_offhrl.data import collect_dataset, save_dataset

    path = tmp_path_factory.mktemp("data") / "hopper_tiny.hdf5"
    save_dataset(collect_dataset("Hopper-v5", 600, num_envs=2, seed=0, progress=False), path)
    return path


def test_tiny_model_search_scores_trials_and_picks_each_model_by_its_loss(ray_session, hopper_file, tmp_path, monkeypatch):
    from torchrl_offhrl.recipes.tune import tune_search

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))  # the workers inherit the driver's environment
    spec = tmp_path / "tiny.yaml"
    spec.write_text("kind: models\nnum_samples: 2\ngrid:\n  ensemble.hidden_sizes: [[8, 8], [16]]\n  cvae.hidden_sizes: [[8], [16]]\n"
                    "overrides: [ensemble.num_models=2, ensemble.fit.max_steps=10, cvae.fit.max_steps=10]\n")
    # the user's ensemble.fit.max_steps=12 overrides the preset's 10 in every trial, and must in the printed command too
    best = tune_search(str(spec), [f"dataset={hopper_file}", "ensemble.fit.max_steps=12"], out_root=str(tmp_path / "out"), verbose=0)
    out = Path(best["out"])
    rows = (out / "results.csv").read_text().splitlines()
    assert len(rows) == 3 and "ensemble_val_loss" in rows[0]
    saved = json.loads((out / "best.json").read_text())
    assert saved["ensemble_val_loss"] <= 10 and saved["cvae_val_loss"] <= 10
    assert saved["command"].startswith("offhrl fit ") and f"dataset={hopper_file}" in saved["command"] and "++ensemble.hidden_sizes=" in saved["command"]
    # the winners are in the model cache: the printed command, split as a shell splits it, loads them
    from torchrl_offhrl.recipes.config import compose, model_config, resolve_dataset
    from torchrl_offhrl.recipes.pipeline import fit_or_load_models

    words = shlex.split(saved["command"])
    assert words[:2] == ["offhrl", "fit"] and set(saved["overrides"]) <= set(words)  # one shell word per override ([8,8], no space)
    cfg = compose("offline_train", words[2:])
    assert cfg.ensemble.fit.max_steps == 12
    _, _, info = fit_or_load_models(model_config(cfg), resolve_dataset(cfg), progress=False)
    assert info["ensemble"].startswith("loaded") and info["cvae"].startswith("loaded")


def test_tiny_sweep_resumes_an_interrupted_sweep_without_redoing_finished_trials(ray_session, hopper_file, tmp_path, monkeypatch):
    from torchrl_offhrl.recipes.tune import sweep

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    over = ["train.total_updates=20", "eval.every_updates=20", "eval.episodes=2", "eval.max_steps=20",
            "algo.batch_size=16", "algo.hidden_sizes=[8]"]  # the dataset is the sweep's --datasets axis
    root = tmp_path / "out" / "sweeps" / "s"
    seed5 = root / "bc-hopper-hopper_tiny-seed5"
    seed5.mkdir(parents=True)
    fd = os.open(seed5 / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # seed 5's run directory is busy: its trial fails, as if interrupted
    first = sweep(["bc"], ["hopper"], [str(hopper_file)], [4, 5], over, name="s", out_root=str(tmp_path / "out"), verbose=0)
    os.close(fd)
    errors = {r["seed"]: r["error"] for r in first["rows"]}
    assert errors[4] is None and errors[5] is not None
    done4 = root / "bc-hopper-hopper_tiny-seed4" / "checkpoint.pt"
    stamp = done4.stat().st_mtime_ns
    second = sweep(["bc"], ["hopper"], [str(hopper_file)], [4, 5], over, name="s", out_root=str(tmp_path / "out"), verbose=0)
    rows = {r["seed"]: r for r in second["rows"]}
    assert rows[5]["error"] is None and (seed5 / "summary.json").is_file()
    assert done4.stat().st_mtime_ns == stamp  # the finished trial was not run again
    assert (root / "results.md").is_file()
    # a larger sweep under the same name is a new experiment: its trials report finished run directories without training them
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.recipes.tune import finished_run

    cfg = compose("offline_train", ["algo=bc", "env=hopper", *over])
    assert finished_run(root / "bc-hopper-hopper_tiny-seed4", cfg)["step"] == 20
    assert finished_run(root / "bc-hopper-hopper_tiny-seed4", compose("offline_train", ["algo=bc", *over, "train.total_updates=40"])) is None
    assert finished_run(root / "bc-hopper-hopper_tiny-seed6", cfg) is None


def test_the_number_of_trials_is_an_option_and_a_search_key_override_says_so(tmp_path):
    """`offhrl tune PRESET --num-samples N` sets how many grid points are drawn; `num_samples=2` as an override is refused with that hint."""
    from torchrl_offhrl.cli import build_parser, overrides_last
    from torchrl_offhrl.recipes.tune import tune_search

    args = build_parser().parse_args(overrides_last(["tune", "models", "env=hopper", "--num-samples", "3"]))
    assert args.num_samples == 3 and args.overrides == ["env=hopper"]
    with pytest.raises(ValueError, match=r"--num-samples N"):
        tune_search("models", ["num_samples=2"], out_root=str(tmp_path))
    with pytest.raises(ValueError, match=r"--num-samples must be >= 1"):
        tune_search("models", [], num_samples=0, out_root=str(tmp_path))


def test_a_sweep_axis_given_as_an_override_is_refused(tmp_path):
    """`offhrl sweep ... dataset=FILE` used to train on the file under the label and run directory of the default
    --datasets medium (`bc-hopper-medium-seed4`); an axis of the sweep is refused as an override, naming its option."""
    from torchrl_offhrl.recipes.tune import sweep

    with pytest.raises(ValueError, match=r"dataset is an axis of the sweep; give it as --datasets"):
        sweep(["bc"], ["hopper"], ["medium"], [4], ["dataset=/data/hopper.hdf5"], out_root=str(tmp_path))
    with pytest.raises(ValueError, match=r"seed is an axis of the sweep; give it as --seeds"):
        sweep(["bc"], ["hopper"], ["medium"], [4], ["+seed=3"], out_root=str(tmp_path))
    assert not (tmp_path / "sweeps").exists()


def test_an_interrupted_search_raises_before_writing_blank_rows():
    """Ctrl-C with trials pending: Ray's results hold trials with no config (never started) or no metrics (cut mid-run).
    The rows refuse them with a resume hint (was: TypeError on r.config["trial"], or blank rows over the old tables)."""
    from types import SimpleNamespace as R

    from torchrl_offhrl.recipes.tune import SearchInterrupted, _rows

    trials = [{"params": {"seed": s}} for s in (4, 5, 6)]
    done = R(config={"trial": 0}, metrics={"final_normalized_d4rl": 50.0}, error=None)
    for cut in (R(config=None, metrics=None, error=None), R(config={"trial": 1}, metrics={}, error=None)):  # never started | cut mid-run
        with pytest.raises(SearchInterrupted, match=r"sweep x: interrupted with 1 of 3 trials finished; run the same command again"):
            _rows([done, cut], trials, ["seed"], "sweep x")
    failed = R(config={"trial": 1}, metrics={}, error=ValueError("bad"))
    rows = _rows([done, failed, R(config={"trial": 2}, metrics={"final_normalized_d4rl": 1.0}, error=None)], trials, ["seed"])
    assert [(r["trial"], r["seed"], r["error"]) for r in rows] == [(0, 4, None), (1, 5, "ValueError"), (2, 6, None)]


def test_scheduler_is_validated_and_trials_carry_their_settings(tmp_path):
    from torchrl_offhrl.recipes.tune import _record_metrics, trial_index

    ok = tmp_path / "ok.yaml"
    ok.write_text("kind: agent\nscheduler: asha\ngrid: {algo.lr: [0.1, 0.2]}\n")
    assert load_search(str(ok))["scheduler"] == "asha"
    assert load_search("moc")["scheduler"] is None  # the presets run every trial's budget
    bad = tmp_path / "bad.yaml"
    bad.write_text("kind: agent\nscheduler: hyperband\ngrid: {algo.lr: [0.1]}\n")
    with pytest.raises(ValueError, match="scheduler must be one of"):
        load_search(str(bad))
    models = tmp_path / "m.yaml"
    models.write_text("kind: models\nscheduler: asha\ngrid: {ensemble.fit.lr: [0.1]}\n")
    with pytest.raises(ValueError, match="has none"):
        load_search(str(models))
    # Ray's config of a trial: its index and its settings (an experiment started before the settings were added: the index alone)
    assert trial_index({"trial": {"index": 3, "algo.lr": 0.1}}) == 3 and trial_index({"trial": 2}) == 2
    rec = {"frames": 10, "step": 10, "return_mean": 5.0, "normalized_d4rl": None, "phase": "offline", "success_per_goal": [1.0], "flag": True}
    assert _record_metrics(rec, "/r") == {"frames": 10, "step": 10, "return_mean": 5.0, "run_dir": "/r", "skipped": False,
                                          "finished": False}


def test_asha_search_reports_every_evaluation_and_finishes(ray_session, hopper_file, tmp_path, monkeypatch):
    from torchrl_offhrl.recipes.tune import tune_search

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    spec = tmp_path / "asha.yaml"
    spec.write_text("kind: agent\nscheduler: asha\nmetric: return_mean\ngrid: {algo.lr: [0.001, 0.0001]}\n"
                    "overrides: [algo=bc, train.total_updates=30, eval.every_updates=10, eval.episodes=2, eval.max_steps=20, "
                    "algo.batch_size=16, 'algo.hidden_sizes=[8]']\n")
    best = tune_search(str(spec), [f"dataset={hopper_file}"], name="a", out_root=str(tmp_path / "out"), verbose=0)
    assert best["trials"] == 2 and isinstance(best["return_mean"], float)
    for i in range(2):  # each trial is an ordinary run directory with its evaluations (0, 10, 20, 30 updates unless ASHA stopped it)
        evals = json.loads((tmp_path / "out" / "tune" / "a" / "runs" / f"trial{i:03d}" / "evals.json").read_text())
        assert [e["updates"] for e in evals][:2] == [0, 10]
    progress = list((tmp_path / "out" / "tune" / "a").rglob("progress.csv"))
    assert progress and max(len(p.read_text().strip().splitlines()) - 1 for p in progress) >= 3  # one Ray result per evaluation, not one per trial


def test_asha_stops_a_poor_trial_at_its_first_rung(ray_session, hopper_file, tmp_path, monkeypatch):
    """Issue 42's acceptance: an ASHA search stops a poor trial early. Two trials one after the other: the first's
    evaluation episodes run 20 steps, the second's 2, so at ASHA's first rung (the 2nd report: grace_period 2) the
    second's return is far below the first's recorded one and ASHA stops it there; the first runs all its evaluations."""
    from torchrl_offhrl.recipes.tune import tune_search

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    spec = tmp_path / "asha.yaml"
    spec.write_text("kind: agent\nscheduler: asha\nmetric: return_mean\ngrid: {eval.max_steps: [20, 2]}\n"
                    "overrides: [algo=bc, train.total_updates=30, eval.every_updates=10, eval.episodes=2, "
                    "algo.batch_size=16, 'algo.hidden_sizes=[8]']\n")
    tune_search(str(spec), [f"dataset={hopper_file}"], name="stop", out_root=str(tmp_path / "out"), verbose=0, max_concurrent=1)
    runs = tmp_path / "out" / "tune" / "stop" / "runs"
    full, poor = ([e["updates"] for e in json.loads((runs / f"trial{i:03d}" / "evals.json").read_text())] for i in range(2))
    assert full == [0, 10, 20, 30]
    assert poor[:2] == [0, 10] and len(poor) < len(full), poor  # stopped at the rung, before its budget
    assert not (runs / "trial001" / "summary.json").is_file() and (runs / "trial000" / "summary.json").is_file()
    import csv

    rows = list(csv.DictReader((tmp_path / "out" / "tune" / "stop" / "results.csv").open()))
    assert [(r["trial"], r["finished"], r["step"]) for r in rows] == [("0", "True", "30"), ("1", "False", str(poor[-1]))]


def test_every_command_of_the_sweeps_guide_parses_and_composes():
    """Each `offhrl tune|sweep` line of docs/guides/sweeps.md's code blocks (lines with `...` are elisions) parses as
    written, names a preset that loads, and every config it would train composes: the guide cannot drift from the CLI."""
    import itertools
    import re

    from torchrl_offhrl.cli import build_parser, overrides_last
    from torchrl_offhrl.recipes.config import compose

    text = (Path(__file__).parents[1] / "docs" / "guides" / "sweeps.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    lines = [ln.split("#", 1)[0].strip() for b in blocks for ln in b.splitlines()]
    commands = [shlex.split(ln) for ln in lines if "offhrl" in ln and "..." not in ln]
    assert len(commands) >= 5
    for words in commands:
        argv = words[words.index("offhrl") + 1:]
        args = build_parser().parse_args(overrides_last(argv))
        if argv[0] == "tune":
            assert load_search(args.preset)["grid"]
            compose("offline_train", list(args.overrides))
        else:
            assert argv[0] == "sweep"
            for algo, env, ds in itertools.product(args.algos, args.envs, args.datasets):
                compose("offline_train", [f"algo={algo}", f"env={env}", f"dataset={ds}", *args.overrides])
