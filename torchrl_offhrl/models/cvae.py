"""A state- (and goal-) conditioned VAE over actions: the latent action space."""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn

from ..nets import mlp
from ._common import FitMixin, buffer

__all__ = ["ConditionalVAE", "CVAEDecoder"]

_LOG_STD_MIN, _LOG_STD_MAX = -4.0, 15.0


class CVAEDecoder(nn.Module):
    """``a = D(s_bar, [g], z)``: maps a latent action to an action in the box.

    Takes *raw* observations (and goals); normalisation happens inside, so the
    decoder can be used directly on an environment's observations. Outputs
    lie in ``[action_low, action_high]`` (a scaled ``tanh``).

    Examples:
        >>> import torch
        >>> dec = CVAEDecoder(observation_dim=3, action_dim=2, latent_dim=2, hidden_sizes=(16,))
        >>> a = dec(torch.randn(5, 3), 10 * torch.randn(5, 2))
        >>> a.shape, bool(a.abs().max() <= 1.0)
        (torch.Size([5, 2]), True)
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        latent_dim: int,
        hidden_sizes: Sequence[int] = (750, 750),
        goal_dim: int = 0,
    ):
        super().__init__()
        self.observation_dim = observation_dim
        self.action_dim = action_dim
        self.latent_dim = latent_dim
        self.goal_dim = goal_dim
        self.net = mlp(observation_dim + goal_dim + latent_dim, action_dim, hidden_sizes, "relu")
        buffer(self, "obs_mean", None, observation_dim)
        buffer(self, "obs_std", None, observation_dim)
        buffer(self, "goal_mean", None, goal_dim)
        buffer(self, "goal_std", None, goal_dim)
        buffer(self, "action_low", None, action_dim)
        buffer(self, "action_high", None, action_dim)

    def condition(self, observation: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        """The normalised conditioning input ``[s_bar, g_bar]``."""
        parts = [(observation - self.obs_mean) / self.obs_std]
        if self.goal_dim:
            if goal is None:
                raise ValueError(f"this decoder is goal-conditioned (goal_dim={self.goal_dim}); pass the goal.")
            parts.append((goal - self.goal_mean) / self.goal_std)
        return torch.cat(parts, -1)

    def squash(self, raw: torch.Tensor) -> torch.Tensor:
        return self.action_low + (torch.tanh(raw) + 1) * 0.5 * (self.action_high - self.action_low)

    def forward(self, observation: torch.Tensor, latent: torch.Tensor, goal: torch.Tensor | None = None) -> torch.Tensor:
        return self.squash(self.net(torch.cat([self.condition(observation, goal), latent], -1)))


class ConditionalVAE(FitMixin, nn.Module):
    """State-conditioned VAE over actions (BCQ/PLAS style), as in the paper.

    Encoder ``E(s_bar, [g], a) -> N(mu, sigma)`` over a latent of
    ``latent_dim`` (default: the action dimension), decoder
    :class:`CVAEDecoder`. Loss = reconstruction (L1 by default, MSE
    selectable) + ``kl_weight`` * KL to ``N(0, I)``. In eval mode the
    reconstruction uses the latent mean.

    Args:
        observation_dim / action_dim: sizes.
        latent_dim: latent size (default ``action_dim``).
        hidden_sizes: encoder and decoder widths (paper: ``(750, 750)``).
        goal_dim: size of the goal conditioning (0: none).
        goal_key: dataset key of the goal when ``goal_dim > 0``.
        kl_weight: weight of the KL term (default 0.5).
        loss: ``"l1"`` or ``"mse"``.

    Examples:
        >>> import torch
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> from torchrl_offhrl.models import ConditionalVAE
        >>> data = make_toy_dataset(num_episodes=10, episode_length=20)
        >>> cvae = ConditionalVAE.for_dataset(data, hidden_sizes=(32, 32))
        >>> cvae = cvae.fit(data, max_epochs=2, progress=False)
        >>> a = cvae.decoder(data[:4]["observation"], torch.zeros(4, cvae.latent_dim))
        >>> a.shape
        torch.Size([4, 2])
    """

    default_fit = {"lr": 1e-4, "batch_size": 256, "patience": 5}

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        latent_dim: int | None = None,
        hidden_sizes: Sequence[int] = (750, 750),
        goal_dim: int = 0,
        goal_key: str | None = None,
        kl_weight: float = 0.5,
        loss: str = "l1",
    ):
        super().__init__()
        if loss not in ("l1", "mse"):
            raise ValueError(f"loss must be 'l1' or 'mse', got {loss!r}.")
        if goal_dim and goal_key is None:
            raise ValueError("a goal-conditioned CVAE (goal_dim > 0) needs goal_key, e.g. 'desired_goal'.")
        latent_dim = int(latent_dim or action_dim)
        self.config = {
            "observation_dim": int(observation_dim),
            "action_dim": int(action_dim),
            "latent_dim": latent_dim,
            "hidden_sizes": [int(h) for h in hidden_sizes],
            "goal_dim": int(goal_dim),
            "goal_key": goal_key,
            "kl_weight": float(kl_weight),
            "loss": loss,
        }
        self.num_members = 1
        self.latent_dim = latent_dim
        self.goal_key = goal_key
        self.kl_weight = kl_weight
        self.loss_type = loss
        self.train_keys = ("observation", "action") + ((goal_key,) if goal_dim else ())
        self.encoder = mlp(observation_dim + goal_dim + action_dim, 2 * latent_dim, hidden_sizes, "relu")
        self._decoder = CVAEDecoder(observation_dim, action_dim, latent_dim, hidden_sizes, goal_dim)

    @property
    def decoder(self) -> CVAEDecoder:
        """The decoder, what :class:`~torchrl_offhrl.envs.LatentActionTransform` wraps."""
        return self._decoder

    @classmethod
    def for_dataset(cls, data, goal_key: str | None = None, **kwargs) -> "ConditionalVAE":
        """A CVAE sized for ``data`` with its normalisation statistics and action box."""
        goal_dim = data.data.get(goal_key).shape[-1] if goal_key else 0
        model = cls(data.observation_dim, data.action_dim, goal_dim=goal_dim, goal_key=goal_key, **kwargs)
        stats = data.stats()
        dec = model.decoder
        dec.obs_mean.copy_(stats.obs_mean)
        dec.obs_std.copy_(stats.obs_std)
        dec.action_low.copy_(stats.action_low)
        dec.action_high.copy_(stats.action_high)
        if goal_key:
            g = data.data.get(goal_key).float()
            dec.goal_mean.copy_(g.mean(0))
            dec.goal_std.copy_(g.std(0).clamp_min(1e-6))
        return model

    def encode(self, observation, action, goal=None):
        """Mean and standard deviation of ``q(z | s, [g], a)``."""
        h = self.encoder(torch.cat([self.decoder.condition(observation, goal), action], -1))
        mean, log_std = h.chunk(2, -1)
        return mean, log_std.clamp(_LOG_STD_MIN, _LOG_STD_MAX).exp()

    def forward(self, observation, action, goal=None):
        """Reconstruction, latent mean and std (sampled latent in train mode)."""
        mean, std = self.encode(observation, action, goal)
        z = mean + std * torch.randn_like(std) if self.training else mean
        return self.decoder(observation, z, goal), mean, std

    def loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Reconstruction + ``kl_weight`` * KL, shape ``[1]``; batch ``[B]`` or ``[1, B]``."""
        batch = batch.reshape(-1)
        obs, act = batch.get("observation"), batch.get("action")
        goal = batch.get(self.goal_key) if self.goal_key else None
        recon, mean, std = self(obs, act, goal)
        err = (recon - act).abs() if self.loss_type == "l1" else (recon - act).pow(2)
        kl = -0.5 * (1 + 2 * std.log() - mean.pow(2) - std.pow(2))
        return (err.mean() + self.kl_weight * kl.mean()).reshape(1)

    @torch.no_grad()
    def sample(self, observation, goal=None, clip: float | None = 0.5):
        """Decode latents drawn from ``N(0, I)`` (clipped to ``±clip`` as BCQ does)."""
        z = torch.randn(*observation.shape[:-1], self.latent_dim, device=observation.device)
        if clip is not None:
            z = z.clamp(-clip, clip)
        return self.decoder(observation, z, goal)
