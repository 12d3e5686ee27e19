import os

import pytest
import torch

torch.set_num_threads(1 if os.environ.get("PYTEST_XDIST_WORKER") else min(2, torch.get_num_threads()))  # xdist: one thread per worker

#: the classes of faults the probe suite covers (``@pytest.mark.fault(kind)``; ``make probes`` runs them and counts per class)
FAULT_CLASSES = {
    "data": "implausible or unreadable data: refused with the file, key and index, nothing left behind",
    "artefact": "damaged or malicious files the library reads: caught by their checksums or a safe loader, rebuilt or fallen back",
    "config": "bad config values: named before any data, fit or training work",
    "disk": "a full, read-only or forbidden disk: one line naming the folder, nothing half-written",
    "paths": "names from the config or a checkpoint never lead outside out_root and the cache",
    "resume": "a killed fit or run resumes to what an uninterrupted one gives",
}


def pytest_configure(config):
    config.addinivalue_line("markers", "fault(kind): a probe of issue 73's fault classes (tests/conftest.py FAULT_CLASSES)")


def pytest_collection_modifyitems(config, items):
    kinds = {}
    for item in items:
        marker = item.get_closest_marker("fault")
        if marker is not None:
            kind = marker.args[0]
            if kind not in FAULT_CLASSES:
                raise pytest.UsageError(f"{item.nodeid}: fault class {kind!r} is not one of {sorted(FAULT_CLASSES)}")
            kinds[item.nodeid] = kind
    config.stash[_FAULT_KINDS] = kinds


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """With ``-m fault`` (``make probes``): how many probes of each class held and failed."""
    if "fault" not in (config.option.markexpr or ""):
        return
    kinds = config.stash.get(_FAULT_KINDS, {})
    counts = {kind: [0, 0] for kind in FAULT_CLASSES}
    for outcome, column in (("passed", 0), ("failed", 1), ("error", 1)):
        for report in terminalreporter.stats.get(outcome, []):
            if report.when in ("call", "setup") and report.nodeid in kinds and (outcome != "passed" or report.when == "call"):
                counts[kinds[report.nodeid]][column] += 1
    terminalreporter.write_sep("=", "fault probes (issue 73): held / failed per class")
    for kind, (held, failed) in counts.items():
        terminalreporter.write_line(f"{kind:9s} {held:3d} held {failed:3d} failed   {FAULT_CLASSES[kind]}")


_FAULT_KINDS = pytest.StashKey[dict]()


@pytest.fixture(scope="session")
def toy_data():
    from torchrl_offhrl.data import make_toy_dataset

    return make_toy_dataset(num_episodes=40, episode_length=25, seed=0)


@pytest.fixture(scope="session")
def fitted_ensemble(toy_data):
    """A small ensemble fitted on the toy linear dynamics (actions in [-0.5, 0.5])."""
    from torchrl_offhrl.models import DynamicsEnsemble

    torch.manual_seed(0)
    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=5, hidden_sizes=(64, 64))
    ens.fit(toy_data, lr=1e-3, batch_size=128, max_epochs=60, patience=10, progress=False)
    return ens


@pytest.fixture(scope="session")
def fitted_gaussian_ensemble(toy_data):
    """MOPO's kind of ensemble on the toy data: Gaussian members (loss nll, learned log-variance bounds), 4 fitted, 3 elites."""
    from torchrl_offhrl.models import DynamicsEnsemble

    torch.manual_seed(0)
    ens = DynamicsEnsemble.for_dataset(toy_data, num_models=4, hidden_sizes=(64, 64), loss="nll", num_elites=3)
    ens.fit(toy_data, lr=1e-3, batch_size=128, max_epochs=30, patience=10, progress=False)
    return ens


@pytest.fixture(scope="session")
def fitted_cvae(toy_data):
    from torchrl_offhrl.models import ConditionalVAE

    torch.manual_seed(0)
    return ConditionalVAE.for_dataset(toy_data, hidden_sizes=(64, 64)).fit(
        toy_data, lr=1e-3, max_epochs=20, progress=False
    )


@pytest.fixture(scope="module")
def hopper_file(tmp_path_factory):
    """A small Hopper-v5 dataset file (1200 random transitions) for the recipes' end-to-end tests."""
    from torchrl_offhrl.data import collect_dataset, save_dataset

    path = tmp_path_factory.mktemp("data") / "hopper_random.hdf5"
    save_dataset(collect_dataset("Hopper-v5", 1200, num_envs=4, seed=0, progress=False), path)
    return path


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A fresh model/dataset cache (``TORCHRL_OFFHRL_CACHE``) for one test module."""
    old = os.environ.get("TORCHRL_OFFHRL_CACHE")
    path = tmp_path_factory.mktemp("cache")
    os.environ["TORCHRL_OFFHRL_CACHE"] = str(path)
    yield path
    if old is None:
        os.environ.pop("TORCHRL_OFFHRL_CACHE")
    else:
        os.environ["TORCHRL_OFFHRL_CACHE"] = old


def load_script(name: str):
    """``scripts/<name>.py`` (or ``experiments/diagnostics/<name>.py``) as a fresh module (the scripts are no package):
    ``load_script("action_pack").main([...])``."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    path = root / "scripts" / f"{name}.py"
    if not path.is_file():
        path = root / "experiments" / "diagnostics" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"{name}_script", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
