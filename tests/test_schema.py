"""Up-front config validation: every bad value named with its key before any dataset or model work."""
import pytest

from torchrl_offhrl.cli import main
from torchrl_offhrl.recipes.config import compose
from torchrl_offhrl.recipes.schema import validate_config
from torchrl_offhrl.utils import to_plain

pytestmark = pytest.mark.fault("config")  # issue 73's probe suite: `make probes`

# the values of issue 14's probe: each used to start generating a 1M-transition dataset first
BAD = {
    "train.total_frames=-5": "train.total_frames: expected an integer >= 1, got -5",
    "algo.lr=-1": "algo.lr: expected a number > 0, got -1",
    "algo.num_options=0": "algo.num_options: expected an integer >= 1, got 0",
    "model_env.horizon=0": "model_env.horizon: expected an integer >= 1 or 'auto', got 0",
    "model_env.latent_bound=-1": "model_env.latent_bound: expected a number > 0 or 'auto', got -1",
    "model_env.reset_states=sometimes": "model_env.reset_states: expected one of 'initial', 'any', 'auto', got 'sometimes'",
    "eval.episodes=0": "eval.episodes: expected an integer >= 1, got 0",
    "eval.every_frames=0": "eval.every_frames: expected an integer >= 1, got 0",
    "seed=abc": "seed: expected an integer >= 0, got 'abc'",
    "model_env.member_mode=sometimes": "model_env.member_mode: expected one of 'episode', 'step', 'mean', got 'sometimes'",
    "model_env.reward_scale=-2": "model_env.reward_scale: expected a positive number or 'auto', got -2",
    "ensemble.hidden_sizes=[64,0]": "ensemble.hidden_sizes: expected a non-empty list of positive integers, got [64, 0]",
    "algo.gamma=1.5": "algo.gamma: expected a number > 0 and <= 1, got 1.5",
}


@pytest.mark.parametrize("override", sorted(BAD))
def test_each_bad_value_is_named_before_any_work(override, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    assert main(["train", override, f"out_root={tmp_path / 'runs'}"]) == 2
    err = capsys.readouterr().err
    assert BAD[override] in err
    assert not (tmp_path / "cache").exists() and not (tmp_path / "runs").exists()  # no dataset, no model, no run directory


def test_every_bad_value_at_once():
    cfg = to_plain(compose("offline_train", list(BAD)))
    with pytest.raises(ValueError) as info:
        validate_config(cfg)
    lines = str(info.value).splitlines()[1:]
    assert sorted(line.strip() for line in lines) == sorted(BAD.values())


def test_cuda_on_a_machine_without_it():
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ValueError, match="device: expected a device this machine has .* got 'cuda'"):
        validate_config(to_plain(compose("offline_train", ["device=cuda"])))
    with pytest.raises(ValueError, match="device: expected a torch device"):
        validate_config(to_plain(compose("offline_train", ["device=gpu0"])))


@pytest.mark.parametrize("config", ["offline_train", "demo", "pipeline"])
@pytest.mark.parametrize("algo", ["moc", "moc_official", "moc_joint", "moc_online", "ppo", "sac"])
def test_the_shipped_configs_are_valid(config, algo):
    for env in ("hopper", "halfcheetah"):
        validate_config(to_plain(compose(config, [f"algo={algo}", f"env={env}"])))


def test_null_head_step_sizes_and_booleans_pass():
    validate_config({"algo": {"lr": 1e-4, "termination_lr": None, "option_lr": 1e-3, "anneal_lr": True, "max_grad_norm": None}})
    with pytest.raises(ValueError, match="algo.termination_lr: expected a number > 0 or null, got 0"):
        validate_config({"algo": {"termination_lr": 0}})
    with pytest.raises(ValueError, match="algo.anneal_lr: expected true or false, got 'yes'"):
        validate_config({"algo": {"anneal_lr": "yes"}})


def test_fit_validates_too(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    assert main(["fit", "ensemble.fit.lr=0"]) == 2
    assert "ensemble.fit.lr: expected a number > 0, got 0" in capsys.readouterr().err
    assert not (tmp_path / "cache").exists()


def test_the_typed_sections_hold_the_shipped_defaults():
    """Each typed section's defaults (recipes.schema) are the values offline_train.yaml ships, key for key: the defaults
    are defined once and the YAML agrees with them; a dict config without a section gets the same values."""
    from dataclasses import asdict

    from torchrl_offhrl.recipes.schema import SECTIONS, RunConfig, section_defaults

    shipped = to_plain(compose("offline_train", []))
    for key in SECTIONS:
        assert shipped[key] == section_defaults(key), key
    assert RunConfig.parse({}) == RunConfig.parse(shipped)
    rc = RunConfig.parse(to_plain(compose("demo", [])))
    assert (rc.train.total("frames"), rc.eval.every("frames"), rc.eval.episodes, rc.collector.num_envs) == (81920, 10240, 30, 64)
    assert rc.transfer is None and asdict(rc.selection) == {"criterion": "last", "include_start": False, "guard": True, "return_cap": "data",
                                                           "fallback": "bc_unless_start"}
    t = RunConfig.parse(to_plain(compose("offline_train", ["transfer.task=backward", "transfer.online_frames=4096"]))).transfer
    assert (t.task, t.online_frames, t.num_envs, t.decoder) == ("backward", 4096, 16, "discard")
    with pytest.raises(ValueError, match="unit must be one of"):
        rc.train.total("steps")


def test_a_key_a_typed_section_lacks_is_refused_with_the_keys_it_takes():
    """A typo in a typed section (train.total_frame) used to be ignored, the run taking the default budget."""
    with pytest.raises(ValueError) as err:
        validate_config({"train": {"total_frame": 100}, "eval": {"episodes": 5, "every_frame": 10}, "selection": "last"})
    msg = str(err.value)
    assert "train.total_frame: unknown key; train takes total_frames, total_updates, online, snapshot_frames" in msg
    assert "eval.every_frame: unknown key; eval takes at_start, model_env, every_frames, every_updates, episodes" in msg
    assert "selection: expected a mapping of criterion, include_start, guard, return_cap, fallback, got 'last'" in msg


def test_cli_refuses_an_unknown_key_added_with_plus(tmp_path, monkeypatch, capsys):
    """Hydra refuses `train.total_frame=5` by itself; `+train.total_frame=5` gets past it and is refused here, before any work."""
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "cache"))
    assert main(["train", "+train.total_frame=5", f"out_root={tmp_path / 'runs'}"]) == 2
    assert "train.total_frame: unknown key; train takes total_frames" in capsys.readouterr().err
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("override,named", [
    ("model_env.discrepancy=maximum", "model_env.discrepancy: expected one of"),
    ("model_env.pessimism={threshold: 0.5, penalty: .nan}", "model_env.pessimism: expected"),
    ("model_env.pessimism={threshold: 0.5, penalty: -3}", "model_env.pessimism: expected"),
    ("model_env.pessimism={quantile: 1.5, penalty: 20}", "model_env.pessimism: expected"),
    ("model_env.pessimism={fraction: 0, penalty: 20}", "model_env.pessimism: expected"),
    ("model_env.pessimism={treshold: 0.5, penalty: 20}", "model_env.pessimism: expected"),
    ("+algo.clip_eps=0.2", "algo.clip_eps: unknown hyper-parameter of algo=ppo; it takes"),
])
def test_model_env_and_algorithm_values_are_refused_before_any_work(override, named):
    """Values that used to fail (or pass silently) only after the data and the models: now named by validate_config."""
    with pytest.raises(ValueError, match=named.replace("(", r"\(")):
        validate_config(to_plain(compose("offline_train", ["algo=ppo", "env=hopper", override])))


def test_good_pessimism_values_and_the_demo_with_sac_pass():
    for ok in ("model_env.pessimism={threshold: 0.5, penalty: 30}", "model_env.pessimism={quantile: 0.999, penalty: 0}",
               "model_env.pessimism={fraction: 1.08, penalty: 20.0}", "model_env.discrepancy=max_pairwise"):
        validate_config(to_plain(compose("offline_train", ["algo=moc", "env=hopper", ok])))
    demo = to_plain(compose("demo", ["algo=sac", "env=hopper"]))  # the demo's on-policy minibatch is not handed to SAC
    assert "minibatch_size" not in demo["algo"] and to_plain(compose("demo", ["algo=moc"]))["algo"]["minibatch_size"] == 256
    validate_config(demo)


def test_every_section_is_typed_and_refuses_a_key_it_lacks():
    """The models' and the P-MDP's sections are dataclasses like the loop's: a typo there (model_env.horizn, a fit's lrr)
    used to pass, the run taking the default; the typed view holds the nested fit as its own dataclass."""
    from torchrl_offhrl.recipes.schema import EnsembleConfig, FitConfig, parse_section

    cfg = to_plain(compose("offline_train", ["+model_env.horizn=5", "+ensemble.fit.lrr=0.1", "+ablation.no_cvea=true"]))
    with pytest.raises(ValueError) as err:
        validate_config(cfg)
    msg = str(err.value)
    assert "model_env.horizn: unknown key; model_env takes horizon, member_mode" in msg
    assert "ensemble.fit.lrr: unknown key; ensemble.fit takes lr, batch_size, max_epochs, max_steps, patience, rel_tol" in msg
    assert "ablation.no_cvea: unknown key; ablation takes no_cvae, no_pessimism" in msg
    ens = parse_section("ensemble", {"hidden_sizes": [64, 64], "fit": {"lr": 3e-4}})
    assert ens == EnsembleConfig(hidden_sizes=(64, 64), fit=FitConfig(lr=3e-4)) and ens.fit.patience == 5
    with pytest.raises(ValueError, match="ensemble.fit.patience: expected an integer >= 0, got -1"):
        validate_config({"ensemble": {"fit": {"patience": -1}}})


def test_mopos_rollout_schedule_values_are_named_before_any_work():
    """algo=mopo's schedule keys are range-checked up front, every bad one named at once."""
    with pytest.raises(ValueError) as err:
        validate_config(to_plain(compose("offline_train", ["algo=mopo", "algo.rollout_freq=0", "algo.rollout_batch_size=-4",
                                                           "algo.model_retain_rollouts=0"])))
    for named in ("algo.rollout_freq: expected an integer >= 1 or null, got 0", "algo.rollout_batch_size: expected an integer >= 1 or null, got -4",
                  "algo.model_retain_rollouts: expected an integer >= 1, got 0"):
        assert named in str(err.value)
    sac_schedule = ["algo=mopo", "algo.rollout_freq=null", "algo.rollout_batch_size=null"]
    with pytest.raises(Exception, match="with either null .SAC's schedule. give train.total_frames and eval.every_frames"):
        to_plain(compose("offline_train", sac_schedule))  # the budget in rollouts has no rollouts to count
    validate_config(to_plain(compose("offline_train", [*sac_schedule, "train.total_frames=204800", "eval.every_frames=40960"])))
