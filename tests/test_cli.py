"""The `offhrl` command line on tiny settings."""
import json
import os
import subprocess
import sys

import pytest

from torchrl_offhrl.cli import build_parser, main

TINY_MODELS = [
    "ensemble.hidden_sizes=[16,16]",
    "ensemble.fit.max_steps=20",
    "cvae.hidden_sizes=[16,16]",
    "cvae.fit.max_steps=20",
]
TINY_TRAIN = [
    "collector.num_envs=4",
    "train.total_frames=128",
    "eval.every_frames=128",
    "eval.episodes=2",
    "eval.max_steps=30",
    "algo.frames_per_batch=64",
    "algo.epochs=1",
]


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_help_lists_every_command():
    out = subprocess.run([sys.executable, "-m", "torchrl_offhrl.cli", "--help"], capture_output=True, text=True, check=True).stdout
    for cmd in ("demo", "policies", "collect", "fit", "train", "evaluate", "aggregate"):
        assert cmd in out
    parser = build_parser()
    for cmd in ("demo", "collect", "fit", "train", "evaluate", "aggregate"):
        with pytest.raises(SystemExit) as e:
            parser.parse_args([cmd, "--help"])
        assert e.value.code == 0


def test_collect_fit_train_evaluate_aggregate(cache, tmp_path, capsys):
    from torchrl_offhrl.data import load_dataset

    out_file = tmp_path / "hopper_random.hdf5"
    assert main(["collect", "hopper", "random", "-n", "600", "--num-envs", "2", "--out", str(out_file)]) == 0
    ds = load_dataset(out_file)
    assert len(ds) == 600 and ds.metadata["level"] == "random"
    assert list((cache / "datasets").glob("hopper-random-600-seed0*.hdf5"))

    assert main(["fit", f"dataset={out_file}", *TINY_MODELS]) == 0
    assert "models in" in capsys.readouterr().out
    # a second fit loads from the cache
    main(["fit", f"dataset={out_file}", *TINY_MODELS])
    assert "ensemble: loaded" in capsys.readouterr().out

    runs = tmp_path / "runs"
    assert main(["train", "algo=moc", f"dataset={out_file}", f"out_root={runs}", *TINY_MODELS, *TINY_TRAIN,
                 "selection.criterion=model_gain_lcb", "selection.guard=true"]) == 0
    (run,) = runs.glob("moc-hopper-hopper_random-*-seed0")
    assert (run / "checkpoint.pt").is_file()
    capsys.readouterr()

    # seed 7 is the recipe's own evaluation seed for seed=0: the deterministic
    # evaluation of the checkpoint reproduces the score recorded during training
    assert main(["evaluate", str(run), "--episodes", "2", "--seed", "7"]) == 0
    printed = capsys.readouterr().out
    res = json.loads(printed[printed.index("{\n"):])
    # the returned policy: the trained one at 128 frames, or when the guard fired the start (0) or the percentile BC
    summary = json.loads((run / "summary.json").read_text())
    returned = 0 if summary["guard"]["fired"] else 128
    assert res["episodes"] == 2 and len(res["returns"]) == 2 and res["frames"] == returned
    evals = json.loads((run / "evals.json").read_text())
    record = (json.loads((run / "fallback.json").read_text()) if summary["guard"]["returned"] == "bc" else
              next(e for e in evals if e["frames"] == returned))
    assert res["return_mean"] == pytest.approx(record["return_mean"], rel=1e-5)

    assert main(["aggregate", str(run), "--out", str(tmp_path / "report")]) == 0
    assert "| moc | Hopper-v5 |" in capsys.readouterr().out
    assert (tmp_path / "report" / "curves.png").is_file()


def test_bad_override_is_explained(cache):
    with pytest.raises(SystemExit, match="key=value"):
        main(["fit", "dataset"])


def test_unknown_dataset_name_is_explained(cache, capsys):
    assert main(["fit", "dataset=hopper-mediumm"]) == 2
    assert "neither an existing file" in capsys.readouterr().err


def test_missing_policy_is_explained(cache, capsys, monkeypatch):
    import torchrl_offhrl.data.policies as pol

    monkeypatch.setattr(pol, "POLICY_DIR", cache / "no_policies")  # as if nothing were shipped
    assert main(["collect", "hopper", "medium", "-n", "100"]) == 2
    err = capsys.readouterr().err
    assert "hopper-medium" in err and "train_behaviour.py" in err


def test_evaluate_rejects_a_non_run_directory(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path)]) == 2
    assert "not a (checkpointed) run directory" in capsys.readouterr().err
    # a folder where the checkpoint should be is named as what it is, not as missing
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "checkpoint.pt").mkdir()
    assert main(["evaluate", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "checkpoint.pt is not a regular file" in err and "is missing" not in err
    # a damaged config.json is named, in one line
    (tmp_path / "checkpoint.pt").rmdir()
    (tmp_path / "checkpoint.pt").write_bytes(b"x")
    (tmp_path / "config.json").write_text('{"env": ')
    assert main(["evaluate", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'config.json'} is not valid JSON" in err and len(err.strip().splitlines()) == 1


def test_demo_tiny(cache, tmp_path, capsys):
    from torchrl_offhrl.data import list_policies

    if "hopper-medium" not in list_policies():
        pytest.skip("no hopper-medium policy is shipped")
    args = ["demo", "num_transitions=400", f"out_root={tmp_path}", *TINY_MODELS, *TINY_TRAIN]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "behaviour data (hopper-medium)" in out and "MOC agent returned (" in out and "400 transitions of hopper-medium" in out
    assert "MOC agent before training" in out
    # the demo says how its returned policy was chosen, and prints its calibration report
    assert "(selection.criterion=last: the last policy)" in out and ("Guard: FIRED" in out or "Guard: passed" in out)
    assert "starts as a behaviour cloner of the highest-return episodes holding 10% of the transitions" in out  # the default origin
    assert "latent origin: the behaviour of the" in out  # in the calibration report, with the episodes it cloned
    summary = json.loads((tmp_path / "moc-hopper-medium-seed0" / "summary.json").read_text())
    # the guard's verdict and what it returned agree: the start (step 0) or the percentile BC when it fired, the last
    # policy when it passed; the BC's score is printed beside the others
    guard = summary["guard"]
    assert guard["returned"] == (guard["against"] if guard["fired"] else "trained") and guard["against"] in ("start", "bc")
    assert (summary["selected"]["frames"] == 0) == guard["fired"] and (summary["selected"].get("policy") == "percentile_bc") == (guard["returned"] == "bc")
    assert "percentile BC of the data's best episodes (the guard's other fallback) scored" in out
    assert "calibration report (offline rules" in out and "pessimism threshold" in out and "latent box" in out
    (run,) = tmp_path.glob("moc-hopper-medium-seed0")
    assert (run / "calibration.png").is_file() and json.loads((run / "calibration.json").read_text())["rules"] == "auto"
    assert "short-budget run" in out and "offhrl train algo=moc env=hopper dataset=medium" in out
    run = tmp_path / "moc-hopper-medium-seed0"
    assert (run / "option_usage.png").is_file() and (run / "demo_summary.json").is_file()


def test_console_script_installed():
    exe = os.path.join(os.path.dirname(sys.executable), "offhrl")
    assert os.path.exists(exe), "pip install -e . installs the offhrl console script"


def test_hydra_deletion_overrides_are_accepted():
    """``~key`` (hydra's deletion, as experiments/results/transfer.py passes for agents without a minibatch) composes."""
    from torchrl_offhrl.recipes.config import compose

    cfg = compose("demo", ["algo=sac", "~algo.minibatch_size"])
    assert "minibatch_size" not in cfg.algo
    with pytest.raises(SystemExit, match="key=value"):
        compose("demo", ["algo.minibatch_size"])


def test_fit_threads_sets_the_model_fits_thread_count_and_restores_it(cache, tmp_path, monkeypatch):
    """``fit_threads`` is the torch thread count while the models are fitted (or loaded), for every caller of
    fit_or_load_models (train, fit, tune models); the caller's count comes back."""
    import time

    import torch

    from torchrl_offhrl.recipes import pipeline, train as recipe
    from torchrl_offhrl.recipes.config import compose
    from torchrl_offhrl.utils import threads, to_plain

    with threads(2):
        assert torch.get_num_threads() == 2
        with threads(None):
            assert torch.get_num_threads() == 2
        with threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2

    class Seen(Exception):
        pass

    def fake_fit(*args, **kwargs):
        raise Seen(torch.get_num_threads())

    monkeypatch.setattr(pipeline, "_fit_or_load_models", fake_fit)  # what fit_or_load_models runs at fit_threads threads
    cfg = to_plain(compose("offline_train", ["env=hopper", "dataset=random", "num_transitions=200", "fit_threads=1",
                                             f"run_dir={tmp_path}"]))
    with threads(2):
        with pytest.raises(Seen) as seen:
            recipe.build_setting(cfg, tmp_path, time.time(), progress=False)
        assert seen.value.args == (1,) and torch.get_num_threads() == 2
    from torchrl_offhrl.recipes.schema import validate_config

    with pytest.raises(ValueError, match="fit_threads: expected an integer >= 1 or null, got 0"):
        validate_config(to_plain(compose("offline_train", ["fit_threads=0"])))


def test_the_demo_cites_no_check_its_config_has_not_had():
    """The demo prints a robustness count (recipes.demo.CHECKED) only once its own config was run on 10+ dataset seeds; the
    robustness page's count (18 of 20) is the demo before the offline rules, so today it prints none."""
    from torchrl_offhrl.recipes.demo import CHECKED, selection_lines

    assert CHECKED["runs"] == 0
    s = {"selected": {"criterion": "model_gain_lcb"}, "guard": {"fired": True, "reason": "no member shows a gain"}}
    lines = selection_lines(s, {})
    assert not any("was checked in" in line for line in lines) and any("Guard: FIRED" in line for line in lines)


def test_the_robustness_page_is_what_its_archived_runs_give():
    """docs/results/demo_robustness.md is rebuilt exactly from docs/results/demo_robustness_runs/ (experiments/results/robustness.py table)."""
    from pathlib import Path

    from importlib import import_module

    mod = import_module("experiments.results.robustness")
    page = (Path(__file__).resolve().parents[1] / "docs" / "results" / "demo_robustness.md").read_text()
    assert mod.table(list(mod.VARIANTS)) + "\n" == page
    rows = mod.rows_of(mod.SHIPPED)
    rows = [r for r in rows if r["dataset_seed"] >= 4]  # the evaluation runs (tuning runs: dataset seeds 1-3)
    assert sorted({r["dataset_seed"] for r in rows}) == list(range(4, 14)) and sorted({r["agent_seed"] for r in rows}) == [0, 1]
    wins = sum(r["selected"] > r["untrained"] and r["selected"] > r["behaviour"] for r in rows)
    assert f"| {wins}/{len(rows)} |" in page and len(rows) == 20


def test_the_robustness_variants_rerun_what_their_archived_runs_ran():
    """Rerunning a robustness variant reproduces what its archived runs ran: the legacy overrides (the demo before the offline
    rules) give the archived config of the last shipped variant, and the variants run before the demo's ensemble fit went from
    10k to 30k steps still fit 10k."""
    import json

    from torchrl_offhrl.recipes.config import LATER_DEFAULTS, compose, pessimism_for, pessimism_table
    from experiments.results import robustness as mod
    from torchrl_offhrl.utils import to_plain

    archived = json.loads((mod.ARCHIVE / mod.SHIPPED / "d4" / "config.json").read_text())
    again = to_plain(compose("demo", [*mod.overrides(mod.SHIPPED), "dataset_seed=4"]))
    for key in ("ensemble", "cvae", "selection", "algo", "train"):
        drop = {"selection": {"guard", "return_cap", "fallback"}, "train": {"snapshot_frames"}, "ensemble": {"num_elites", "learn_reward"},
                "cvae": {"goal_key"}, "algo": {"termination_coef", "option_coef", "normalize_advantage"}}.get(key, set())  # added since
        assert all(again[key][k] == LATER_DEFAULTS.get(key, {}).get(k, again[key][k]) for k in drop if k in again[key]), key  # as before
        strip = lambda d: {k: v for k, v in d.items() if k not in drop}  # noqa: E731
        fit = lambda d: {**d, "fit": {k: v for k, v in d["fit"].items() if k != "rel_tol"}} if "fit" in d else d  # noqa: E731
        assert fit(strip(again[key])) == strip(archived[key]), key
    assert again["selection"]["guard"] is False and again["ensemble"]["fit"]["rel_tol"] == 0.0
    # latent_origin came later (origin_share with it, unused under zero); its "zero" decodes as the archived runs did (no key)
    again["model_env"].pop("origin_share")
    assert again["model_env"].pop("sample") is False  # came later (MOPO's sampled step): off, the model env as it was
    assert again["model_env"].pop("latent_origin") == "zero" and again["model_env"] == archived["model_env"]
    assert pessimism_for(again["env"], "medium", table=pessimism_table(again)) == archived["resolved_pessimism"]
    old = to_plain(compose("demo", mod.overrides("shipped")))
    assert old["ensemble"]["fit"]["max_steps"] == 10000 and again["ensemble"]["fit"]["max_steps"] == 30000


@pytest.mark.parametrize("argv, expect", [
    # the README's and `sweep --help`'s example: overrides after an option with several values
    (["sweep", "--algos", "moc", "ppo", "iql", "--envs", "hopper", "halfcheetah", "--seeds", "4", "5", "6", "train.total_frames=204800"],
     {"algos": ["moc", "ppo", "iql"], "envs": ["hopper", "halfcheetah"], "seeds": [4, 5, 6], "overrides": ["train.total_frames=204800"]}),
    (["tune", "my.yaml", "--name", "x", "--max-concurrent", "1", "env=hopper", "dataset=medium"],
     {"preset": "my.yaml", "name": "x", "max_concurrent": 1, "overrides": ["env=hopper", "dataset=medium"]}),
    (["sweep", "train.total_frames=1", "--algos", "moc", "--seeds", "4"], {"algos": ["moc"], "seeds": [4], "overrides": ["train.total_frames=1"]}),
    (["sweep", "--algos", "moc", "--", "train.total_frames=1"], {"algos": ["moc"], "overrides": ["train.total_frames=1"]}),
    (["train", "algo=moc", "env=hopper"], {"overrides": ["algo=moc", "env=hopper"]}),
    (["evaluate", "some/run", "--episodes", "3"], {"run_dir": "some/run", "episodes": 3}),
])
def test_overrides_parse_wherever_they_come(argv, expect):
    """Hydra overrides may follow any option (issue: `--seeds 4 5 6 train.total_frames=...` was read as a seed)."""
    from torchrl_offhrl.cli import build_parser, overrides_last

    args = vars(build_parser().parse_args(overrides_last(argv)))
    assert {k: args[k] for k in expect} == expect


def test_a_run_dir_in_use_is_refused_in_one_line_before_any_work(tmp_path, capsys):
    """Another live run holds the folder's lock: `offhrl train` says so in one line (no traceback), rc 2, and leaves it alone."""
    from torchrl_offhrl.recipes.rundir import RunDirectory

    run = tmp_path / "busy"
    with RunDirectory(run, "fp").locked():  # a second open file description: flock refuses it, even in this process
        rc = main(["train", "algo=moc", "env=hopper", "dataset=medium", f"run_dir={run}", *TINY_MODELS, *TINY_TRAIN])
    err = capsys.readouterr().err
    assert rc == 2 and "is in use by a run that is still going" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and {p.name for p in run.iterdir()} == {".lock"}


@pytest.mark.fault("paths")
def test_config_values_that_go_into_a_run_folder_name_never_leave_out_root(tmp_path):
    """A label or env name with path separators or dots (`../`) is made one safe folder name under out_root."""
    from torchrl_offhrl.recipes.config import default_run_dir, safe_name

    cfg = {"dataset": "medium", "seed": 1, "out_root": str(tmp_path / "out"), "algo": {"name": "moc", "label": "../../escaped"},
           "env": {"name": "../hopper"}, "ablation": {}, "train": {}}
    path = default_run_dir(cfg)
    assert path.parent == tmp_path / "out" and path.resolve().parent == (tmp_path / "out").resolve()
    assert "/" not in path.name and path.name == "_.._.._escaped-.._hopper-medium-seed1"
    assert safe_name("..") == "_.." and safe_name("") == "_" and safe_name("a b;rm -rf") == "a_b_rm_-rf"
