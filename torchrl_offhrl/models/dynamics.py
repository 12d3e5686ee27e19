"""The dynamics (and reward) ensemble behind the pessimistic MDP."""
from __future__ import annotations

from typing import Callable, Sequence

import torch
from tensordict import TensorDictBase
from torch import nn

from ._common import FitMixin, buffer
from .ensemble import EnsembleMLP

__all__ = ["DynamicsEnsemble", "DISCREPANCIES"]

_LOSSES = ("l1", "mse", "nll")
DISCREPANCIES = ("variance", "std", "max_pairwise")
_LOGVAR_MIN, _LOGVAR_MAX = -10.0, 2.0


class DynamicsEnsemble(FitMixin, nn.Module):
    """``K`` dynamics models (and reward models) evaluated in one batched pass.

    Member ``k`` maps the normalised state and the action to the normalised
    next-state residual: ``s' = s + delta_mean + delta_std * T_k(s_bar, a)``.
    Rewards come from a learned reward ensemble ``R_k(s_bar, a)`` (the
    paper's locomotion setting) or from a known function
    ``reward_fn(obs, action, next_obs)`` (sparse goal rewards).

    Args:
        observation_dim / action_dim: sizes.
        num_models: ``K`` (paper: 5).
        hidden_sizes: hidden widths of each member (paper: ``(512, 512)``).
        loss: ``"l1"`` (paper), ``"mse"`` or ``"nll"`` (Gaussian negative
            log-likelihood; members then also predict a log-variance).
        learn_reward: learn a reward ensemble; set ``False`` and pass
            ``reward_fn`` for a known reward.
        reward_hidden_sizes: hidden widths of the reward members (default:
            ``hidden_sizes``).
        reward_fn: known reward ``f(obs, action, next_obs)`` returning ``[K, N]``
            (``next_obs`` holds every member's prediction, ``[K, N, obs_dim]``)
            or ``[N]``; used
            instead of the learned one when given. Not saved in checkpoints:
            pass it again to :meth:`load` through ``reward_fn=...`` on the
            returned model.

    Examples:
        >>> import torch
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> from torchrl_offhrl.models import DynamicsEnsemble
        >>> data = make_toy_dataset(num_episodes=10, episode_length=20)
        >>> ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(32, 32))
        >>> ens = ens.fit(data, max_epochs=2, progress=False)
        >>> out = ens.predict(data[:4]["observation"], data[:4]["action"])
        >>> out["next_observation"].shape, out["reward"].shape
        (torch.Size([3, 4, 3]), torch.Size([3, 4]))
        >>> ens.discrepancy(data[:4]["observation"], data[:4]["action"]).shape
        torch.Size([4])
    """

    train_keys = ("observation", "action", ("next", "observation"), ("next", "reward"))
    default_fit = {"lr": 1e-4, "batch_size": 256, "patience": 5}

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        num_models: int = 5,
        hidden_sizes: Sequence[int] = (512, 512),
        loss: str = "l1",
        learn_reward: bool = True,
        reward_hidden_sizes: Sequence[int] | None = None,
        reward_fn: Callable | None = None,
    ):
        super().__init__()
        if loss not in _LOSSES:
            raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}.")
        if num_models < 2:
            raise ValueError(f"an ensemble needs num_models >= 2 to measure disagreement, got {num_models}.")
        self.config = {
            "observation_dim": int(observation_dim),
            "action_dim": int(action_dim),
            "num_models": int(num_models),
            "hidden_sizes": [int(h) for h in hidden_sizes],
            "loss": loss,
            "learn_reward": bool(learn_reward),
            "reward_hidden_sizes": None if reward_hidden_sizes is None else [int(h) for h in reward_hidden_sizes],
        }
        self.observation_dim = observation_dim
        self.action_dim = action_dim
        self.num_members = num_models
        self.loss_type = loss
        out_mult = 2 if loss == "nll" else 1
        self.dynamics = EnsembleMLP(num_models, observation_dim + action_dim, observation_dim * out_mult, hidden_sizes)
        self.reward_net = (
            EnsembleMLP(num_models, observation_dim + action_dim, out_mult, reward_hidden_sizes or hidden_sizes)
            if learn_reward
            else None
        )
        self.reward_fn = reward_fn
        for name, size in [
            ("obs_mean", observation_dim), ("obs_std", observation_dim),
            ("delta_mean", observation_dim), ("delta_std", observation_dim),
            ("reward_mean", 1), ("reward_std", 1),
            ("obs_min", observation_dim), ("obs_max", observation_dim),
        ]:  # fmt: skip
            buffer(self, name, None, size)

    @property
    def num_models(self) -> int:
        return self.num_members

    @classmethod
    def for_dataset(cls, data, num_models: int = 5, **kwargs) -> "DynamicsEnsemble":
        """An ensemble sized for ``data`` with its normalisation statistics."""
        model = cls(data.observation_dim, data.action_dim, num_models=num_models, **kwargs)
        return model.set_stats(data.stats())

    def set_stats(self, stats) -> "DynamicsEnsemble":
        for name in ("obs_mean", "obs_std", "delta_mean", "delta_std", "reward_mean", "reward_std", "obs_min", "obs_max"):
            getattr(self, name).copy_(getattr(stats, name).reshape(-1))
        return self

    # -------------------------------------------------------------- forward
    def _inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return torch.cat([(obs - self.obs_mean) / self.obs_std, action], -1)

    def _split(self, out: torch.Tensor):
        if self.loss_type == "nll":
            mean, logvar = out.chunk(2, -1)
            return mean, logvar.clamp(_LOGVAR_MIN, _LOGVAR_MAX)
        return out, None

    def predict(self, observation: torch.Tensor, action: torch.Tensor, chunk: int | None = None) -> dict:
        """Every member's prediction for a batch of state-action pairs.

        ``chunk``: predict at most this many pairs at a time and concatenate
        (the same values: each pair is computed on its own). On a CPU the
        members' activations of a few thousand pairs leave the caches; in
        chunks of 1,024 the ensemble predicts 4,096 pairs 1.33x faster on the
        project's 2-core machine (``benchmarks/env_throughput.py``). None: all at once.

        Args:
            observation: ``[N, obs_dim]`` raw (unnormalised) states.
            action: ``[N, action_dim]``.

        Returns:
            dict with ``next_observation`` ``[K, N, obs_dim]``, ``reward``
            ``[K, N]`` (``None`` without a reward model or function),
            ``delta`` ``[K, N, obs_dim]`` (the normalised residuals, what the
            discrepancy is measured on).
        """
        if chunk is not None and observation.shape[0] > chunk:
            parts = [self.predict(o, a) for o, a in zip(observation.split(chunk), action.split(chunk))]
            return {k: None if parts[0][k] is None else torch.cat([p[k] for p in parts], dim=1) for k in parts[0]}
        x = self._inputs(observation, action)
        delta, _ = self._split(self.dynamics(x))
        next_obs = observation + self.delta_mean + self.delta_std * delta
        if self.reward_fn is not None:
            # [K, N] (computed per member's next state) or [N] / [N, 1] (shared)
            r = self.reward_fn(observation, action, next_obs)
            reward = r.reshape(-1, observation.shape[0]).expand(self.num_members, -1)
        elif self.reward_net is not None:
            r, _ = self._split(self.reward_net(x))
            reward = (self.reward_mean + self.reward_std * r).squeeze(-1)
        else:
            reward = None
        return {"next_observation": next_obs, "reward": reward, "delta": delta}

    forward = predict

    @staticmethod
    def discrepancy_of(delta: torch.Tensor, kind: str = "variance") -> torch.Tensor:
        """Disagreement of member predictions ``delta`` ``[K, N, D]`` -> ``[N]``.

        * ``"variance"`` (the paper): the variance across members, summed over
          state dimensions (the trace of the members' covariance);
        * ``"std"``: the square root of that trace, the L2 norm of the
          members' standard deviations: in the state's units, as MOPO's
          uncertainty (the norm of a learned standard deviation) and
          MOReL's distance are, where the variance is in squared units;
        * ``"max_pairwise"`` (MOReL): the largest L2 distance between two
          members' predictions.
        """
        if kind in ("variance", "std"):
            trace = delta.var(0, unbiased=False).sum(-1)
            return trace.sqrt() if kind == "std" else trace
        if kind == "max_pairwise":
            d = delta.transpose(0, 1)  # [N, K, D]
            return torch.cdist(d, d).flatten(1).max(-1).values
        raise ValueError(f"discrepancy must be one of {DISCREPANCIES}, got {kind!r}.")

    @torch.no_grad()
    def discrepancy(self, observation: torch.Tensor, action: torch.Tensor, kind: str = "variance") -> torch.Tensor:
        """:meth:`discrepancy_of` the members' predictions for these pairs, ``[N]``."""
        x = self._inputs(observation, action)
        delta, _ = self._split(self.dynamics(x))
        return self.discrepancy_of(delta, kind)

    # ------------------------------------------------------------- training
    def _member_loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        mean, logvar = self._split(pred)
        if self.loss_type == "l1":
            err = (mean - target).abs()
        elif self.loss_type == "mse":
            err = (mean - target).pow(2)
        else:
            err = 0.5 * (logvar + (mean - target).pow(2) * torch.exp(-logvar))
        return err.flatten(1).mean(-1) if err.dim() == 3 else err.mean()

    def loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Per-member training loss, ``[K]``; batch ``[K, B]`` or ``[B]``."""
        obs = batch.get("observation")
        act = batch.get("action")
        nobs = batch.get(("next", "observation"))
        x = self._inputs(obs, act)
        target = ((nobs - obs) - self.delta_mean) / self.delta_std
        if target.dim() == 2:
            target = target.unsqueeze(0).expand(self.num_members, *target.shape)
        loss = self._member_loss(self.dynamics(x), target)
        if self.reward_net is not None:
            r = (batch.get(("next", "reward")) - self.reward_mean) / self.reward_std
            if r.dim() == 2:
                r = r.unsqueeze(0).expand(self.num_members, *r.shape)
            loss = loss + self._member_loss(self.reward_net(x), r)
        return loss
