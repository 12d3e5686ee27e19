"""Damaged artefacts: each is reported in one line naming the file and the fix; cache entries are rebuilt, a run falls back."""
from pathlib import Path

import pytest
import torch

from torchrl_offhrl.data import DatasetError, load_dataset, make_toy_dataset
from torchrl_offhrl.data import generate
from torchrl_offhrl.data.catalog import dataset_path, named_dataset
from torchrl_offhrl.models import DynamicsEnsemble
from torchrl_offhrl.recipes.pipeline import fit_or_load_models
from torchrl_offhrl.recipes.rundir import RunDirectory
from torchrl_offhrl.utils import CorruptFileError


def _truncate(path, keep=0.5):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _tiny_models(tmp_path, monkeypatch):
    """Toy data and a config of two-step model fits, cached under ``tmp_path``."""
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path))
    data = make_toy_dataset(num_episodes=4, episode_length=25)
    fit = {"lr": 1e-3, "batch_size": 32, "max_epochs": 1, "max_steps": 2, "patience": 1}
    cfg = {"seed": 0, "dataset": {"val_ratio": 0.2}, "ensemble": {"num_models": 2, "hidden_sizes": [8], "loss": "l1", "fit": fit},
           "cvae": {"hidden_sizes": [8], "kl_weight": 0.05, "fit": fit}}
    return data, cfg


class _Agent:
    replay_buffer = None

    def __init__(self, value=0.0):
        self.w = torch.tensor([value])

    def state_dict(self):
        return {"w": self.w.clone()}

    def load_state_dict(self, state):
        self.w = state["w"].clone()


@pytest.mark.fault("artefact")
def test_a_damaged_run_checkpoint_falls_back_to_the_one_before(tmp_path):
    run = RunDirectory(tmp_path / "run", "fp")
    for frames, value in ((100, 1.0), (200, 2.0)):
        run.frames = frames
        run.checkpoint(_Agent(value))
    _truncate(run.checkpoint_path)
    again, agent = RunDirectory(tmp_path / "run", "fp"), _Agent()
    with pytest.warns(UserWarning, match=r"checkpoint\.pt: the run checkpoint is corrupt.*resuming from the checkpoint before it"):
        assert again.resume(agent)
    assert again.frames == 100 and agent.w.item() == 1.0  # the checkpoint at 100 frames, intact
    # without the one before: one line naming the file and the fix
    again.previous_path.unlink()
    with pytest.raises(CorruptFileError, match=r"run/checkpoint\.pt: the run checkpoint is corrupt or truncated .*delete it to start over") as info:
        RunDirectory(tmp_path / "run", "fp").resume(_Agent())
    assert "\n" not in str(info.value)


@pytest.mark.fault("data")
def test_a_damaged_hdf5_file_names_the_file(tmp_path):
    from torchrl_offhrl.data.io import save_dataset

    path = tmp_path / "d.hdf5"
    save_dataset(make_toy_dataset(num_episodes=50, episode_length=100), path)
    _truncate(path)
    with pytest.raises(DatasetError, match=r"d\.hdf5: cannot be read: the file is corrupt or truncated"):
        load_dataset(path)


@pytest.mark.fault("artefact")
def test_a_damaged_cached_dataset_is_generated_again(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path))
    # the reference returns (10 expert episodes of 1000 steps per generation, ~15 s each) play no part in recovering the file
    refs = generate._reference_returns
    monkeypatch.setattr(generate, "_reference_returns", lambda env_id, short, expert, episodes, seed: refs(env_id, short, expert, 0, seed))
    first = named_dataset("hopper-medium", num_transitions=200, seed=1, num_envs=2, progress=False)
    path = dataset_path("hopper-medium", 200, 1, 2)
    _truncate(path)
    with pytest.warns(UserWarning, match="is corrupt .* generating it again"):
        again = named_dataset("hopper-medium", num_transitions=200, seed=1, num_envs=2, progress=False)
    assert torch.equal(again.data["observation"], first.data["observation"])  # the same seed gives the same data
    load_dataset(path)  # the file is whole again


@pytest.mark.fault("artefact")
def test_a_damaged_cached_model_is_fitted_again(tmp_path, monkeypatch):
    data, cfg = _tiny_models(tmp_path, monkeypatch)
    _, _, info = fit_or_load_models(cfg, data, progress=False)
    e_path = tmp_path / "models" / info["model_dir"].rsplit("/", 1)[1] / "ensemble.pt"
    _truncate(e_path)
    with pytest.raises(CorruptFileError, match=r"ensemble\.pt: the DynamicsEnsemble checkpoint is corrupt"):
        DynamicsEnsemble.load(e_path)
    with pytest.warns(UserWarning, match=r"model cache entry is corrupt, fitting the model again: .*ensemble\.pt"):
        _, _, info = fit_or_load_models(cfg, data, progress=False)
    assert info["ensemble"] == "fitted" and info["cvae"] == "loaded"
    DynamicsEnsemble.load(e_path)


@pytest.mark.fault("resume")
def test_a_model_fit_killed_midway_resumes_from_its_cache_folder(tmp_path, monkeypatch):
    from torchrl_offhrl.models import trainer

    monkeypatch.setattr(trainer, "CHECKPOINT_EVERY_S", 0.0)  # a checkpoint after every epoch (two minutes apart by default)
    data, cfg = _tiny_models(tmp_path / "whole", monkeypatch)
    cfg["ensemble"]["fit"] = {"lr": 1e-3, "batch_size": 32, "max_epochs": 4, "patience": 10}  # 2 steps per epoch on 80 transitions
    whole = fit_or_load_models(cfg, data, progress=False, with_cvae=False)[0]

    monkeypatch.setenv("TORCHRL_OFFHRL_CACHE", str(tmp_path / "killed"))
    loss, calls = DynamicsEnsemble.loss, [0]

    def killed_in_epoch_3(self, batch):
        calls[0] += 1
        if calls[0] > 7:  # 3 calls an epoch (2 steps, 1 validation): the first step of epoch 3
            raise KeyboardInterrupt
        return loss(self, batch)

    monkeypatch.setattr(DynamicsEnsemble, "loss", killed_in_epoch_3)
    with pytest.raises(KeyboardInterrupt):
        fit_or_load_models(cfg, data, progress=False, with_cvae=False)
    [state] = (tmp_path / "killed" / "models").glob("*/ensemble.fit-state.pt")
    assert not state.with_name("ensemble.pt").exists()
    calls[0] = -(10**9)  # no kill this time; counts the steps from -1e9
    resumed, _, info = fit_or_load_models(cfg, data, progress=False, with_cvae=False)
    assert calls[0] + 10**9 == 6  # epochs 3 and 4 only (12 calls from scratch): epochs 1 and 2 came from the fit state
    assert info["ensemble"] == "fitted" and len(info["ensemble_history"]) == 4 and not state.exists()
    for a, b in zip(whole.state_dict().values(), resumed.state_dict().values()):
        assert torch.equal(a, b)


def test_a_model_is_reused_when_only_the_other_models_settings_change(tmp_path, monkeypatch):
    data, cfg = _tiny_models(tmp_path, monkeypatch)
    ens, _, first = fit_or_load_models(cfg, data, progress=False)
    other = {**cfg, "cvae": {**cfg["cvae"], "hidden_sizes": [6]}}
    ens2, cvae2, info = fit_or_load_models(other, data, progress=False)
    assert info["model_dir"] != first["model_dir"] and info["ensemble"].startswith("loaded from") and info["cvae"] == "fitted"
    for a, b in zip(ens.state_dict().values(), ens2.state_dict().values()):
        assert torch.equal(a, b)
    assert (Path(info["model_dir"]) / "ensemble.pt").is_file()  # a copy of its own
    # other ensemble settings: the ensemble is fitted, the CVAE borrowed from the first entry
    third = {**cfg, "ensemble": {**cfg["ensemble"], "hidden_sizes": [6]}}
    info3 = fit_or_load_models(third, data, progress=False)[2]
    assert info3["ensemble"] == "fitted" and info3["cvae"].startswith("loaded from")


@pytest.mark.fault("artefact")
def test_stale_tmp_files_are_removed_and_fresh_ones_kept(tmp_path):
    import os
    import time

    from torchrl_offhrl.utils import remove_stale_tmp

    (tmp_path / "a").mkdir()
    old, fresh, keep = tmp_path / "a" / "ensemble.pt.x1.tmp", tmp_path / "fresh.pt.x2.tmp", tmp_path / "cvae.pt"
    for p in (old, fresh, keep):
        p.write_bytes(b"x")
    two_hours_ago = time.time() - 7200
    os.utime(old, (two_hours_ago, two_hours_ago))
    assert remove_stale_tmp(tmp_path) == [old]
    assert not old.exists() and fresh.exists() and keep.exists()


@pytest.mark.fault("data")
def test_a_failed_dataset_load_leaves_no_run_directory(tmp_path, capsys):
    from torchrl_offhrl.cli import main

    bad = tmp_path / "bad.hdf5"
    bad.write_bytes(b"not hdf5")
    assert main(["train", f"dataset={bad}", f"out_root={tmp_path / 'runs'}"]) == 2
    assert "is not an HDF5 file" in capsys.readouterr().err
    assert not any((tmp_path / "runs").glob("*"))


@pytest.mark.fault("artefact")
def test_aggregate_names_an_empty_or_damaged_evals_file(tmp_path):
    from torchrl_offhrl.recipes.report import load_run

    run = tmp_path / "run"
    run.mkdir()
    (run / "evals.json").write_text("[]")
    with pytest.raises(ValueError, match=r"run/evals\.json holds no evaluation records"):
        load_run(run)
    (run / "evals.json").write_text('[{"frames": 0, ')
    with pytest.raises(ValueError, match=r"run/evals\.json is not valid JSON .* damaged"):
        load_run(run)


@pytest.mark.fault("artefact")
def test_a_run_record_changed_after_it_was_written_is_refused_by_its_checksum(tmp_path):
    """A record the run wrote (evals.json) with one number changed is still valid JSON, which json.loads would read as
    it is: its checksum refuses it, naming the file and both ways out; without the .sha256 (an archived copy) it reads."""
    from torchrl_offhrl.recipes.report import load_run
    from torchrl_offhrl.recipes.runs import read_json, write_json
    from torchrl_offhrl.utils import CorruptFileError, checksum_path

    run = tmp_path / "run"
    run.mkdir()
    records = [{"frames": 0, "step": 0, "return_mean": 10.0, "normalized_d4rl": 1.0}]
    write_json(run / "evals.json", records, indent=1)
    assert checksum_path(run / "evals.json").is_file() and read_json(run / "evals.json") == records
    (run / "evals.json").write_text((run / "evals.json").read_text().replace("10.0", "90.0"))
    with pytest.raises(CorruptFileError, match=r"run/evals\.json does not match its checksum evals\.json\.sha256.*delete evals\.json\.sha256"):
        load_run(run)
    checksum_path(run / "evals.json").unlink()
    assert read_json(run / "evals.json")[0]["return_mean"] == 90.0


def _flip_byte(path, at=0.6):
    data = bytearray(path.read_bytes())
    data[int(len(data) * at)] ^= 0x40
    path.write_bytes(bytes(data))


@pytest.mark.fault("artefact")
def test_a_flipped_byte_or_junk_in_a_checkpoint_is_caught_by_its_checksum_and_the_run_falls_back(tmp_path):
    """torch.load would read a checkpoint with one flipped byte without complaint (a weight of 1e37): the checksum written
    beside it refuses it, and junk bytes (struct.error inside torch.load) take the same path: resume from the one before."""
    run = RunDirectory(tmp_path / "run", "fp")
    for frames, value in ((100, 1.0), (200, 2.0)):
        run.frames = frames
        run.checkpoint(_Agent(value))
    assert run.checkpoint_path.with_name("checkpoint.pt.sha256").is_file() and run.previous_path.with_name("checkpoint.prev.pt.sha256").is_file()
    for damage in (_flip_byte, lambda p: p.write_bytes(b"\x80\x02junk" * 7)):
        good = run.checkpoint_path.read_bytes()
        damage(run.checkpoint_path)
        again, agent = RunDirectory(tmp_path / "run", "fp"), _Agent()
        with pytest.warns(UserWarning, match=r"checkpoint\.pt: the run checkpoint is corrupt or truncated.*resuming from the checkpoint before it"):
            assert again.resume(agent)
        assert again.frames == 100 and agent.w.item() == 1.0
        run.checkpoint_path.write_bytes(good)
    assert RunDirectory(tmp_path / "run", "fp").resume(_Agent())  # restored: its checksum matches again


@pytest.mark.fault("artefact")
def test_a_flipped_byte_in_a_cached_model_is_fitted_again(tmp_path, monkeypatch):
    data, cfg = _tiny_models(tmp_path, monkeypatch)
    _, _, info = fit_or_load_models(cfg, data, progress=False)
    c_path = tmp_path / "models" / info["model_dir"].rsplit("/", 1)[1] / "cvae.pt"
    _flip_byte(c_path, at=0.9)
    with pytest.raises(CorruptFileError, match=r"cvae\.pt: the ConditionalVAE checkpoint is corrupt or truncated \(its bytes do not match"):
        from torchrl_offhrl.models import ConditionalVAE

        ConditionalVAE.load(c_path)
    with pytest.warns(UserWarning, match=r"model cache entry is corrupt, fitting the model again: .*cvae\.pt"):
        _, _, info = fit_or_load_models(cfg, data, progress=False)
    assert info["cvae"] == "fitted" and info["ensemble"] == "loaded"


@pytest.mark.fault("disk")
def test_disk_faults_end_in_one_line_naming_the_folder_with_nothing_half_written(tmp_path, monkeypatch, capsys):
    """A full disk (dataset: checked before h5py writes; torch.save's writer failing), a read-only folder (every atomic
    write, and the CLI for the run folder itself): DiskWriteError naming the folder and the fix, no file left behind."""
    import errno
    import tempfile

    from torchrl_offhrl.cli import main
    from torchrl_offhrl.data import io
    from torchrl_offhrl.utils import DiskWriteError, save_torch_file

    ds = make_toy_dataset(num_episodes=4, episode_length=25)
    monkeypatch.setattr(io.shutil, "disk_usage", lambda p: type("U", (), {"free": 1000})())
    with pytest.raises(DiskWriteError, match=rf"cannot write d\.hdf5 in {tmp_path}: the dataset needs up to 1 MiB.*Free space there"):
        io.save_dataset(ds, tmp_path / "d.hdf5")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []

    def full(*a, **k):
        raise RuntimeError("[enforce fail at inline_container.cc:603] . PytorchStreamWriter failed writing file data/0: file write failed")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(DiskWriteError, match=rf"cannot write m\.pt in {tmp_path}: .*failed writing file"):
        save_torch_file({"w": 1}, tmp_path / "m.pt")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []

    def read_only(*a, **k):
        raise OSError(errno.EROFS, "Read-only file system", str(tmp_path))

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    with pytest.raises(DiskWriteError, match=rf"cannot write m\.pt in {tmp_path}: Read-only file system.*out_root="):
        save_torch_file({"w": 1}, tmp_path / "m.pt")
    monkeypatch.undo()
    # the CLI: a run folder that cannot be made is one line, rc 2
    real_mkdir = Path.mkdir

    def no_mkdir(self, *a, **k):
        if str(self).startswith(str(tmp_path / "ro")):
            raise OSError(errno.EROFS, "Read-only file system", str(self))
        return real_mkdir(self, *a, **k)

    monkeypatch.setattr(Path, "mkdir", no_mkdir)
    assert main(["train", "algo=moc", "env=hopper", f"out_root={tmp_path / 'ro'}", "train.total_frames=128"]) == 2
    err = capsys.readouterr().err
    assert "Read-only file system" in err and str(tmp_path / "ro") in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.fault("artefact")
def test_a_flipped_byte_in_a_saved_dataset_is_caught_by_its_checksum(tmp_path):
    """A byte of the data itself (not the HDF5 structure) flipped after saving: h5py would read it without complaint."""
    from torchrl_offhrl.data.io import save_dataset

    path = tmp_path / "d.hdf5"
    save_dataset(make_toy_dataset(num_episodes=50, episode_length=100), path, compression=None)
    assert path.with_name("d.hdf5.sha256").is_file()
    load_dataset(path)
    _flip_byte(path, at=0.5)
    with pytest.raises(DatasetError, match=r"d\.hdf5: cannot be read: the file is corrupt or truncated \(its bytes do not match its checksum"):
        load_dataset(path)
    path.with_name("d.hdf5.sha256").unlink()  # a file from elsewhere (no checksum): read as it is
    load_dataset(path)
