"""The pessimistic MDP (P-MDP) as a batched TorchRL environment, and where its ensemble stops being trusted (the
discrepancy threshold calibrated on the dataset: :func:`calibrate_threshold`, :class:`CalibrationReport`)."""
from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from ..models.dynamics import DISCREPANCIES
from .tasks import termination_fn_for

__all__ = ["calibrate_threshold", "CalibrationReport", "dataset_discrepancy", "PessimisticModelEnv"]

log = logging.getLogger(__name__)
_MEMBER_MODES = ("episode", "step", "mean")


class PessimisticModelEnv(EnvBase):
    """A learned, pessimistic model of an environment, stepped in batch.

    At reset, each environment draws a start state from the dataset and one
    ensemble member ``k`` that supplies its next states and rewards for the
    whole episode (the paper; ``member_mode="step"`` redraws ``k`` each step,
    ``"mean"`` averages the members). Every step also measures the members'
    disagreement on ``(s, a)``; above ``threshold`` the episode ends with
    ``terminated=True`` and reward ``-penalty``. A prediction that is NaN/inf
    or lands more than ``bounds_margin`` data ranges outside the dataset's
    state bounds is *unknown*: it terminates the same way and the state is
    kept at its last known value, so no NaN ever leaves the env. The task's
    own termination (e.g. Hopper's health check) applies on top, and
    episodes are truncated after ``horizon`` steps.

    Why :class:`~torchrl.envs.EnvBase` and not TorchRL's
    ``ModelBasedEnvBase``: that base steps one ``world_model`` module on the
    tensordict and leaves termination, rewards and resets to the subclass,
    while this env needs every member's prediction at once (the discrepancy),
    one member per episode kept in the state, dataset start states and the
    penalty; none of which ``ModelBasedEnvBase`` provides, so the base would
    add a module call convention and nothing else.

    Args:
        ensemble (DynamicsEnsemble): a fitted ensemble (with a learned
            reward or a ``reward_fn``).
        data (OfflineDataset): supplies start states, state bounds, the
            action box, the env id and (when ``threshold`` is None) the
            calibration pairs.
        threshold (float, optional): discrepancy above which a step is
            penalised. ``None`` calibrates it on the dataset: ``quantile`` of
            the pairs' discrepancies (0.99 by default), or ``fraction`` times
            their maximum when ``fraction`` is given.
        penalty (float): the reward on a pessimistic termination is
            ``-penalty`` (paper: 20 to 50).
        reward_penalty (float): MOPO's soft pessimism (Yu et al., 2020): every
            step that is not terminated pessimistically pays
            ``reward_penalty * discrepancy`` out of its reward (default 0: the
            paper's P-MDP, which only ends episodes above the threshold).
            Measured on the demo in ``docs/results/demo_robustness_notes.md``.
        discrepancy (str): ``"variance"`` (the paper), ``"std"`` (its square
            root: in the state's units, the scale of MOPO's uncertainty),
            ``"max_pairwise"`` (MOReL) or ``"aleatoric"`` (MOPO's own penalty:
            the largest norm of the members' predicted standard deviations,
            for an ensemble fitted with ``loss="nll"``; with
            ``reward_penalty`` it is MOPO's ``r - lambda u(s, a)``).
        quantile / fraction: calibration, see ``threshold``.
        termination_fn: ``"auto"`` (by the dataset's env id), a callable
            ``f(next_obs) -> bool[...]``, or ``None`` (never).
        horizon (int): truncation after this many steps (default 1000).
        member_mode (str): ``"episode"``, ``"step"`` or ``"mean"``.
        sample (bool): a step draws the next state and reward from the
            member's Gaussian (its mean plus its predicted standard deviation
            times standard normal noise, from the env's generator), as MOPO's
            code steps its model; default False: the member's mean. Needs an
            ensemble that predicts standard deviations (``loss="nll"``).
        member_draw (str): how an episode's member is chosen at reset:
            ``"random"`` (uniformly, the default) or ``"cyclic"`` (env ``i``
            of the batch always uses member ``i % K``: an evaluation that
            gives every member the same number of episodes, so each member's
            mean return, and the worst of them, can be read off).
        reset_states (str): ``"initial"`` (episode starts in the data) or
            ``"any"`` (any dataset state).
        bounds_margin (float): how many data ranges outside
            ``[obs_min, obs_max]`` a state may go before it counts as unknown.
        batch_size: e.g. ``[1024]`` parallel model rollouts; ``[]`` for one.
        device: where the ensemble and the rollouts live.
        seed (int, optional): seeds start states and member draws.

    The env writes, besides TorchRL's standard keys, ``discrepancy``
    (``[*B, 1]``), ``penalized`` (pessimistic termination, ``[*B, 1]``),
    ``model_member`` (the member that made the step; its value is meaningless
    with ``member_mode="mean"``) and ``model_step`` (``[*B, 1]``, int64).

    Examples:
        >>> import torch
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> from torchrl_offhrl.models import DynamicsEnsemble
        >>> from torchrl_offhrl.envs import PessimisticModelEnv
        >>> data = make_toy_dataset(num_episodes=10, episode_length=20)
        >>> ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(32, 32))
        >>> ens = ens.fit(data, max_epochs=3, progress=False)
        >>> env = PessimisticModelEnv(ens, data, penalty=20.0, horizon=50, batch_size=[16], seed=0)
        >>> check_env_specs(env)
        >>> td = env.rollout(10, break_when_any_done=False)
        >>> td.batch_size
        torch.Size([16, 10])
        >>> bool(torch.isfinite(td["next", "observation"]).all())
        True
    """

    #: whether the ensemble must predict the reward (a learned reward or a ``reward_fn``); subclasses that compute
    #: their rewards from the predicted states set it to False
    needs_model_reward: bool = True

    def __init__(
        self,
        ensemble,
        data,
        threshold: float | None = None,
        penalty: float = 20.0,
        reward_penalty: float = 0.0,
        discrepancy: str = "variance",
        quantile: float | None = 0.99,
        fraction: float | None = None,
        termination_fn: str | Callable | None = "auto",
        horizon: int = 1000,
        member_mode: str = "episode",
        sample: bool = False,
        reset_states: str = "initial",
        member_draw: str = "random",
        bounds_margin: float = 1.0,
        batch_size: Sequence[int] | torch.Size | None = None,
        device: str | torch.device = "cpu",
        seed: int | None = None,
    ):
        batch_size = torch.Size([] if batch_size is None else batch_size)
        super().__init__(device=device, batch_size=batch_size)
        if discrepancy not in DISCREPANCIES:
            raise ValueError(f"discrepancy must be one of {DISCREPANCIES}, got {discrepancy!r}.")
        if discrepancy == "aleatoric" and getattr(ensemble, "loss_type", "nll") != "nll":
            raise ValueError(f"discrepancy='aleatoric' (MOPO's penalty) reads the members' predicted standard deviations, and "
                             f"this ensemble was fitted with loss={ensemble.loss_type!r}, which predicts none: fit it with "
                             "loss='nll' (ensemble.loss=nll) or choose another discrepancy.")
        if member_mode not in _MEMBER_MODES:
            raise ValueError(f"member_mode must be one of {_MEMBER_MODES}, got {member_mode!r}.")
        if sample and (getattr(ensemble, "loss_type", "nll") != "nll" or member_mode == "mean"):
            raise ValueError("sample=True draws from a member's Gaussian: it needs an ensemble fitted with loss='nll' "
                             "(ensemble.loss=nll), which predicts standard deviations, and a member per step or episode (not "
                             "member_mode='mean')")
        if member_draw not in ("random", "cyclic"):
            raise ValueError(f"member_draw must be 'random' or 'cyclic', got {member_draw!r}.")
        if reset_states not in ("initial", "any"):
            raise ValueError(f"reset_states must be 'initial' or 'any', got {reset_states!r}.")
        if data.observation_dim != ensemble.observation_dim or data.action_dim != ensemble.action_dim:
            raise ValueError(
                f"the dataset has obs/action dims ({data.observation_dim}, {data.action_dim}) but the "
                f"ensemble was built for ({ensemble.observation_dim}, {ensemble.action_dim})."
            )
        if self.needs_model_reward and ensemble.reward_fn is None and ensemble.reward_net is None:
            raise ValueError("the ensemble predicts no reward: build it with learn_reward=True or a reward_fn.")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}.")
        if not reward_penalty >= 0:
            raise ValueError(f"reward_penalty must be >= 0 (a cost per unit of discrepancy), got {reward_penalty}.")
        self.ensemble = ensemble.to(self.device).eval()
        self.discrepancy_kind = discrepancy
        self.penalty = float(penalty)
        self.reward_penalty = float(reward_penalty)
        #: on a CPU the ensemble predicts at most this many envs at a time (DynamicsEnsemble.predict; None: all at once); a GPU
        #: prefers one batch and always gets it
        self.predict_chunk: int | None = 1024
        self.horizon = int(horizon)
        self.member_mode = member_mode
        self.sample = bool(sample)
        self.member_draw = member_draw
        self.num_members = ensemble.num_members

        self._data = data
        if threshold is None:
            self._calibration: CalibrationReport | None = calibrate_threshold(
                self.ensemble, data, discrepancy, quantile=quantile, fraction=fraction
            )
            self.threshold = self._calibration.threshold
        else:  # the report is computed on first use only: no start-up cost
            self._calibration = None
            self.threshold = float(threshold)

        if termination_fn == "auto":
            termination_fn = termination_fn_for(data.env_id)
        self.termination_fn = termination_fn

        stats = data.stats()
        span = (stats.obs_max - stats.obs_min).clamp_min(1e-6)
        self.register_buffer("obs_low", (stats.obs_min - bounds_margin * span).to(self.device))
        self.register_buffer("obs_high", (stats.obs_max + bounds_margin * span).to(self.device))
        starts = data.initial_observations() if reset_states == "initial" else data.data.get("observation")
        self.register_buffer("start_states", starts.float().to(self.device))

        # draws happen on the CPU and move to the env's device, so the env
        # keeps working after env.to(other_device)
        self._rng = torch.Generator()
        self._rng.manual_seed(int(torch.empty((), dtype=torch.int64).random_().item()) if seed is None else seed)
        self._make_specs(data)

    # ------------------------------------------------------------------ specs
    def _make_specs(self, data) -> None:
        B = self.batch_size
        D = data.observation_dim
        obs_spec = Composite(
            observation=Unbounded((*B, D), dtype=torch.float32, device=self.device),
            discrepancy=Unbounded((*B, 1), dtype=torch.float32, device=self.device),
            penalized=Categorical(2, (*B, 1), dtype=torch.bool, device=self.device),
            model_member=Bounded(0, self.num_members - 1, (*B, 1), dtype=torch.int64, device=self.device),
            model_step=Bounded(0, self.horizon, (*B, 1), dtype=torch.int64, device=self.device),
            shape=B,
            device=self.device,
        )
        self.observation_spec = obs_spec
        self.state_spec = Composite(
            model_member=obs_spec["model_member"].clone(),
            model_step=obs_spec["model_step"].clone(),
            shape=B,
            device=self.device,
        )
        low = data.action_low.to(self.device).expand(*B, data.action_dim)
        high = data.action_high.to(self.device).expand(*B, data.action_dim)
        self.action_spec = Bounded(low, high, (*B, data.action_dim), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded((*B, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            {k: Categorical(2, (*B, 1), dtype=torch.bool, device=self.device) for k in ("done", "terminated", "truncated")},
            shape=B,
            device=self.device,
        )

    # ------------------------------------------------------------------ reset
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        B = self.batch_size
        n = max(1, B.numel())
        idx = torch.randint(0, self.start_states.shape[0], (n,), generator=self._rng).to(self.device)
        if self.member_draw == "cyclic":
            member = (torch.arange(n) % self.num_members).reshape(n, 1)
        else:
            member = torch.randint(0, self.num_members, (n, 1), generator=self._rng)
        member = member.to(self.device)
        out = TensorDict(
            {
                "observation": self.start_states[idx].reshape(*B, -1),
                "discrepancy": torch.zeros(*B, 1, device=self.device),
                "penalized": torch.zeros(*B, 1, dtype=torch.bool, device=self.device),
                "model_member": member.reshape(*B, 1),
                "model_step": torch.zeros(*B, 1, dtype=torch.int64, device=self.device),
                "done": torch.zeros(*B, 1, dtype=torch.bool, device=self.device),
                "terminated": torch.zeros(*B, 1, dtype=torch.bool, device=self.device),
                "truncated": torch.zeros(*B, 1, dtype=torch.bool, device=self.device),
            },
            batch_size=B,
            device=self.device,
        )
        # Envs that are not reset keep their values: EnvBase.reset merges
        # this output into the input with the "_reset" mask.
        return out

    # ------------------------------------------------------------------- step
    @torch.no_grad()
    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        B = self.batch_size
        D = self.ensemble.observation_dim
        obs = tensordict.get("observation").reshape(-1, D)
        act = tensordict.get("action").reshape(obs.shape[0], -1)
        member = tensordict.get("model_member", None)
        step = tensordict.get("model_step", None)
        if member is None or step is None:
            raise KeyError(
                "PessimisticModelEnv.step needs 'model_member' and 'model_step' in the input "
                "tensordict; start from env.reset() (or env.fake_tensordict())."
            )
        member = member.reshape(-1)
        n = obs.shape[0]
        chunk = self.predict_chunk if obs.device.type == "cpu" else None
        # the chunk argument only where it chunks: an ensemble (or a stand-in) with predict(obs, act) still serves smaller batches
        pred = self.ensemble.predict(obs, act, chunk=chunk) if chunk is not None and n > chunk else self.ensemble.predict(obs, act)
        disc = self.ensemble.discrepancy_of(pred["delta"], self.discrepancy_kind, pred.get("std"))
        rewards = pred["reward"]
        if rewards is None:  # a subclass that computes its own rewards (needs_model_reward = False)
            rewards = torch.zeros(self.num_members, n, device=self.device, dtype=obs.dtype)
        if self.member_mode == "mean":
            next_obs = pred["next_observation"].mean(0)
            reward = rewards.mean(0)
        else:
            if self.member_mode == "step":
                member = torch.randint(0, self.num_members, (n,), generator=self._rng).to(self.device)
            rows = torch.arange(n, device=self.device)
            next_obs = pred["next_observation"][member, rows]
            reward = rewards[member, rows]
            if self.sample:  # MOPO's step: the member's mean plus its predicted std times standard normal noise
                std = pred["std"][member, rows]  # [n, obs_dim (+ 1: the reward's, when the ensemble learns the reward)]
                noise = torch.randn(std.shape, generator=self._rng, dtype=std.dtype).to(self.device) * std
                next_obs = next_obs + noise[:, : next_obs.shape[-1]]
                if std.shape[-1] > next_obs.shape[-1]:
                    reward = reward + noise[:, -1]
        unknown = (
            ~torch.isfinite(next_obs).all(-1)
            | ~torch.isfinite(reward)
            | ~torch.isfinite(disc)
            | ((next_obs < self.obs_low) | (next_obs > self.obs_high)).any(-1)
        )
        penalized = unknown | (disc > self.threshold)
        next_obs = torch.where(unknown.unsqueeze(-1), obs, next_obs)
        if self.reward_penalty:
            reward = reward - self.reward_penalty * disc
        reward = torch.where(penalized, torch.full_like(reward, -self.penalty), reward)
        terminated = penalized.clone()
        if self.termination_fn is not None:
            terminated |= self.termination_fn(next_obs).reshape(n)
        step = step.reshape(-1) + 1
        truncated = (step >= self.horizon) & ~terminated
        disc = torch.where(torch.isfinite(disc), disc, torch.full_like(disc, float("inf")))
        return TensorDict(
            {
                "observation": next_obs.reshape(*B, D),
                "reward": reward.reshape(*B, 1),
                "discrepancy": disc.reshape(*B, 1),
                "penalized": penalized.reshape(*B, 1),
                "model_member": member.reshape(*B, 1) if self.member_mode == "step" else tensordict.get("model_member"),
                "model_step": step.reshape(*B, 1),
                "terminated": terminated.reshape(*B, 1),
                "truncated": truncated.reshape(*B, 1),
                "done": (terminated | truncated).reshape(*B, 1),
            },
            batch_size=B,
            device=self.device,
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._rng.manual_seed(int(seed))

    # ------------------------------------------------------------- reporting
    @property
    def calibration(self) -> CalibrationReport:
        """How the threshold sits on the dataset's discrepancies (computed once)."""
        if self._calibration is None:
            disc = dataset_discrepancy(self.ensemble, self._data, self.discrepancy_kind)
            self._calibration = CalibrationReport.from_values(disc, self.threshold, "explicit", None, self.discrepancy_kind)
        return self._calibration

    def calibration_report(self, plot_path: str | None = None) -> str:
        """A text summary of the threshold; also saves the histogram when ``plot_path`` is given."""
        text = self.calibration.summary() + f"\npenalty on violation: -{self.penalty:g}"
        if plot_path is not None:
            text += f"\nhistogram: {self.calibration.plot(plot_path)}"
        return text


# ---- where the ensemble stops being trusted: the threshold from the dataset's own discrepancies --------------------------

def dataset_discrepancy(ensemble, data, kind: str = "variance", chunk: int = 65536) -> torch.Tensor:
    """Discrepancy of ``ensemble`` on every state-action pair of ``data``, ``[N]``."""
    device = next(ensemble.parameters()).device
    obs = data.data.get("observation")
    act = data.data.get("action")
    out = []
    for start in range(0, obs.shape[0], chunk):
        o = obs[start : start + chunk].to(device)
        a = act[start : start + chunk].to(device)
        out.append(ensemble.discrepancy(o, a, kind).cpu())
    return torch.cat(out)


@dataclasses.dataclass
class CalibrationReport:
    """The threshold and how it sits on the dataset's discrepancies."""

    threshold: float
    method: str  # "quantile", "fraction" or "explicit"
    value: float | None  # the quantile or fraction used
    discrepancy: str
    num_pairs: int
    fraction_above: float
    disc_min: float
    disc_median: float
    disc_max: float
    discrepancies: torch.Tensor = dataclasses.field(repr=False)

    @classmethod
    def from_values(cls, disc: torch.Tensor, threshold: float, method: str, value, kind: str) -> "CalibrationReport":
        d = disc.double()
        return cls(
            threshold=float(threshold),
            method=method,
            value=None if value is None else float(value),
            discrepancy=kind,
            num_pairs=int(d.numel()),
            fraction_above=float((d > threshold).double().mean()),
            disc_min=float(d.min()),
            disc_median=float(d.median()),
            disc_max=float(d.max()),
            discrepancies=disc,
        )

    def summary(self) -> str:
        how = {"quantile": f"quantile {self.value}", "fraction": f"{self.value} x max", "explicit": "given"}[self.method]
        return (
            f"discrepancy ({self.discrepancy}) on {self.num_pairs} dataset pairs: "
            f"min {self.disc_min:.4g}, median {self.disc_median:.4g}, max {self.disc_max:.4g}\n"
            f"threshold {self.threshold:.4g} ({how}); pairs above it: {100 * self.fraction_above:.2f}%"
        )

    def as_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "discrepancies"}

    def plot(self, path: str | os.PathLike, bins: int = 100) -> Path:
        """Save a histogram of the dataset's discrepancies with the threshold (PNG)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        d = self.discrepancies.double().clamp_min(1e-12).numpy()
        fig, ax = plt.subplots(figsize=(6, 3.5))
        import numpy as np

        edges = np.logspace(np.log10(d.min()), np.log10(max(d.max(), self.threshold) * 1.05), bins)
        ax.hist(d, bins=edges, color="tab:blue", alpha=0.8)
        ax.axvline(self.threshold, color="tab:red", lw=2, label=f"threshold {self.threshold:.3g}")
        ax.set_xscale("log")
        ax.set_xlabel(f"discrepancy ({self.discrepancy})")
        ax.set_ylabel("dataset pairs")
        ax.set_title(f"{100 * self.fraction_above:.2f}% of {self.num_pairs} pairs above the threshold")
        ax.legend()
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
        return path


def calibrate_threshold(
    ensemble,
    data,
    kind: str = "variance",
    quantile: float | None = 0.99,
    fraction: float | None = None,
) -> CalibrationReport:
    """Threshold from the dataset's discrepancies: a quantile, or a fraction of the max.

    ``fraction`` wins when both are given (the paper's locomotion tables use
    fractions, e.g. Hopper medium 1.08, its robotics table a 99% quantile).

    Examples:
        >>> import torch
        >>> from torchrl_offhrl.data import make_toy_dataset
        >>> from torchrl_offhrl.models import DynamicsEnsemble
        >>> data = make_toy_dataset(num_episodes=4, episode_length=25)
        >>> ens = DynamicsEnsemble.for_dataset(data, num_models=3, hidden_sizes=(8,))
        >>> rep = calibrate_threshold(ens, data, quantile=0.9)
        >>> round(rep.fraction_above, 2)
        0.1
        >>> rep2 = calibrate_threshold(ens, data, fraction=0.5)
        >>> abs(rep2.threshold - 0.5 * rep2.disc_max) < 1e-6
        True
    """
    disc = dataset_discrepancy(ensemble, data, kind)
    if fraction is not None:
        if fraction <= 0:
            raise ValueError(f"fraction must be > 0, got {fraction}.")
        threshold = fraction * float(disc.max())
        return CalibrationReport.from_values(disc, threshold, "fraction", fraction, kind)
    if quantile is None or not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must be in (0, 1], got {quantile}; or pass fraction=... instead.")
    threshold = float(torch.quantile(disc.double(), quantile)) if disc.numel() <= 16_000_000 else float(
        disc.double().kthvalue(max(1, int(round(quantile * disc.numel())))).values
    )
    return CalibrationReport.from_values(disc, threshold, "quantile", quantile, kind)
