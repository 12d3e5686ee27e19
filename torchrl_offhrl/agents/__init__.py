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

from collections.abc import Mapping

from ..utils import to_plain
from .base import Agent, DatasetAgent, MetricMeans, OnPolicyAgent, action_box, adam, sum_losses
from .registry import AGENTS, agent_class, agent_defaults, goal_conditioned, register_agent, requires_goal, unknown_hyperparameters

__all__ = [
    "AGENTS", "Agent", "DatasetAgent", "MetricMeans", "OnPolicyAgent", "action_box", "adam", "agent_class", "agent_defaults", "goal_conditioned", "make_agent", "register_agent", "requires_goal",
    "sum_losses", "unknown_hyperparameters",
]

def make_agent(name: str, env, cfg: Mapping | None = None, *, obs_loc=None, obs_scale=None, action_key: str = "latent_action", device="cpu",
               goal_key: str | None = None, **kwargs) -> Agent:
    """Build the agent registered as ``name`` for ``env`` (specs only: the composed model env or a real env with the same action key).

    Args:
        name: a key of :data:`AGENTS` (``sac``, ``ppo``, ``moc``, or your own).
        env: the env the agent acts in.
        obs_loc, obs_scale: observation normalisation built into the networks (the dataset's statistics).
        action_key: the key the policy writes: ``"latent_action"`` under the
            latent transform, ``"action"`` for the "no CVAE" ablation.
        device: where the networks and updates live.
        goal_key: on a goal-conditioned task (block stacking), the goal the
            agent is conditioned on (``"sub_goal"``: the low-level goal); only
            agents that take it (:func:`goal_conditioned`) can act there.
        cfg, **kwargs: the algorithm's hyper-parameters (``configs/algo/<name>.yaml``,
            as a mapping and/or keyword arguments; ``name`` and ``label`` (a
            config's run name, e.g. ``moc_official``) are not passed on). An unknown key is an error that lists the accepted ones.
    """
    cls = agent_class(name)
    cfg = {k: v for k, v in {**to_plain(cfg or {}), **kwargs}.items() if k not in ("name", "label")}
    unknown = unknown_hyperparameters(name, cfg)
    if unknown:
        raise TypeError(f"algo={name}: unknown hyper-parameter(s) {unknown}; {cls.__name__} accepts "
                        f"{sorted(agent_defaults(name, loss=cfg.get('loss')))}")
    context = {"obs_loc": obs_loc, "obs_scale": obs_scale, "action_key": action_key, "device": device}
    if goal_key is not None:
        if not goal_conditioned(name):
            raise ValueError(f"algo={name} is not goal-conditioned: on a goal-conditioned task use one of "
                             f"{sorted(n for n in AGENTS if goal_conditioned(n))}")
        context["goal_key"] = goal_key
    return cls(env, **context, **cfg).to(device)


# the algorithms shipped with the library register themselves on import
from . import bc, cql, iql, moc, mopo, ppo, sac, sac_her, td3bc, uof  # noqa: E402,F401
