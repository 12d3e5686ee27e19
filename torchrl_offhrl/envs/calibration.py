"""Discrepancy calibration: where the ensemble stops being trusted."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import torch

__all__ = ["CalibrationReport", "calibrate_threshold", "dataset_discrepancy"]


@torch.no_grad()
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
