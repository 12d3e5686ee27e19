"""Install-level regressions: pinned dependencies and the public API."""
import importlib.metadata as md
from pathlib import Path

import pytest


def test_fetch_env_resets():
    """gymnasium-robotics' Fetch envs fail at reset with mujoco >= 3.12 (see pyproject's pin)."""
    import gymnasium as gym
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    env = gym.make("FetchPickAndPlace-v4")
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
    obs, *_ = env.step(env.action_space.sample())
    assert obs["observation"].shape == (25,)
    env.close()


def test_mujoco_pin_is_declared_and_honoured():
    text = (Path(__file__).parents[1] / "pyproject.toml").read_text()
    assert '"mujoco>=3.5,<3.12"' in text
    major, minor = (int(x) for x in md.version("mujoco").split(".")[:2])
    assert (major, minor) < (3, 12)


def test_public_api_imports():
    from torchrl_offhrl.data import load_dataset  # noqa: F401
    from torchrl_offhrl.envs import LatentActionTransform, PessimisticModelEnv  # noqa: F401
    from torchrl_offhrl.models import ConditionalVAE, DynamicsEnsemble  # noqa: F401
    from torchrl.envs import EnvBase, Transform

    assert issubclass(PessimisticModelEnv, EnvBase) and issubclass(LatentActionTransform, Transform)


@pytest.mark.parametrize("name", ["torchrl", "tensordict"])
def test_torchrl_family_versions(name):
    assert md.version(name).startswith("0.14")


def test_wheel_ships_configs_and_policies(tmp_path):
    """A non-editable install must find the hydra configs and the shipped policies."""
    import subprocess
    import sys
    import zipfile
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    try:  # build with the venv's setuptools when it is recent enough, else let pip fetch one
        import setuptools

        recent = int(setuptools.__version__.split(".")[0]) >= 77
    except ImportError:
        recent = False
    flags = ["--no-build-isolation"] if recent else []
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(root), "--no-deps", *flags, "-q", "-w", str(tmp_path)], check=True)
    (wheel,) = tmp_path.glob("*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for cfg in ("offline_train.yaml", "demo.yaml", "algo/moc.yaml", "algo/ppo.yaml", "algo/sac.yaml", "env/hopper.yaml", "env/halfcheetah.yaml"):
        assert f"torchrl_offhrl/configs/{cfg}" in names, cfg
    shipped = {Path(n).name for n in names if n.startswith("torchrl_offhrl/data/policies/")}
    assert {"hopper-medium.pt", "hopper-medium.json"} <= shipped


def test_one_version_and_a_changelog_entry_for_it():
    """The version lives in pyproject.toml alone (the package reads it back), and CHANGELOG.md says where it stands."""
    import re

    import torchrl_offhrl

    root = Path(__file__).parents[1]
    version = re.search(r'^version = "([^"]+)"$', (root / "pyproject.toml").read_text(), re.M).group(1)
    assert torchrl_offhrl.__version__ == version  # an editable install made before a version bump: reinstall (make install)
    log = (root / "CHANGELOG.md").read_text()
    released = re.findall(r"^## \[(\d+\.\d+\.\d+)\] - \d{4}-\d{2}-\d{2}$", log, re.M)
    assert released, "CHANGELOG.md has no release section"
    if ".dev" in version:  # work towards the next release: listed under [Unreleased], which names it
        assert f"`{version}`" in log.split("## [", 2)[1]
    else:
        assert released[0] == version
