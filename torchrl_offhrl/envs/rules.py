"""Offline rules: the P-MDP's settings computed from the dataset and the fitted models, with no simulator.

Our users have a dataset and no simulator, so nothing here reads a real
environment. Every rule reads the *held-out* episodes of the models' own
train/validation split (the episodes the ensemble and the CVAE never trained
on, :meth:`~torchrl_offhrl.data.OfflineDataset.split` with the fits'
``val_ratio`` and seed): real transitions the models have not seen are the
only offline evidence of where the models can be trusted.

The rules (each function's docstring gives its reasoning):

* :func:`threshold_rule`: the pessimism threshold, the largest discrepancy
  the members show on held-out transitions;
* :func:`penalty_rule`: the pessimistic termination's penalty, one standard
  deviation of the data's discounted returns-to-go (plus whatever makes
  ending an episode unattractive when returns can be negative);
* :func:`horizon_rule`: the model episode's length and where episodes
  start: how many steps the members can roll a held-out trajectory forward
  on its logged actions before their error passes a tolerance;
* :func:`latent_bound_rule`: the latent box, the box holding 99% of the
  latents the CVAE's decoder was trained on (posterior draws of held-out pairs);
* the reward scale is :func:`~torchrl_offhrl.recipes.config.auto_reward_scale`
  (1 / std of the returns-to-go), resolved with the other recipe settings.

Beside the settings, the report shows the models' held-out quality
(:func:`~torchrl_offhrl.models.ensemble_quality`: the ensemble mean's error
next to the members' spread) and whether the decoder uses its latent
(:func:`~torchrl_offhrl.models.decoder_sensitivity`), the two things that
make a P-MDP useless whatever its settings.

:func:`offline_rules` runs them all and returns an :class:`OfflineRules`,
whose :meth:`~OfflineRules.summary` and :meth:`~OfflineRules.plot` are the
run's calibration report.
"""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import torch

from ..models.cvae import encode_in_chunks
from ..models.quality import decoder_sensitivity, ensemble_quality
from .pessimistic import dataset_discrepancy

__all__ = ["OfflineRules", "horizon_rule", "latent_bound_rule", "offline_rules", "open_loop_errors", "penalty_rule", "threshold_rule"]

#: normalised RMS state error above which an open-loop model prediction no longer counts as tracking the truth
#: (see :func:`horizon_rule`)
HORIZON_TOLERANCE = 0.5
#: shortest and longest model episodes the horizon rule returns
MIN_HORIZON, MAX_HORIZON = 5, 1000
#: a decoder whose action moves by less than this share of the data's action spread over the latent box is reported as
#: collapsed (see :func:`~torchrl_offhrl.models.decoder_sensitivity`)
COLLAPSED_DECODER_SHARE = 0.1


@torch.no_grad()
def threshold_rule(ensemble, held_out, kind: str = "variance", disc: torch.Tensor | None = None) -> tuple[float, dict]:
    """The pessimism threshold: the largest discrepancy of the members on held-out transitions.

    Reasoning. Every held-out pair is a real transition the members never
    trained on, so their disagreement there is what disagreement looks like
    where the model is being asked something the data can answer. A pair
    whose disagreement is larger than any of them is outside everything the
    models were checked against, and the P-MDP should stop there. A lower
    threshold (a quantile of the *training* pairs' discrepancy, as the paper's
    tables use) ends model episodes on ordinary in-distribution states: on
    hopper-medium-expert the paper's ``0.08 x max`` is the data's 99th
    percentile and ended every untrained model episode after ~110 steps.

    ``disc``: the held-out pairs' discrepancies when the caller has them
    (:func:`~torchrl_offhrl.envs.pessimistic.dataset_discrepancy`), else computed here.

    Returns ``(threshold, info)``; ``info`` has the held-out and training
    discrepancies' quantiles, and how the ensemble mean's held-out error
    compares with the discrepancy (``error_over_discrepancy``: the median of
    their ratio, in the discrepancy's units; about 1 when the members'
    disagreement measures their error).
    """
    disc = (dataset_discrepancy(ensemble, held_out, kind) if disc is None else disc).double()
    if disc.numel() == 0:
        raise ValueError("threshold_rule: the held-out split is empty; the rules need held-out episodes (val_ratio > 0)")
    threshold = float(disc.max())
    err = _held_out_error(ensemble, held_out, kind)
    ratio = (err / disc.clamp_min(1e-12)).median()
    info = {
        "held_out_pairs": int(disc.numel()),
        "held_out_median": float(disc.median()),
        "held_out_q999": float(torch.quantile(disc, 0.999)) if disc.numel() <= 16_000_000 else None,
        "held_out_max": threshold,
        "error_over_discrepancy": float(ratio),
    }
    return threshold, info


@torch.no_grad()
def _held_out_error(ensemble, data, kind: str, chunk: int = 65536) -> torch.Tensor:
    """The ensemble mean's squared error on ``data``'s normalised residuals (``variance``'s units), its root for ``std``; ``[N]``."""
    device = next(ensemble.parameters()).device
    obs, act, nxt = data.data.get("observation"), data.data.get("action"), data.data.get(("next", "observation"))
    out = []
    for s in range(0, obs.shape[0], chunk):
        o, a, n = obs[s : s + chunk].to(device), act[s : s + chunk].to(device), nxt[s : s + chunk].to(device)
        delta = ensemble.predict(o, a)["delta"]  # [K, N, D] normalised residuals
        target = ((n - o) - ensemble.delta_mean) / ensemble.delta_std
        sq = (delta.mean(0) - target).pow(2).sum(-1)
        out.append((sq.sqrt() if kind in ("std", "max_pairwise") else sq).double().cpu())
    return torch.cat(out)


def penalty_rule(data, gamma: float = 0.99) -> tuple[float, dict]:
    """The reward of a pessimistic termination is ``-penalty``, with ``penalty = std(G) + max(0, -min(G))``.

    ``G`` are the data's discounted returns-to-go (``gamma``: the agent's).
    Reasoning. Ending an episode already costs the agent the value of the
    state it would have reached; the penalty adds one standard deviation of
    the values the data reaches (the spread between a good and a poor state of
    the data), so a termination is worse than any ordinary outcome. Where
    returns-to-go can be negative (a task whose rewards are costs), ending an
    episode would be a way out of them; the second term removes that. With the
    ``auto`` reward scale (rewards divided by ``std(G)``) the penalty is
    1 + that term in the agent's units whatever the dataset.
    """
    g = data.returns_to_go(gamma)
    if g.numel() < 2:
        raise ValueError("penalty_rule: the dataset has fewer than two transitions")
    std, low = float(g.std()), float(g.min())
    if not std > 0:
        raise ValueError("penalty_rule: the dataset's returns-to-go have zero spread; set model_env.pessimism.penalty")
    penalty = std + max(0.0, -low)
    return penalty, {"returns_to_go_std": std, "returns_to_go_min": low, "gamma": float(gamma)}


def _segments(data, length: int, max_starts: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Start indices of held-out windows and how many logged steps follow each one inside its episode (``<= length``)."""
    ep = data.data.get("episode")
    n = ep.shape[0]
    ends = torch.ones(n, dtype=torch.bool)
    ends[:-1] = ep[1:] != ep[:-1]
    last = torch.flip(torch.cummin(torch.flip(torch.where(ends, torch.arange(n), torch.full((n,), n, dtype=torch.long)), (0,)), 0).values, (0,))
    remaining = (last - torch.arange(n) + 1).clamp(max=length)  # transitions from i to the end of its episode
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(n, generator=g)[:max_starts]
    return idx, remaining[idx]


@torch.no_grad()
def open_loop_errors(ensemble, held_out, length: int = 200, max_starts: int = 256, seed: int = 0) -> torch.Tensor:
    """Each member's open-loop error on held-out trajectories: ``[length]``, the median normalised RMS state error ``h`` steps ahead.

    From ``max_starts`` random held-out states every member rolls the model
    forward on the *logged* actions, its own predictions fed back, and at step
    ``h`` the prediction is compared with the logged state ``h`` steps later:
    ``sqrt(mean_d ((pred_d - true_d) / std_d)^2)`` with the data's per-dimension
    state std. Windows shorter than ``h`` (the episode ended) leave step ``h``;
    a step no window reaches is NaN. One matmul per layer for all members and
    windows (vectorised).
    """
    device = next(ensemble.parameters()).device
    idx, remaining = _segments(held_out, length, max_starts, seed)
    obs = held_out.data.get("observation").to(device)
    act = held_out.data.get("action").to(device)
    nxt = held_out.data.get(("next", "observation")).to(device)
    std = obs.std(0).clamp_min(1e-6)
    k, m = ensemble.num_members, idx.numel()
    state = obs[idx].unsqueeze(0).expand(k, m, -1).reshape(k * m, -1)  # member-major: row j*m + i is member j's window i
    member = torch.arange(k, device=device).repeat_interleave(m)
    out = torch.full((length,), float("nan"), dtype=torch.float64)
    for h in range(length):
        live = (remaining > h).to(device)
        if not bool(live.any()):
            break
        step = (idx.to(device) + h).clamp(max=obs.shape[0] - 1)
        a = act[step].repeat(k, 1)
        pred = ensemble.predict(state, a)["next_observation"]  # [K, K*m, D]: every member on every row
        state = pred[member, torch.arange(k * m, device=device)]  # each row keeps its own member's prediction
        state = torch.nan_to_num(state, nan=0.0, posinf=1e6, neginf=-1e6)
        err = ((state - nxt[step].repeat(k, 1)) / std).pow(2).mean(-1).sqrt()
        out[h] = float(err[live.repeat(k)].median())
    return out


def horizon_rule(ensemble, held_out, episode_length: float, tolerance: float = HORIZON_TOLERANCE, length: int = 200,
                 max_starts: int = 256, seed: int = 0) -> tuple[int, str, dict]:
    """The model episode's length and start states: ``(horizon, reset_states, info)``.

    Reasoning. A model episode is only worth training on while the model
    still tracks what the real system would do. Rolled open loop on the
    logged actions of held-out episodes (:func:`open_loop_errors`), the
    members' median error grows with the steps; the horizon is the last step
    before it passes ``tolerance`` (0.5: the prediction is off by half the
    data's spread of each state dimension, halfway to an uninformed guess,
    which is ``sqrt(2)`` for a state drawn at random from the data). When the
    model tracks the data for as long as the data's episodes last (``horizon``
    at least their median length ``episode_length``), episodes run the data's
    full length from its start states (``"initial"``: the paper's P-MDP);
    otherwise they are ``horizon`` steps long and branch from any dataset
    state (``"any"``: MOPO's short branched rollouts), so every part of the
    data is reached without trusting the model for longer than it holds.

    The horizon is kept within ``[MIN_HORIZON, MAX_HORIZON]``; a curve that
    never passes the tolerance within ``length`` steps gives the data's
    episode length.
    """
    curve = open_loop_errors(ensemble, held_out, length=length, max_starts=max_starts, seed=seed)
    over = torch.nonzero(curve > tolerance).flatten()
    known = torch.isfinite(curve)
    if over.numel():
        horizon = int(over[0])  # steps 1..over[0] stayed within the tolerance (curve[h] is the error h + 1 steps ahead)
    elif bool(known.all()):
        horizon = max(length, int(round(episode_length)))
    else:  # windows ran out (short episodes) before the error passed the tolerance: the model holds for whole episodes
        horizon = max(int(known.sum()), int(round(episode_length)))
    horizon = int(min(max(horizon, MIN_HORIZON), MAX_HORIZON))
    full = horizon >= episode_length
    info = {"tolerance": float(tolerance), "episode_length_median": float(episode_length),
            "error_at": {str(h): (None if not math.isfinite(float(curve[h - 1])) else round(float(curve[h - 1]), 4))
                         for h in (1, 5, 10, 25, 50, 100, 200) if h <= curve.numel()},
            "curve": [None if not math.isfinite(float(v)) else float(v) for v in curve]}
    return horizon, ("initial" if full else "any"), info


@torch.no_grad()
def latent_bound_rule(cvae, held_out, quantile: float = 0.99, seed: int = 0, chunk: int = 65536) -> tuple[float, dict]:
    """The latent box's half-width: the ``quantile`` of ``|z|`` over posterior draws of held-out pairs (every dimension pooled).

    Reasoning. The decoder was trained on latents drawn from the encoder's
    posterior ``q(z | s, a)`` of the data's pairs; inside the box that holds
    99% of such draws it maps latents to actions like the data's, outside it
    extrapolates. Held-out pairs, drawn once each with a fixed seed, stand for
    the data without the pairs the encoder fitted.
    """
    device = next(cvae.parameters()).device
    g = torch.Generator(device="cpu").manual_seed(seed)
    zs, mus = [], []
    for _, _, mean, std in encode_in_chunks(cvae, held_out.data, device, chunk):
        eps = torch.randn(mean.shape, generator=g).to(device)
        zs.append((mean + std * eps).abs().flatten().double().cpu())
        mus.append(mean.abs().flatten().double().cpu())
    z, mu = torch.cat(zs), torch.cat(mus)
    if z.numel() == 0:
        raise ValueError("latent_bound_rule: the held-out split is empty")
    bound = float(_quantile(z, quantile))
    return bound, {"quantile": quantile, "posterior_mean_abs_q99": float(_quantile(mu, 0.99)), "draws": int(z.numel()),
                   "z_abs": z}


def _quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    if x.numel() <= 16_000_000:
        return torch.quantile(x, q)
    return x.kthvalue(max(1, int(round(q * x.numel())))).values


@dataclasses.dataclass
class OfflineRules:
    """The settings the offline rules chose for one dataset and its models, with the evidence behind each (the calibration report)."""

    threshold: float
    penalty: float
    horizon: int
    reset_states: str
    latent_bound: float | None
    discrepancy: str
    info: dict
    held_out_discrepancy: torch.Tensor = dataclasses.field(repr=False, default=None)
    train_discrepancy: torch.Tensor = dataclasses.field(repr=False, default=None)

    def settings(self) -> dict:
        """The model env's settings (``make_model_env``'s ``env`` config keys)."""
        out = {"threshold": self.threshold, "penalty": self.penalty, "horizon": self.horizon, "reset_states": self.reset_states}
        if self.latent_bound is not None:
            out["latent_bound"] = self.latent_bound
        return out

    def as_dict(self) -> dict:
        info = {k: ({kk: vv for kk, vv in v.items() if kk not in ("curve", "z_abs")} if isinstance(v, dict) else v) for k, v in self.info.items()}
        return {**self.settings(), "discrepancy": self.discrepancy, "rules": "auto", "evidence": info}

    def summary(self) -> str:
        t, h, p = self.info["threshold"], self.info["horizon"], self.info["penalty"]
        train_above = None
        if self.train_discrepancy is not None and self.train_discrepancy.numel():
            train_above = float((self.train_discrepancy > self.threshold).double().mean())
        # the rules' values a run sets otherwise (recipes.config.rules_not_used): stated, marked as not this run's
        not_used = self.info.get("not_used") or {}

        def mark(*keys: str) -> str:
            why = "; ".join(dict.fromkeys(not_used[k] for k in keys if k in not_used))
            return f" [not used by this run: {why}]" if why else ""

        lines = [
            "calibration report (offline rules: the dataset and the fitted models only, no simulator)",
            f"  pessimism threshold {self.threshold:.4g} ({self.discrepancy}): the largest held-out discrepancy of {t['held_out_pairs']} pairs "
            f"(median {t['held_out_median']:.3g}); training pairs above it: "
            + ("n/a" if train_above is None else f"{100 * train_above:.3f}%")
            + f"; held-out error / discrepancy (median) {t['error_over_discrepancy']:.2f}" + mark("pessimism"),
            f"  penalty {self.penalty:.4g}: std of the returns-to-go ({p['returns_to_go_std']:.4g}) + max(0, -min) "
            f"({max(0.0, -p['returns_to_go_min']):.4g})" + mark("pessimism"),
            f"  model episodes {self.horizon} steps from {'the data start states' if self.reset_states == 'initial' else 'any dataset state'}: "
            f"open-loop held-out error within {h['tolerance']} for {self.horizon} steps "
            f"(median error at 1/10/50/100 steps: {', '.join(str(h['error_at'].get(str(s))) for s in (1, 10, 50, 100))}; data episodes' "
            f"median length {h['episode_length_median']:.0f})" + mark("horizon", "reset_states"),
        ]
        q = self.info.get("models")
        if q is not None:
            reward = "" if q["reward_error"] is None else f"; reward error {q['reward_error']:.3g} (spread {q['reward_spread']:.3g})"
            lines.append(f"  models on {q['pairs']} held-out pairs: the ensemble mean's one-step error {q['state_error']:.3g} state-change stds, "
                         f"the members' spread {q['state_spread']:.3g} (error / spread {q['error_over_spread']:.2f}){reward}")
        d = self.info.get("decoder")
        if d is not None:
            collapsed = d["corner_share"] < COLLAPSED_DECODER_SHARE
            lines.append(f"  decoder: over the latent box its action moves by {100 * d['corner_share']:.0f}% of the data's action spread "
                         f"({100 * d['prior_share']:.0f}% over N(0, I))"
                         + (f"; below {100 * COLLAPSED_DECODER_SHARE:.0f}%, the decoder ignores its latent (posterior collapse: lower "
                            "cvae.kl_weight) and no latent policy can act differently from its mean action" if collapsed else ""))
        if self.latent_bound is not None:
            lb = self.info["latent_bound"]
            lines.append(f"  latent box +-{self.latent_bound:.3g}: {100 * lb['quantile']:.0f}% of the decoder's posterior draws on held-out pairs "
                         f"(|posterior mean| q99 {lb['posterior_mean_abs_q99']:.3g})" + mark("latent_bound"))
        origin = self.info.get("latent_origin")
        if origin is not None:  # recipes.pipeline.apply_latent_origin, model_env.latent_origin=best
            lines.append(f"  latent origin: the behaviour of the {origin['episodes_kept']} highest-return of {origin['episodes']} episodes "
                         f"({origin['transitions_kept']} transitions, {100 * origin['share']:g}% asked; mean return {origin['return_kept_mean']:.4g} "
                         f"against {origin['return_mean']:.4g} over all): the untrained agent, and a fallback of the guard with the percentile BC of the same episodes")
        return "\n".join(lines)

    def plot(self, path: str | os.PathLike) -> Path:
        """The report as a figure (PNG): discrepancies and threshold, open-loop error and horizon, latent draws and box."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import numpy as np

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
        ax = axes[0]
        held = self.held_out_discrepancy.double().clamp_min(1e-12).numpy() if self.held_out_discrepancy is not None else np.array([self.threshold])
        tr = self.train_discrepancy.double().clamp_min(1e-12).numpy() if self.train_discrepancy is not None else held
        lo, hi = min(held.min(), tr.min()), max(held.max(), tr.max(), self.threshold) * 1.05
        edges = np.logspace(np.log10(lo), np.log10(hi), 80)
        ax.hist(tr, bins=edges, alpha=0.6, density=True, label="training pairs")
        ax.hist(held, bins=edges, alpha=0.6, density=True, label="held-out pairs")
        ax.axvline(self.threshold, color="tab:red", lw=2, label=f"threshold {self.threshold:.3g}")
        ax.set_xscale("log")
        ax.set_xlabel(f"discrepancy ({self.discrepancy})")
        ax.set_title("pessimism threshold")
        ax.legend(fontsize=7)
        ax = axes[1]
        curve = np.array([np.nan if v is None else v for v in self.info["horizon"]["curve"]], dtype=float)
        ax.plot(np.arange(1, curve.size + 1), curve, color="tab:blue")
        ax.axhline(self.info["horizon"]["tolerance"], color="tab:red", ls="--", label="tolerance")
        ax.axvline(min(self.horizon, curve.size), color="tab:green", label=f"horizon {self.horizon} ({self.reset_states})")
        ax.set_xlabel("steps rolled open loop on held-out actions")
        ax.set_ylabel("median normalised RMS error")
        ax.set_title("model episode length")
        ax.legend(fontsize=7)
        ax = axes[2]
        lb = self.info.get("latent_bound")
        if lb is not None and "z_abs" in lb:
            ax.hist(lb["z_abs"].numpy(), bins=80, color="tab:purple", alpha=0.8)
            ax.axvline(self.latent_bound, color="tab:red", lw=2, label=f"box +-{self.latent_bound:.3g}")
            ax.set_xlabel("|z| of posterior draws (held-out pairs)")
            ax.legend(fontsize=7)
        ax.set_title("latent box")
        fig.tight_layout()
        fig.savefig(path, dpi=90)
        plt.close(fig)
        return path


def median_episode_length(data) -> float:
    """Median length of the data's episodes (the complete ones when the data marks those cut short by its collection)."""
    ep = data.data.get("episode")
    ids, counts = torch.unique_consecutive(ep, return_counts=True)
    unfinished = data.metadata.get("unfinished_episodes") or []
    if unfinished and ids.numel() > len(unfinished):
        counts = counts[~torch.isin(ids, torch.as_tensor(unfinished, dtype=ids.dtype))]
    return float(counts.double().median())


def offline_rules(ensemble, data, cvae=None, val_ratio: float = 0.1, split_seed: int = 0, discrepancy: str = "variance",
                  gamma: float = 0.99, tolerance: float = HORIZON_TOLERANCE) -> OfflineRules:
    """Every offline rule on ``data`` and its fitted models: the calibration of a run's P-MDP (see the module's docstring).

    ``val_ratio`` and ``split_seed`` must be those the models were fitted with
    (the recipes pass them), so that the held-out episodes are the ones the
    models never saw.

    Examples:
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> from torchrl_offhrl.models import DynamicsEnsemble
        >>> data = make_toy_dataset(num_episodes=20, episode_length=30)
        >>> ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(16,)).fit(data, max_epochs=2, progress=False)
        >>> rules = offline_rules(ens, data)
        >>> rules.threshold > 0 and rules.penalty > 0 and rules.reset_states in ("initial", "any")
        True
    """
    train, held_out = data.split(val_ratio, seed=split_seed)
    held_disc = dataset_discrepancy(ensemble, held_out, discrepancy)
    threshold, t_info = threshold_rule(ensemble, held_out, discrepancy, disc=held_disc)
    penalty, p_info = penalty_rule(data, gamma)
    horizon, reset_states, h_info = horizon_rule(ensemble, held_out, median_episode_length(data), tolerance=tolerance, seed=split_seed)
    info = {"threshold": t_info, "penalty": p_info, "horizon": h_info, "models": ensemble_quality(ensemble, held_out)}
    bound = None
    if cvae is not None:
        bound, info["latent_bound"] = latent_bound_rule(cvae, held_out, seed=split_seed)
        info["decoder"] = decoder_sensitivity(cvae, held_out, bound, seed=split_seed)
    return OfflineRules(threshold=threshold, penalty=penalty, horizon=horizon, reset_states=reset_states, latent_bound=bound,
                        discrepancy=discrepancy, info=info, held_out_discrepancy=held_disc,
                        train_discrepancy=dataset_discrepancy(ensemble, train, discrepancy))
