"""The dynamics (and reward) ensemble behind the pessimistic MDP, and its members as one network (:class:`EnsembleMLP`: one
batched matmul per layer, no Python loop over members)."""
from __future__ import annotations

import math
from typing import Callable, Sequence

import torch
from tensordict import TensorDictBase
from torch import nn

from .trainer import FitMixin, buffer

__all__ = ["DISCREPANCIES", "DynamicsEnsemble", "EnsembleLinear", "EnsembleMLP"]

_LOSSES = ("l1", "mse", "nll")
DISCREPANCIES = ("variance", "std", "max_pairwise", "aleatoric")
#: where a Gaussian member's learned log-variance bounds start (MOPO's and MBPO's code: -10 and 0.5)
LOGVAR_MIN_INIT, LOGVAR_MAX_INIT = -10.0, 0.5
#: weight of the bounds' regulariser in each member's loss (MOPO's code: 0.01 x (sum of max - sum of min))
LOGVAR_BOUND_WEIGHT = 0.01


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
        loss: ``"l1"`` (paper), ``"mse"`` or ``"nll"`` (MOPO's Gaussian
            ensemble: members also predict a log-variance, softly bounded by
            learned bounds, see below).
        num_elites: MOPO's elites: after :meth:`fit`, keep only this many
            members, those with the lowest held-out error of their mean
            prediction (MOPO trains 7 and keeps 5); ``None`` keeps all. The
            kept members become the ensemble (``num_models`` is then the
            elites' count; ``elites`` records which were kept and why).
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
        elites: set by :meth:`fit` when ``num_elites`` pruned the ensemble
            (the trained count, the kept members, their held-out errors);
            stored in the checkpoint's config.

    With ``loss="nll"`` each member predicts a mean and a log-variance for
    the state residual and the reward. As in MOPO's code, the log-variance
    is squashed between a learned upper and lower bound,
    ``max - softplus(max - v)`` then ``min + softplus(v - min)``, which start
    at 0.5 and -10 and are pushed together by ``0.01 (sum max - sum min)``
    in the loss; the loss is ``mean((mu - y)^2 exp(-v) + v)``. Each member
    has its own bounds (MOPO shares one pair across members) so that the
    trainer restores every member's best weights, bounds included, on their
    own; early stopping and the elites use the held-out mean squared error
    of the means (:meth:`val_loss`), as MOPO's does. :meth:`predict` then
    also returns every member's predicted standard deviation in the data's
    units (``std``), from which ``discrepancy="aleatoric"`` is MOPO's
    penalty.

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
        num_elites: int | None = None,
        elites: dict | None = None,
    ):
        super().__init__()
        if loss not in _LOSSES:
            raise ValueError(f"loss must be one of {_LOSSES}, got {loss!r}.")
        if num_models < 2:
            raise ValueError(f"an ensemble needs num_models >= 2 to measure disagreement, got {num_models}.")
        if num_elites is not None and not 2 <= int(num_elites) <= num_models:
            raise ValueError(f"num_elites must be between 2 and num_models ({num_models}), got {num_elites}: the elites are "
                             "the members kept after the fit, and the pessimism needs two of them to disagree.")
        self.config = {
            "observation_dim": int(observation_dim),
            "action_dim": int(action_dim),
            "num_models": int(num_models),
            "hidden_sizes": [int(h) for h in hidden_sizes],
            "loss": loss,
            "learn_reward": bool(learn_reward),
            "reward_hidden_sizes": None if reward_hidden_sizes is None else [int(h) for h in reward_hidden_sizes],
            "num_elites": None if num_elites is None else int(num_elites),
            "elites": elites,
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
        if loss == "nll":  # learned log-variance bounds, one pair per member and output (see the class docstring)
            outs = {"dynamics": observation_dim, **({"reward": 1} if learn_reward else {})}
            self.max_logvar = nn.ParameterDict({k: nn.Parameter(torch.full((num_models, 1, d), LOGVAR_MAX_INIT)) for k, d in outs.items()})
            self.min_logvar = nn.ParameterDict({k: nn.Parameter(torch.full((num_models, 1, d), LOGVAR_MIN_INIT)) for k, d in outs.items()})
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

    def _split(self, out: torch.Tensor, head: str = "dynamics"):
        """``(mean, log-variance or None)`` of a head's output ``[K, N, 2D]``: the log-variance softly bounded by that head's
        learned bounds (``loss="nll"``)."""
        if self.loss_type == "nll":
            mean, logvar = out.chunk(2, -1)
            hi, lo = self.max_logvar[head], self.min_logvar[head]
            logvar = hi - nn.functional.softplus(hi - logvar)
            return mean, lo + nn.functional.softplus(logvar - lo)
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
        delta, logvar = self._split(self.dynamics(x))
        next_obs = observation + self.delta_mean + self.delta_std * delta
        std = None if logvar is None else (0.5 * logvar).exp() * self.delta_std  # [K, N, D], the state's units
        if self.reward_fn is not None:
            # [K, N] (computed per member's next state) or [N] / [N, 1] (shared)
            r = self.reward_fn(observation, action, next_obs)
            reward = r.reshape(-1, observation.shape[0]).expand(self.num_members, -1)
        elif self.reward_net is not None:
            r, r_logvar = self._split(self.reward_net(x), "reward")
            reward = (self.reward_mean + self.reward_std * r).squeeze(-1)
            if std is not None:  # MOPO's model predicts the reward beside the state: its std counts in the penalty too
                std = torch.cat([std, (0.5 * r_logvar).exp() * self.reward_std], -1)
        else:
            reward = None
        return {"next_observation": next_obs, "reward": reward, "delta": delta, "std": std}

    forward = predict

    @staticmethod
    def discrepancy_of(delta: torch.Tensor, kind: str = "variance", std: torch.Tensor | None = None) -> torch.Tensor:
        """Disagreement of member predictions ``delta`` ``[K, N, D]`` -> ``[N]``.

        * ``"variance"`` (the paper): the variance across members, summed over
          state dimensions (the trace of the members' covariance);
        * ``"std"``: the square root of that trace, the L2 norm of the
          members' standard deviations: in the state's units, as MOPO's
          uncertainty (the norm of a learned standard deviation) and
          MOReL's distance are, where the variance is in squared units;
        * ``"max_pairwise"`` (MOReL): the largest L2 distance between two
          members' predictions;
        * ``"aleatoric"`` (MOPO's penalty): not a disagreement but the largest
          L2 norm over members of each member's own predicted standard
          deviation, ``std`` ``[K, N, D']`` (:meth:`predict`'s, state and
          reward, in the data's units): needs an ensemble with ``loss="nll"``.
        """
        if kind == "aleatoric":
            if std is None:
                raise ValueError("discrepancy='aleatoric' (MOPO's penalty) is the norm of the members' predicted standard "
                                 "deviations: it needs an ensemble that predicts them, fitted with loss='nll' "
                                 "(ensemble.loss=nll), not one fitted with an L1 or MSE loss.")
            return std.norm(dim=-1).amax(0)
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
        if kind == "aleatoric":
            pred = self.predict(observation, action)
            return self.discrepancy_of(pred["delta"], kind, pred["std"])
        x = self._inputs(observation, action)
        delta, _ = self._split(self.dynamics(x))
        return self.discrepancy_of(delta, kind)

    # ------------------------------------------------------------- training
    def _member_loss(self, pred: torch.Tensor, target: torch.Tensor, head: str = "dynamics") -> torch.Tensor:
        mean, logvar = self._split(pred, head)
        if self.loss_type == "l1":
            err = (mean - target).abs()
        elif self.loss_type == "mse":
            err = (mean - target).pow(2)
        else:
            err = logvar + (mean - target).pow(2) * torch.exp(-logvar)
        loss = err.flatten(1).mean(-1) if err.dim() == 3 else err.mean()
        if self.loss_type == "nll":  # the bounds' regulariser: pulls each member's max and min log-variance together
            loss = loss + LOGVAR_BOUND_WEIGHT * (self.max_logvar[head].flatten(1).sum(-1) - self.min_logvar[head].flatten(1).sum(-1))
        return loss

    @torch.no_grad()
    def val_loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Held-out error per member, ``[K]``, what early stopping and the elites compare: the training loss, except for
        ``loss="nll"``, where it is the mean squared error of the means (state residual and reward, normalised), as in
        MOPO's code (a likelihood rewards a member that only widens its variance)."""
        if self.loss_type != "nll":
            return self.loss(batch)
        x, target, r = self._inputs_and_targets(batch)
        err = (self._split(self.dynamics(x))[0] - target).pow(2).flatten(1).mean(-1)
        if r is not None:
            err = err + (self._split(self.reward_net(x), "reward")[0] - r).pow(2).flatten(1).mean(-1)
        return err

    def fit(self, data, val_ratio: float = 0.1, split_seed: int = 0, **trainer_kwargs) -> "DynamicsEnsemble":
        """:meth:`FitMixin.fit <torchrl_offhrl.models.trainer.FitMixin.fit>`, then, with ``num_elites``, keep the elites:
        the members with the lowest :meth:`val_loss` on the held-out episodes (the same split), in that order."""
        super().fit(data, val_ratio=val_ratio, split_seed=split_seed, **trainer_kwargs)
        elites = self.config["num_elites"]
        if elites is None or elites == self.num_members:
            return self
        held_out = data.split(val_ratio, seed=split_seed)[1] if val_ratio and data.num_episodes >= 2 else data
        device = next(self.parameters()).device
        errors = self.val_loss(held_out.data.select(*self.train_keys).to(device))
        keep = errors.argsort()[:elites]
        return self.keep_members(keep, errors)

    @torch.no_grad()
    def keep_members(self, members: torch.Tensor, errors: torch.Tensor | None = None) -> "DynamicsEnsemble":
        """Keep only ``members`` (indices, in that order): every per-member parameter is sliced, ``num_models`` becomes
        their count and ``config["elites"]`` records what was kept (the trained count, the members, their errors)."""
        members = torch.as_tensor(members, dtype=torch.long).reshape(-1)
        trained = self.num_members
        for mod in self.modules():
            if hasattr(mod, "num_members") and mod is not self:
                mod.num_members = len(members)
        for p in self.parameters():
            p.data = p.data.index_select(0, members.to(p.device))
        self.num_members = len(members)
        self.config.update(num_models=len(members), num_elites=None, elites={
            "trained": trained, "kept": members.tolist(),
            **({"val_mse": [float(errors[i]) for i in members]} if errors is not None else {})})
        return self

    def _inputs_and_targets(self, batch: TensorDictBase):
        """``(inputs, state-residual targets [K, B, D], reward targets [K, B, 1] or None)``, normalised, of a batch ``[K, B]``
        or ``[B]`` (the same pairs for every member)."""
        obs = batch.get("observation")
        nobs = batch.get(("next", "observation"))
        x = self._inputs(obs, batch.get("action"))
        target = ((nobs - obs) - self.delta_mean) / self.delta_std
        if target.dim() == 2:
            target = target.unsqueeze(0).expand(self.num_members, *target.shape)
        r = None
        if self.reward_net is not None:
            r = (batch.get(("next", "reward")) - self.reward_mean) / self.reward_std
            if r.dim() == 2:
                r = r.unsqueeze(0).expand(self.num_members, *r.shape)
        return x, target, r

    def loss(self, batch: TensorDictBase) -> torch.Tensor:
        """Per-member training loss, ``[K]``; batch ``[K, B]`` or ``[B]``."""
        x, target, r = self._inputs_and_targets(batch)
        loss = self._member_loss(self.dynamics(x), target)
        if r is not None:
            loss = loss + self._member_loss(self.reward_net(x), r, "reward")
        return loss


# ---- the members as one network: each layer one batched matmul over the members (EnsembleLinear, EnsembleMLP) ------------

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
