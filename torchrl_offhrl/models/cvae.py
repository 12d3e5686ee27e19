"""A state- (and goal-) conditioned VAE over actions: the latent action space."""
from __future__ import annotations

from typing import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn

from ..nets import mlp
from .trainer import FitMixin, buffer

__all__ = ["ConditionalVAE", "CVAEDecoder", "LatentOrigin", "encode_in_chunks"]

_LOG_STD_MIN, _LOG_STD_MAX = -4.0, 15.0


@torch.no_grad()
def encode_in_chunks(cvae, td, device, chunk: int = 65536):
    """``(observation, goal, mean, std)`` of ``cvae.encode`` over the pairs of ``td`` (a dataset's TensorDict), ``chunk`` pairs at a
    time on ``device`` (``goal`` None without ``cvae.goal_key``). Any object with ``encode`` (and ``goal_key``) will do."""
    goal_key = getattr(cvae, "goal_key", None)
    obs, act = td.get("observation"), td.get("action")
    goals = td.get(goal_key) if goal_key else None
    for s in range(0, obs.shape[0], chunk):
        o, a = obs[s : s + chunk].float().to(device), act[s : s + chunk].float().to(device)
        g = None if goals is None else goals[s : s + chunk].float().to(device)
        mean, std = cvae.encode(o, a, g)
        yield o, g, mean, std


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
        self._origin: tuple = ()  # (LatentOrigin, bound) once set_origin ran: kept out of the state dict and the module tree

    @property
    def origin(self):
        """The :class:`LatentOrigin` latents are decoded relative to (None: the prior's mean, 0)."""
        return self._origin[0] if self._origin else None

    def _apply(self, fn, *args, **kwargs):
        # .to() / .cuda() / .double() reach the origin too, though it is no submodule
        out = super()._apply(fn, *args, **kwargs)
        if self._origin:
            self._origin[0]._apply(fn, *args, **kwargs)
        return out

    def set_origin(self, origin: "LatentOrigin | None", bound: float | None = None) -> "CVAEDecoder":
        """Decode every latent ``z`` as ``clamp(origin(s) + z, -bound, bound)``: ``z = 0`` is then the data's own latent at ``s``.

        ``origin=None`` restores the plain decoder. The origin is not a
        submodule (a saved CVAE never holds it: it is fitted after the CVAE and
        cached beside it, :meth:`ConditionalVAE.fit_origin`); it is moved to
        this decoder's device here. ``bound`` (the latent box, None: no clamp)
        keeps the shifted latent where the decoder was trained.
        """
        if origin is None:
            self._origin = ()
            return self
        if origin.latent_dim != self.latent_dim or origin.condition_dim != self.observation_dim + self.goal_dim:
            raise ValueError(f"the latent origin maps {origin.condition_dim} inputs to {origin.latent_dim} latents; this decoder "
                             f"conditions on {self.observation_dim + self.goal_dim} and decodes {self.latent_dim}")
        origin = origin.to(self.obs_mean.device).eval().requires_grad_(False)
        self._origin = (origin, None if bound is None else float(bound))
        return self

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
        cond = self.condition(observation, goal)
        if self._origin:
            origin, bound = self._origin
            latent = origin(cond) + latent
            if bound is not None:
                latent = latent.clamp(-bound, bound)
        return self.squash(self.net(torch.cat([cond, latent], -1)))


class LatentOrigin(FitMixin, nn.Module):
    """``z_b(s) ~ E[mu(s, a)]``: where the data's actions lie in the latent space at each state (a behaviour cloner in latents).

    An MLP from the decoder's normalised conditioning input ``[s_bar, g_bar]``
    to the mean of the CVAE posterior ``q(z | s, [g], a)`` over the data's
    actions at ``s``, fitted by regression on the posterior means of the
    dataset's pairs (:meth:`ConditionalVAE.fit_origin`). Decoded, ``z_b(s)``
    is the data's action; the prior's mean ``z = 0`` is not: with a weak KL
    term the decoder spreads the data's actions over the latent box and
    ``decoder(s, 0)`` is an average of them. Its limit: on data of several
    behaviours the regression averages their latents, and where that average
    decodes depends on the fit; fitted on the data's best episodes only
    (``model_env.latent_origin=best``, the default) it clones the best one.
    Measured in ``docs/results/offline_rules.md``.

    Examples:
        >>> import torch
        >>> o = LatentOrigin(condition_dim=3, latent_dim=2, hidden_sizes=(8,))
        >>> o(torch.zeros(5, 3)).shape
        torch.Size([5, 2])
    """

    default_fit = {"lr": 1e-3, "batch_size": 256, "patience": 5}
    train_keys = ("latent_condition", "latent_target")

    def __init__(self, condition_dim: int, latent_dim: int, hidden_sizes: Sequence[int] = (256, 256)):
        super().__init__()
        self.config = {"condition_dim": int(condition_dim), "latent_dim": int(latent_dim), "hidden_sizes": [int(h) for h in hidden_sizes]}
        self.condition_dim, self.latent_dim, self.num_members = int(condition_dim), int(latent_dim), 1
        self.net = mlp(self.condition_dim, self.latent_dim, hidden_sizes, "relu")

    def forward(self, condition: torch.Tensor) -> torch.Tensor:
        return self.net(condition)

    def loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Mean squared error to the posterior means, shape ``[1]``."""
        batch = batch.reshape(-1)
        return (self(batch.get("latent_condition")) - batch.get("latent_target")).pow(2).mean().reshape(1)


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
    def posterior_means(self, data, chunk: int = 65536) -> tuple[torch.Tensor, torch.Tensor]:
        """``(condition, mean)``: the decoder's conditioning input and the posterior mean of every pair of ``data``."""
        was = self.training
        self.eval()
        conds, means = [], []
        for obs, goal, mean, _ in encode_in_chunks(self, data.data, self.decoder.obs_mean.device, chunk):
            conds.append(self.decoder.condition(obs, goal))
            means.append(mean)
        self.train(was)
        return torch.cat(conds), torch.cat(means)

    def fit_origin(self, data, hidden_sizes: Sequence[int] = (256, 256), val_ratio: float = 0.1, split_seed: int = 0, **fit) -> LatentOrigin:
        """A :class:`LatentOrigin` fitted on ``data``'s posterior means (the same episode split as the CVAE's, to convergence).

        ``fit`` goes to :class:`~torchrl_offhrl.models.SupervisedTrainer`
        (e.g. ``seed``, ``rel_tol``, ``progress``).
        """
        from ..data import OfflineDataset

        cond, mean = self.posterior_means(data)
        td = data.data.clone(False)
        td.set("latent_condition", cond.to(td.device))
        td.set("latent_target", mean.to(td.device))
        keyed = OfflineDataset(td, metadata=data.metadata, action_bounds=(data.action_low, data.action_high))
        origin = LatentOrigin(cond.shape[-1], self.latent_dim, hidden_sizes).to(cond.device)
        return origin.fit(keyed, val_ratio=val_ratio, split_seed=split_seed, **{"desc": "fit LatentOrigin", **fit})

    @torch.no_grad()
    def sample(self, observation, goal=None, clip: float | None = 0.5):
        """Decode latents drawn from ``N(0, I)`` (clipped to ``±clip`` as BCQ does)."""
        z = torch.randn(*observation.shape[:-1], self.latent_dim, device=observation.device)
        if clip is not None:
            z = z.clamp(-clip, clip)
        return self.decoder(observation, z, goal)
