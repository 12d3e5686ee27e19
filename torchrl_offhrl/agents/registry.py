"""The registry of agents: ``register_agent`` (a class decorator) and lookups by name."""
from __future__ import annotations

import inspect

from .base import Agent

__all__ = ["AGENTS", "agent_class", "agent_defaults", "goal_conditioned", "register_agent", "requires_goal", "unknown_hyperparameters"]

#: Registered agent classes by name.
AGENTS: dict[str, type[Agent]] = {}

# arguments every builder takes from the training loop rather than from its config
_CONTEXT = ("env", "obs_loc", "obs_scale", "action_key", "device", "goal_key")


def register_agent(name: str):
    """Class decorator: make the agent available as ``make_agent(name, ...)`` / ``algo=name``."""

    def deco(cls: type[Agent]) -> type[Agent]:
        if name in AGENTS and AGENTS[name] is not cls:
            raise ValueError(f"an agent named {name!r} is already registered ({AGENTS[name].__module__}.{AGENTS[name].__qualname__})")
        cls.name = name
        AGENTS[name] = cls
        return cls

    return deco


def agent_defaults(name: str) -> dict:
    """The hyper-parameters agent ``name`` takes from its config, with their defaults (``inspect.Parameter.empty`` if required).

    A subclass whose ``__init__`` passes ``**kwargs`` on to its parent's (e.g.
    MOPO's to SAC's) takes the parent's hyper-parameters too.
    """
    out: dict = {}
    for cls in agent_class(name).__mro__:
        if "__init__" not in vars(cls):
            continue
        params = inspect.signature(cls.__init__).parameters
        for k, p in params.items():
            if k != "self" and k not in _CONTEXT and p.kind is p.KEYWORD_ONLY:
                out.setdefault(k, p.default)
        if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
            break
    return out


def unknown_hyperparameters(name: str, cfg) -> list[str]:
    """The keys of an algorithm config agent ``name`` does not take (``name`` and ``label``, a config's run name, aside), sorted."""
    accepted = agent_defaults(name)
    return sorted(k for k in cfg if k not in ("name", "label") and k not in accepted)


def agent_class(name: str) -> type[Agent]:
    """The agent class registered as ``name`` (case-insensitive; a clear error listing the registered ones otherwise)."""
    try:
        return AGENTS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r}; registered agents: {sorted(AGENTS)}") from None


def goal_conditioned(name: str) -> bool:
    """Whether agent ``name`` can act on a goal-conditioned task (its builder takes ``goal_key``, e.g. ``uof``, ``sac_her``, ``bc``)."""
    return "goal_key" in inspect.signature(agent_class(name).__init__).parameters


def requires_goal(name: str) -> bool:
    """Whether agent ``name`` acts only on goal-conditioned tasks (its ``goal_key`` has a default: ``uof``, ``sac_her``; not ``bc``)."""
    p = inspect.signature(agent_class(name).__init__).parameters.get("goal_key")
    return p is not None and p.default is not None
