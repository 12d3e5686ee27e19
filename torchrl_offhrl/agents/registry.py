"""The registry of agents: ``register_agent`` (a class decorator), lookups by name, and :func:`make_agent`, which builds one."""
from __future__ import annotations

import inspect
from collections.abc import Mapping

from ..utils import to_plain
from .base import Agent

__all__ = ["AGENTS", "agent_class", "agent_defaults", "goal_conditioned", "loss_arguments", "make_agent", "loss_kwargs_for", "register_agent", "requires_goal", "unknown_hyperparameters"]

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


def agent_defaults(name: str, loss=None) -> dict:
    """The hyper-parameters agent ``name`` takes from its config, with their defaults (``inspect.Parameter.empty`` if required).

    A subclass whose ``__init__`` passes ``**kwargs`` on to its parent's (e.g.
    MOPO's to SAC's) takes the parent's hyper-parameters too. An agent whose
    ``__init__`` passes ``**loss_kwargs`` on to its loss (``loss_class``, e.g.
    MOC's :class:`~torchrl_offhrl.objectives.OptionCriticLoss`) takes the
    loss's keyword arguments, with the loss's defaults unless the agent's
    ``loss_defaults`` gives others, apart from the ones the agent sets itself
    (``loss_set_by_agent``) or, where the agent names them
    (``loss_hyperparameters``: a TorchRL loss's tuning knobs, not its
    plumbing such as ``reduction`` or ``priority_key``), only those: the loss
    declares them once. ``loss``: the
    loss class the config names instead (``algo.loss``, a class or a dotted
    path), whose own arguments are taken too.
    """
    out: dict = {}
    agent = agent_class(name)
    for params in _init_chain(agent):
        for k, p in params.items():
            if k != "self" and k not in _CONTEXT and p.kind is p.KEYWORD_ONLY:
                out.setdefault(k, p.default)
        if any(p.kind is p.VAR_KEYWORD and p.name == "loss_kwargs" for p in params.values()):
            for k, v in loss_arguments(agent, loss).items():  # the registered class's loss, defaults and exclusions
                out.setdefault(k, v)
            break
    return out


def _init_chain(cls):
    """The parameters of each ``__init__`` along ``cls``'s MRO, as far as each passes ``**kwargs`` on to the next."""
    for c in cls.__mro__:
        if "__init__" not in vars(c):
            continue
        params = inspect.signature(c.__init__).parameters
        yield params
        if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
            return


def loss_arguments(cls, loss=None) -> dict:
    """The keyword arguments (with defaults) an agent class forwarding ``**loss_kwargs`` takes for its loss: ``loss`` (a
    class, a dotted path, or None for the agent's losses), walking up the loss's own ``**kwargs`` chain. A dotted path
    is imported and checked against ``cls.loss_base`` (the class every loss of the agent derives from) as the agent does.
    An agent choosing among several losses (``loss_classes``, e.g. PPO's clipped ratio or KL penalty) takes the union of
    theirs (``loss=None``); ``loss``, one of them, gives that one's."""
    if isinstance(loss, str):
        from ..utils import import_class

        loss = import_class(loss, getattr(cls, "loss_base", cls.loss_class), "algo.loss")
    set_by_agent, deviations = getattr(cls, "loss_set_by_agent", ()), getattr(cls, "loss_defaults", {})
    only = getattr(cls, "loss_hyperparameters", None)
    classes = [loss] if loss is not None else list(getattr(cls, "loss_classes", {}).values()) or [cls.loss_class]
    out: dict = {}
    for klass in classes:
        for params in _init_chain(klass):
            for k, p in params.items():
                if k != "self" and k not in set_by_agent and (only is None or k in only) and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD):
                    out.setdefault(k, deviations.get(k, p.default))
    if only is not None and loss is None and set(only) - set(out):
        raise TypeError(f"{cls.__name__}.loss_hyperparameters names {sorted(set(only) - set(out))}, which "
                        f"{' nor '.join(c.__name__ for c in classes)} does not take")
    return out


def loss_kwargs_for(cls, loss_class, loss_kwargs: dict) -> dict:
    """The arguments an agent of class ``cls`` gives ``loss_class``, one of its ``loss_classes``: the config's
    ``loss_kwargs`` over the agent's ``loss_defaults``, less the hyper-parameters only its other losses take (a config
    holds every loss's, as ``configs/algo/ppo.yaml`` holds the clipped ratio's ``clip_epsilon`` and the KL penalty's
    ``dtarg``: the run's loss reads its own). A name no loss of the agent takes reaches the loss, whose ``TypeError``
    names it."""
    takes, every = loss_arguments(cls, loss_class), loss_arguments(cls)
    kwargs = {**getattr(cls, "loss_defaults", {}), **loss_kwargs}
    return {k: v for k, v in kwargs.items() if k in takes or k not in every}


def unknown_hyperparameters(name: str, cfg) -> list[str]:
    """The keys of an algorithm config agent ``name`` does not take (``name`` and ``label``, a config's run name, aside), sorted."""
    accepted = agent_defaults(name, loss=cfg.get("loss") if hasattr(cfg, "get") else None)
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
