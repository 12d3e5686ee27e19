"""Agents as plug-ins: one file per algorithm, registered by name.

``make_agent("moc", env, **cfg)`` builds the agent registered as ``"moc"``
for ``env`` from its config (``configs/algo/moc.yaml``), given as keyword
arguments. An algorithm is added by writing a subclass of
:class:`~torchrl_offhrl.agents.base.Agent` in its own file, decorating it
with :func:`register_agent` and importing the file below (or, from your own
code, just defining it: registration happens at class creation); see
``CONTRIBUTING.md``.

Examples:
    >>> from torchrl_offhrl.agents import AGENTS
    >>> sorted(AGENTS)
    ['bc', 'cql', 'iql', 'moc', 'mopo', 'ppo', 'sac', 'sac_her', 'td3bc', 'uof']
"""
from __future__ import annotations

from .base import Agent, DatasetAgent, MetricMeans, OnPolicyAgent, action_box, adam, sum_losses
from .registry import AGENTS, agent_class, agent_defaults, goal_conditioned, make_agent, register_agent, requires_goal, unknown_hyperparameters

__all__ = [
    "AGENTS", "Agent", "DatasetAgent", "MetricMeans", "OnPolicyAgent", "action_box", "adam", "agent_class", "agent_defaults", "goal_conditioned", "make_agent", "register_agent", "requires_goal",
    "sum_losses", "unknown_hyperparameters",
]

# the algorithms shipped with the library register themselves on import
from . import bc, cql, iql, moc, mopo, ppo, sac, sac_her, td3bc, uof  # noqa: E402,F401
