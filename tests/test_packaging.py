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
