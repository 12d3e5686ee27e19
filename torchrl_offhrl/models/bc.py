"""Percentile behaviour cloning: the guard's second fallback, a direct regression of the best episodes' actions."""
from __future__ import annotations

from typing import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn

from ..nets import mlp
from .trainer import FitMixin, buffer


class PercentileBC(FitMixin, nn.Module):
    """``pi(s) = low + (tanh(f(s_bar)) + 1) / 2 * (high - low)``: an MLP from the normalised state to the action box.

    Fitted on the data's highest-return episodes (percentile BC, Chen et al.
    2021: the same episodes the latent origin clones,
    ``model_env.origin_share``) by the mean absolute action error in units of
    the data's action standard deviation, to convergence on held-out
    episodes. The run's start clones the same episodes through the CVAE's
    decoder, ``decoder(s, z_b(s))``; on the design data the two had the same
    held-out action error, yet the direct regression ran 16 and 25 D4RL points
    higher in the real env on two of four datasets
    (``experiments/diagnostics/start_quality.py``,
    ``docs/results/offline_probes.md``): the guard can return either
    (:class:`~torchrl_offhrl.recipes.selection.PolicySelector`).

    Examples:
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> data = make_toy_dataset(num_episodes=4, episode_length=10)
        >>> bc = PercentileBC.for_dataset(data, hidden_sizes=(16,))
        >>> act = bc(data.data["observation"])
        >>> act.shape, bool((act.abs() <= 1).all())
        (torch.Size([40, 2]), True)
    """

    #: to convergence on the held-out episodes: checked every 500 steps, stopped after 10 checks (5,000 steps) without a
    #: better held-out error (any improvement counts). Under the CVAE's settings (an epoch-long check, 5 checks, 0.5%
    #: relative) the cloner stopped at a held-out error above the start's, i.e. stopped, not converged
    #: (``docs/results/offline_probes.md``, section 4).
    default_fit = {"lr": 1e-3, "batch_size": 256, "steps_per_epoch": 500, "patience": 10, "max_epochs": 200, "rel_tol": 0.0}
    train_keys = ("observation", "action")

    def __init__(self, observation_dim: int, action_dim: int, hidden_sizes: Sequence[int] = (256, 256)):
        super().__init__()
        self.config = {"observation_dim": int(observation_dim), "action_dim": int(action_dim), "hidden_sizes": [int(h) for h in hidden_sizes]}
        self.observation_dim, self.action_dim, self.num_members = int(observation_dim), int(action_dim), 1
        self.net = mlp(self.observation_dim, self.action_dim, hidden_sizes, "relu")
        buffer(self, "obs_mean", None, observation_dim)
        buffer(self, "obs_std", None, observation_dim)
        buffer(self, "action_low", None, action_dim)
        buffer(self, "action_high", None, action_dim)
        buffer(self, "action_std", None, action_dim)

    @classmethod
    def for_dataset(cls, data, **kwargs) -> "PercentileBC":
        """A cloner sized for ``data``, with its state statistics, action box and action spread (the loss's units)."""
        model = cls(data.observation_dim, data.action_dim, **kwargs)
        stats = data.stats()
        model.obs_mean.copy_(stats.obs_mean)
        model.obs_std.copy_(stats.obs_std)
        model.action_low.copy_(stats.action_low)
        model.action_high.copy_(stats.action_high)
        model.action_std.copy_(data.data.get("action").float().std(0).clamp_min(1e-6))
        return model

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        raw = self.net((observation - self.obs_mean) / self.obs_std)
        return self.action_low + (torch.tanh(raw) + 1) * 0.5 * (self.action_high - self.action_low)

    def loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Mean absolute action error in action-std units, shape ``[1]``."""
        batch = batch.reshape(-1)
        return ((self(batch.get("observation")) - batch.get("action")).abs() / self.action_std).mean().reshape(1)


class ClonedPolicy:
    """A :class:`PercentileBC` as an evaluator sees an agent (``recipes.evaluation``): ``eval_policy`` writes ``action`` from ``observation``."""

    def __init__(self, bc: PercentileBC):
        self.bc = bc.eval().requires_grad_(False)
        self.eval_policy = TensorDictModule(self.bc, in_keys=["observation"], out_keys=["action"])
        self.evaluation_files: tuple = ()

    def evaluation_metrics(self, td, alive) -> dict:
        return {}

    def save_evaluation(self, td, alive, folder, title) -> None:
        return None

    def state_dict(self) -> dict:
        return {"config": self.bc.config, "state_dict": {k: v.detach().cpu() for k, v in self.bc.state_dict().items()}}

    @classmethod
    def from_state(cls, state: Mapping) -> "ClonedPolicy":
        bc = PercentileBC(**state["config"])
        bc.load_state_dict(state["state_dict"])
        return cls(bc)
