"""Agents for the offline recipes: SAC (TorchRL ``SACLoss``), PPO (``ClipPPOLoss``), MOC (``OptionCriticLoss``).

:func:`make_agent` builds, from the composed env's specs and an algorithm
config, everything a training loop needs: the exploration policy, the
deterministic evaluation policy, the loss, its optimiser, the transforms the
policy needs on every env it acts in (``InitTracker`` + ``prev_option`` primer
for MOC), and whether the algorithm learns on-policy (batches of rollouts
with GAE) or off-policy (replay buffer).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from tensordict.nn import (
    AddStateIndependentNormalScale,
    NormalParamExtractor,
    TensorDictModule,
)
from torch import nn
from torchrl.envs import EnvBase

from ..modules.options import (
    ObservationNormalizer,
    OptionCriticActor,
    OptionHeads,
    make_option_critic,
    mlp,
)

__all__ = ["ALGORITHMS", "Agent", "make_agent"]

ALGORITHMS = ("sac", "ppo", "moc")


@dataclass
class Agent:
    """What a recipe needs to train and evaluate one algorithm."""

    name: str
    policy: nn.Module  # exploration policy (collectors)
    loss: nn.Module
    optimizers: list[torch.optim.Optimizer]
    on_policy: bool
    env_transforms: Callable[[], list] = field(default=list)
    target_updater: Any = None
    action_key: str = "action"
    options: int = 0

    def state_dict(self) -> dict:
        out = {"loss": self.loss.state_dict(), "optimizers": [o.state_dict() for o in self.optimizers]}
        if self.target_updater is not None:
            out["target_updater"] = self.target_updater.state_dict()
        return out

    def load_state_dict(self, state: Mapping) -> None:
        self.loss.load_state_dict(state["loss"])
        for o, s in zip(self.optimizers, state["optimizers"]):
            o.load_state_dict(s)
        if self.target_updater is not None and "target_updater" in state:
            self.target_updater.load_state_dict(state["target_updater"])


def _box(env: EnvBase, key: str):
    spec = env.full_action_spec[key] if key in env.full_action_spec.keys(True, True) else env.action_spec
    dim = spec.shape[-1]
    low = spec.space.low.reshape(-1, dim)[0].float()
    high = spec.space.high.reshape(-1, dim)[0].float()
    return dim, low, high


def make_agent(name: str, env: EnvBase, cfg: Mapping, obs_loc=None, obs_scale=None, action_key: str = "latent_action") -> Agent:
    """Build agent ``name`` (``"sac"``, ``"ppo"`` or ``"moc"``) for ``env``.

    Args:
        name: the algorithm.
        env: the env the agent acts in (specs only; the composed model env or
            a real env with the same action key).
        cfg: the algorithm's hyper-parameters (``configs/algo/<name>.yaml``).
        obs_loc, obs_scale: observation normalisation built into the networks
            (the dataset's statistics).
        action_key: the key the policy writes: ``"latent_action"`` under the
            latent transform, ``"action"`` for the "no CVAE" ablation.
    """
    name = name.lower()
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; choose one of {ALGORITHMS}")
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim, low, high = _box(env, action_key)
    return {"sac": _sac, "ppo": _ppo, "moc": _moc}[name](env, cfg, obs_dim, act_dim, low, high, obs_loc, obs_scale, action_key)


def _normalized_mlp(obs_dim, in_extra, out, hidden, activation, obs_loc, obs_scale):
    """MLP on ``cat(normalised observation, extra)``."""

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.norm = ObservationNormalizer(obs_dim, obs_loc, obs_scale)
            self.net = mlp(obs_dim + in_extra, out, hidden, activation)

        def forward(self, obs, *extra):
            return self.net(torch.cat([self.norm(obs), *extra], -1))

    return Net()


def _tanh_actor(module, low, high, action_key):
    from torchrl.modules import ProbabilisticActor, TanhNormal

    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=[action_key],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": low, "high": high},
        return_log_prob=True,
    )


def _sac(env, cfg, obs_dim, act_dim, low, high, obs_loc, obs_scale, action_key) -> Agent:
    from torchrl.modules import ValueOperator
    from torchrl.objectives import SACLoss, SoftUpdate

    hidden = list(cfg.get("hidden_sizes", [256, 256]))
    net = nn.Sequential(_normalized_mlp(obs_dim, 0, 2 * act_dim, hidden, "relu", obs_loc, obs_scale), NormalParamExtractor())
    actor = _tanh_actor(TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]), low, high, action_key)
    qnet = _normalized_mlp(obs_dim, act_dim, 1, hidden, "relu", obs_loc, obs_scale)
    qvalue = ValueOperator(qnet, in_keys=["observation", action_key], out_keys=["state_action_value"])
    loss = SACLoss(
        actor,
        qvalue,
        num_qvalue_nets=2,
        loss_function="l2",
        delay_actor=False,
        delay_qvalue=True,
        alpha_init=cfg.get("alpha_init", 1.0),
        # the unbatched spec: the default target entropy is -(action elements), per env
        action_spec=env.full_action_spec_unbatched[action_key],
    )
    loss.set_keys(action=action_key)
    loss.make_value_estimator(gamma=cfg.get("gamma", 0.99))
    lr = cfg.get("lr", 3e-4)
    opts = [
        torch.optim.Adam(loss.actor_network_params.flatten_keys().values(), lr=lr),
        torch.optim.Adam(loss.qvalue_network_params.flatten_keys().values(), lr=lr),
        torch.optim.Adam([loss.log_alpha], lr=lr),
    ]
    return Agent("sac", actor, loss, opts, on_policy=False, target_updater=SoftUpdate(loss, tau=cfg.get("tau", 0.005)), action_key=action_key)


def _ppo(env, cfg, obs_dim, act_dim, low, high, obs_loc, obs_scale, action_key) -> Agent:
    from torchrl.modules import ValueOperator
    from torchrl.objectives import ClipPPOLoss

    hidden = list(cfg.get("hidden_sizes", [64, 64]))
    act = cfg.get("activation", "tanh")
    net = nn.Sequential(
        _normalized_mlp(obs_dim, 0, act_dim, hidden, act, obs_loc, obs_scale),
        AddStateIndependentNormalScale(act_dim, scale_lb=1e-4),
    )
    actor = _tanh_actor(TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]), low, high, action_key)
    critic = ValueOperator(_normalized_mlp(obs_dim, 0, 1, hidden, act, obs_loc, obs_scale), in_keys=["observation"])
    loss = ClipPPOLoss(
        actor,
        critic,
        clip_epsilon=cfg.get("clip_epsilon", 0.2),
        entropy_coeff=cfg.get("ent_coef", 0.0),
        critic_coeff=cfg.get("vf_coef", 0.5),
        loss_critic_type="l2",  # squared error, as SB3 (whose values the paper took) and as MOC's critic
        normalize_advantage=True,
    )
    loss.set_keys(action=action_key, sample_log_prob=f"{action_key}_log_prob")
    loss.make_value_estimator(gamma=cfg.get("gamma", 0.99), lmbda=cfg.get("lmbda", 0.95))
    opt = torch.optim.Adam(loss.parameters(), lr=cfg.get("lr", 3e-4))
    return Agent("ppo", actor, loss, [opt], on_policy=True, action_key=action_key)


def _moc(env, cfg, obs_dim, act_dim, low, high, obs_loc, obs_scale, action_key) -> Agent:
    from ..objectives import OptionCriticLoss

    n = int(cfg.get("num_options", 4))
    hidden = list(cfg.get("hidden_sizes", [64, 64]))
    act = cfg.get("activation", "tanh")
    heads = OptionHeads(
        obs_dim, act_dim, n, hidden=hidden, shared_trunk=cfg.get("shared_trunk", False), activation=act,
        obs_loc=obs_loc, obs_scale=obs_scale, init_log_std=cfg.get("init_log_std", 0.0),
    )
    actor = OptionCriticActor(heads, low=low, high=high, action_key=action_key)
    critic = make_option_critic(obs_dim, n, hidden, act, obs_loc, obs_scale)
    loss = OptionCriticLoss(
        actor,
        critic,
        num_options=n,
        eta=cfg.get("eta", 0.7),
        clip_epsilon=cfg.get("clip_epsilon", 0.2),
        xi=cfg.get("xi", 0.0),
        normalize_option_advantages=cfg.get("normalize_option_advantages", False),
        critic_coef=cfg.get("critic_coef", 0.5),
        entropy_coef=cfg.get("entropy_coef", 0.0),
        option_entropy_coef=cfg.get("option_entropy_coef", 0.01),
        gamma=cfg.get("gamma", 0.99),
        lmbda=cfg.get("lmbda", 0.95),
    )
    opt = torch.optim.Adam(loss.parameters(), lr=cfg.get("lr", 1e-4))
    return Agent("moc", actor, loss, [opt], on_policy=True, env_transforms=actor.make_transforms, action_key=action_key, options=n)
