"""Goal-conditioned block stacking (the paper's third setting): the real tasks and their shared goal functions.

* :mod:`.goals`: sub-goals, successes and rewards as pure, vectorised tensor
  functions of the state, shared by the real envs and the model env
  (:class:`torchrl_offhrl.envs.BlockStackModelEnv`);
* :mod:`.env`: ``BlockStack2-v0`` / ``BlockStack3-v0``, Gymnasium goal envs on
  gymnasium-robotics' Fetch robot, registered when this package is imported.

A base-layer package (like Gymnasium's own envs for the locomotion tasks):
the data layer collects datasets in these envs, the env layer builds the
pessimistic model env on the same functions.
"""
from . import goals
from .env import DEFAULT_HORIZON, make_blockstack_env, register_blockstack_envs

__all__ = ["DEFAULT_HORIZON", "goals", "make_blockstack_env", "register_blockstack_envs"]

register_blockstack_envs()  # gymnasium-robotics is imported only when one of the envs is made
