"""Network pieces every layer shares: TorchRL's MLP by activation name, a fixed observation normaliser, tanh-Gaussian actors.

These sit below ``data`` in the layer order (behaviour policies, world
models, option-critic heads and every agent build on them), so no layer
needs to reach up for a generic network.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["ACTIVATIONS", "GoalMLP", "NormalizedMLP", "ObservationNormalizer", "activation_class", "mlp", "tanh_gaussian_actor"]

#: Activation names accepted by :func:`mlp` (and the configs' ``activation``).
ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU}


def activation_class(name: str) -> type[nn.Module]:
    """The activation module class for ``name`` (a clear error for an unknown one)."""
    try:
        return ACTIVATIONS[name]
    except KeyError:
        raise ValueError(f"activation {name!r} is not one of {sorted(ACTIVATIONS)}") from None


def mlp(in_dim: int, out_dim: int, hidden: Sequence[int], activation: str = "tanh") -> nn.Sequential:
    """:class:`torchrl.modules.MLP` with the activation given by name; the last layer has no activation.

    Layers are created in order (``Linear``, activation, ..., ``Linear``), so
    the initial weights for a seed and the state-dict keys (``0.weight``,
    ``2.weight``, ...) are those of a plain ``nn.Sequential``.

    Examples:
        >>> net = mlp(3, 2, [8, 8], "relu")
        >>> net(torch.zeros(5, 3)).shape
        torch.Size([5, 2])
        >>> [k for k in net.state_dict()][:2]
        ['0.weight', '0.bias']
    """
    from torchrl.modules import MLP

    return MLP(in_features=in_dim, out_features=out_dim, num_cells=list(hidden), activation_class=activation_class(activation))


class ObservationNormalizer(nn.Module):
    """``(x - loc) / scale`` with fixed buffers (e.g. the dataset's statistics).

    Offline data gives the statistics up front, so networks normalise with
    them instead of running estimates. With ``loc=None`` it is the identity.
    ``clip`` bounds the normalised values to ``[-clip, clip]`` (the official
    MOC code clips at 5).

    Examples:
        >>> norm = ObservationNormalizer(2, torch.tensor([1.0, 0.0]), torch.tensor([2.0, 1.0]))
        >>> norm(torch.tensor([3.0, 1.0]))
        tensor([1., 1.])
        >>> ObservationNormalizer(2, clip=5.0)(torch.tensor([9.0, -1.0]))
        tensor([ 5., -1.])
    """

    def __init__(self, dim: int, loc: torch.Tensor | None = None, scale: torch.Tensor | None = None, clip: float | None = None):
        super().__init__()
        loc = torch.zeros(dim) if loc is None else torch.as_tensor(loc, dtype=torch.float32).reshape(dim)
        scale = torch.ones(dim) if scale is None else torch.as_tensor(scale, dtype=torch.float32).reshape(dim)
        self.register_buffer("loc", loc.clone())
        self.register_buffer("scale", scale.clamp_min(1e-6).clone())
        if clip is not None and clip <= 0:
            raise ValueError(f"clip must be > 0 (or None for no clipping), got {clip}")
        self.clip = clip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = (x - self.loc) / self.scale
        return x if self.clip is None else x.clamp(-self.clip, self.clip)


class NormalizedMLP(nn.Module):
    """An MLP on ``cat(normalised observation, *extra)``: the dataset's statistics built into the network.

    Examples:
        >>> q = NormalizedMLP(3, 2, 1, [8], "relu", obs_loc=torch.ones(3), obs_scale=torch.full((3,), 2.0))
        >>> q(torch.zeros(5, 3), torch.zeros(5, 2)).shape
        torch.Size([5, 1])
    """

    def __init__(self, obs_dim: int, in_extra: int, out: int, hidden: Sequence[int], activation: str, obs_loc=None, obs_scale=None):
        super().__init__()
        self.norm = ObservationNormalizer(obs_dim, obs_loc, obs_scale)
        self.net = mlp(obs_dim + in_extra, out, hidden, activation)

    def forward(self, obs, *extra):
        return self.net(torch.cat([self.norm(obs), *extra], -1))


class GoalMLP(nn.Module):
    """An MLP on ``cat(norm(observation), norm(goal), *extra)``: goal-conditioned networks (UOF's, SAC + HER's).

    UOF normalises its inputs as ``(x - mean) / (std + 0.01)`` clipped to
    ``[-3, 3]``: pass ``scale = std + 0.01`` and ``clip=3``. ``extra``
    inputs (a one-hot goal, an action) are not normalised. With
    ``last_layer_init`` the last layer's weights and biases are drawn from
    ``U(-last_layer_init, last_layer_init)`` (UOF: 3e-3).

    Examples:
        >>> net = GoalMLP(3, 2, 1, 4, [8], "relu", clip=3.0)
        >>> net(torch.zeros(5, 3), torch.zeros(5, 2), torch.zeros(5, 1)).shape
        torch.Size([5, 4])
    """

    def __init__(self, obs_dim: int, goal_dim: int, in_extra: int, out: int, hidden: Sequence[int], activation: str, obs_loc=None, obs_scale=None,
                 goal_loc=None, goal_scale=None, clip: float | None = None, last_layer_init: float | None = None):
        super().__init__()
        self.norm = ObservationNormalizer(obs_dim, obs_loc, obs_scale, clip=clip)
        self.goal_norm = ObservationNormalizer(goal_dim, goal_loc, goal_scale, clip=clip)
        self.net = mlp(obs_dim + goal_dim + in_extra, out, hidden, activation)
        if last_layer_init is not None:
            last = [m for m in self.net.modules() if isinstance(m, nn.Linear)][-1]
            nn.init.uniform_(last.weight, -last_layer_init, last_layer_init)
            nn.init.uniform_(last.bias, -last_layer_init, last_layer_init)

    def forward(self, obs, goal, *extra):
        return self.net(torch.cat([self.norm(obs), self.goal_norm(goal), *extra], -1))


def tanh_gaussian_actor(module, low, high, action_key: str = "action"):
    """A TorchRL :class:`~torchrl.modules.ProbabilisticActor` with a tanh-Gaussian on the box ``[low, high]``.

    ``module`` writes ``loc`` and ``scale``; the actor writes ``action_key``
    and its log-probability (``<action_key>_log_prob``).

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import NormalParamExtractor, TensorDictModule
        >>> net = TensorDictModule(nn.Sequential(mlp(3, 4, [8]), NormalParamExtractor()), ["observation"], ["loc", "scale"])
        >>> actor = tanh_gaussian_actor(net, -torch.ones(2), torch.ones(2))
        >>> actor(TensorDict(observation=torch.zeros(5, 3), batch_size=[5]))["action"].shape
        torch.Size([5, 2])
    """
    from torchrl.modules import ProbabilisticActor, TanhNormal

    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=[action_key],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": torch.as_tensor(low, dtype=torch.float32), "high": torch.as_tensor(high, dtype=torch.float32)},
        return_log_prob=True,
    )
