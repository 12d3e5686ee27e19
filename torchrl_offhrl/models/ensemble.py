"""Ensembles of MLPs computed with one batched matmul per layer."""
from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn

__all__ = ["EnsembleLinear", "EnsembleMLP"]


class EnsembleLinear(nn.Module):
    """``K`` independent linear layers applied with one ``torch.baddbmm``.

    Weights have shape ``[K, in, out]``; each member is initialised like
    :class:`torch.nn.Linear` (uniform in ``±1/sqrt(in)``).

    Args:
        num_members: ``K``.
        in_features / out_features: sizes of one member.

    Input ``[K, B, in]`` (one batch per member) or ``[B, in]`` (the same batch
    for every member); output ``[K, B, out]``.

    Examples:
        >>> import torch
        >>> layer = EnsembleLinear(5, 3, 2)
        >>> layer(torch.randn(7, 3)).shape
        torch.Size([5, 7, 2])
        >>> x = torch.randn(5, 7, 3)
        >>> torch.allclose(layer(x)[1], x[1] @ layer.weight[1] + layer.bias[1], atol=1e-6)
        True
    """

    def __init__(self, num_members: int, in_features: int, out_features: int):
        super().__init__()
        self.num_members = num_members
        self.in_features = in_features
        self.out_features = out_features
        bound = 1.0 / math.sqrt(in_features)
        self.weight = nn.Parameter(torch.empty(num_members, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(num_members, 1, out_features).uniform_(-bound, bound))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() == 2:
            x = x.unsqueeze(0).expand(self.num_members, *x.shape)
        elif x.dim() != 3 or x.shape[0] != self.num_members:
            raise ValueError(
                f"EnsembleLinear expects [B, {self.in_features}] or [{self.num_members}, B, "
                f"{self.in_features}] input, got {tuple(x.shape)}."
            )
        return torch.baddbmm(self.bias, x, self.weight)

    def extra_repr(self) -> str:
        return f"num_members={self.num_members}, in_features={self.in_features}, out_features={self.out_features}"


class EnsembleMLP(nn.Module):
    """An MLP of :class:`EnsembleLinear` layers: ``K`` members, one matmul per layer.

    Args:
        num_members: ``K``.
        in_features: input size.
        out_features: output size.
        hidden_sizes: hidden widths (default ``(512, 512)``, the paper's).
        activation: activation class (default ReLU).

    Examples:
        >>> import torch
        >>> net = EnsembleMLP(5, 14, 11, hidden_sizes=(32, 32))
        >>> net(torch.randn(8, 14)).shape
        torch.Size([5, 8, 11])
    """

    def __init__(
        self,
        num_members: int,
        in_features: int,
        out_features: int,
        hidden_sizes: Sequence[int] = (512, 512),
        activation: type[nn.Module] = nn.ReLU,
    ):
        super().__init__()
        self.num_members = num_members
        sizes = [in_features, *hidden_sizes, out_features]
        layers: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
            layers.append(EnsembleLinear(num_members, a, b))
            if i < len(sizes) - 2:
                layers.append(activation())
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def flops_per_sample(self) -> int:
        """Multiply-adds x2 of one forward pass of all members on one sample."""
        return sum(
            2 * m.num_members * m.in_features * m.out_features for m in self.net if isinstance(m, EnsembleLinear)
        )
