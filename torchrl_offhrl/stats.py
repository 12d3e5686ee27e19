"""Statistics over runs as the field reports them (Agarwal et al., 2021, *Deep RL at the Edge of the Statistical Precipice*).

* :func:`iqm`: the interquartile mean, the mean of the middle 50% of the
  runs' scores (scipy's ``trim_mean(x, 0.25)``, which is what ``rliable``'s
  ``aggregate_iqm`` computes);
* :func:`bootstrap_ci`: a percentile confidence interval by the *stratified*
  bootstrap: runs are resampled with replacement within each task (dataset),
  never across tasks, as ``rliable.library.get_interval_estimates`` does;
* :func:`paired_change`: the mean change of a run's score over its own
  untrained start, with a bootstrap CI over the pairs;
* :func:`performance_profile`: the fraction of runs above each score
  threshold, with stratified-bootstrap bands, and :func:`plot_performance_profiles`.

Why not ``rliable`` itself: it imports ``arch``, whose releases that pip
resolves beside this stack (arch 7.2 with pandas 3) fail at import
(``deprecate_kwarg() missing 1 required positional argument``), and its
bootstrap code is a loop in Python. The functions here are the same
estimators on numpy arrays, vectorised over the bootstrap replicates;
``tests/test_stats.py`` checks them against hand-computed cases.

Scores are arrays ``[runs]`` (one task) or ``[runs, tasks]``.

Examples:
    >>> import numpy as np
    >>> iqm([1.0, 2.0, 3.0, 4.0, 100.0])  # the lowest and highest of 5 are cut
    3.0
    >>> lo, hi = bootstrap_ci(np.array([10.0, 11.0, 12.0, 13.0, 14.0]), reps=2000, seed=0)
    >>> 10.0 <= lo <= 12.0 <= hi <= 14.0
    True
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["bootstrap_ci", "iqm", "iqm_ci", "mean_ci", "mean_std", "paired_change", "performance_profile", "plot_performance_profiles", "summarize"]

#: bootstrap replicates: rliable's default for its interval estimates is 50,000; 10,000 keeps a 95% percentile
#: interval's ends within ~1% of the data's spread and costs milliseconds
DEFAULT_REPS = 10_000


def _as_matrix(scores) -> np.ndarray:
    x = np.asarray(scores, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"scores must be [runs] or [runs, tasks] with at least one run, got shape {tuple(x.shape)}")
    if not np.isfinite(x).all():
        raise ValueError(f"scores hold non-finite values ({x.ravel().tolist()}): leave out the runs without a score")
    return x


def _resample(x: np.ndarray, reps: int, seed: int) -> np.ndarray:
    """``[reps, runs, tasks]`` stratified bootstrap replicates of ``x [runs, tasks]``: runs drawn with replacement within each task."""
    n, t = x.shape
    idx = np.random.default_rng(seed).integers(0, n, size=(int(reps), n, t))
    return np.take_along_axis(np.broadcast_to(x, (int(reps), n, t)), idx, axis=1)


def _iqm_last2(x: np.ndarray) -> np.ndarray:
    """IQM over the last two axes (runs x tasks pooled), for a stack of replicates ``[..., runs, tasks]``."""
    flat = np.sort(x.reshape(*x.shape[:-2], -1), axis=-1)
    n = flat.shape[-1]
    k = int(0.25 * n)  # scipy's trim_mean: int(proportiontocut * n) cut from each end
    return flat[..., k:n - k].mean(-1)


def _mean_last2(x: np.ndarray) -> np.ndarray:
    return x.reshape(*x.shape[:-2], -1).mean(-1)


def iqm(scores) -> float:
    """Interquartile mean of ``scores`` (``[runs]`` or ``[runs, tasks]``, pooled): the 25% trimmed mean.

    With fewer than 4 scores nothing is cut (the mean).
    """
    return float(_iqm_last2(_as_matrix(scores)))


def bootstrap_ci(scores, statistic: Callable[[np.ndarray], np.ndarray] | str = "iqm", reps: int = DEFAULT_REPS, ci: float = 0.95,
                 seed: int = 0) -> tuple[float, float]:
    """Percentile ``ci`` interval of ``statistic`` by the stratified bootstrap (runs resampled within each task).

    ``statistic`` is ``"iqm"``, ``"mean"``, or a function of an array
    ``[reps, runs, tasks]`` returning ``[reps]``. One run gives the point
    itself as both ends (there is nothing to resample).
    """
    x = _as_matrix(scores)
    fn = {"iqm": _iqm_last2, "mean": _mean_last2}.get(statistic, statistic) if isinstance(statistic, str) else statistic
    if not callable(fn):
        raise ValueError(f"statistic must be 'iqm', 'mean' or a function, got {statistic!r}")
    if not 0 < ci < 1:
        raise ValueError(f"ci must be in (0, 1), got {ci}")
    boot = fn(_resample(x, reps, seed))
    lo, hi = np.quantile(boot, [(1 - ci) / 2, 1 - (1 - ci) / 2])
    return float(lo), float(hi)


def iqm_ci(scores, reps: int = DEFAULT_REPS, ci: float = 0.95, seed: int = 0) -> tuple[float, float, float]:
    """``(IQM, lower, upper)``."""
    lo, hi = bootstrap_ci(scores, "iqm", reps, ci, seed)
    return iqm(scores), lo, hi


def mean_std(values: Sequence[float | None]) -> tuple[float | None, float | None, int]:
    """``(mean, sample std, n)`` of the values that are not None: ``(None, None, 0)`` without any, std 0 for one value.

    Examples:
        >>> mean_std([1.0, None, 3.0])
        (2.0, 1.4142135623730951, 2)
        >>> mean_std([5.0]), mean_std([None])
        ((5.0, 0.0, 1), (None, None, 0))
    """
    vals = np.array([v for v in values if v is not None], dtype=np.float64)
    if vals.size == 0:
        return None, None, 0
    return float(vals.mean()), float(vals.std(ddof=1)) if vals.size > 1 else 0.0, int(vals.size)


def mean_ci(scores, reps: int = DEFAULT_REPS, ci: float = 0.95, seed: int = 0) -> tuple[float, float, float]:
    """``(mean, lower, upper)``."""
    lo, hi = bootstrap_ci(scores, "mean", reps, ci, seed)
    return float(_as_matrix(scores).mean()), lo, hi


def paired_change(after: Sequence[float], before: Sequence[float], reps: int = DEFAULT_REPS, ci: float = 0.95, seed: int = 0) -> dict:
    """The change ``after - before`` of each run over its own start: mean, bootstrap CI, and how many runs went up.

    Examples:
        >>> d = paired_change([50.0, 60.0, 40.0], [30.0, 30.0, 45.0], reps=1000)
        >>> d["mean"], d["up"], d["n"]
        (15.0, 2, 3)
    """
    a, b = np.asarray(after, dtype=np.float64), np.asarray(before, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or a.size == 0:
        raise ValueError(f"after and before must be two equally long lists of per-run scores, got shapes {a.shape} and {b.shape}")
    d = a - b
    m, lo, hi = mean_ci(d, reps, ci, seed)
    return {"mean": m, "ci": (lo, hi), "up": int((d > 0).sum()), "n": int(d.size), "per_run": d.tolist()}


def performance_profile(scores, taus: Sequence[float], reps: int = DEFAULT_REPS, ci: float = 0.95, seed: int = 0):
    """``(fraction, lower, upper)``, each ``[len(taus)]``: the share of runs (all tasks pooled) scoring above each ``tau``.

    The bands come from the stratified bootstrap, as ``rliable``'s
    ``create_performance_profile``.
    """
    x = _as_matrix(scores)
    taus = np.asarray(taus, dtype=np.float64)
    frac = (x.ravel()[None, :] > taus[:, None]).mean(-1)
    boot = _resample(x, reps, seed).reshape(int(reps), -1)
    bfrac = (boot[:, None, :] > taus[None, :, None]).mean(-1)  # [reps, taus]
    lo, hi = np.quantile(bfrac, [(1 - ci) / 2, 1 - (1 - ci) / 2], axis=0)
    return frac, lo, hi


def plot_performance_profiles(groups: dict[str, np.ndarray], path=None, taus: Sequence[float] | None = None, title: str = "",
                              xlabel: str = "D4RL-normalised score (tau)", reference: float | None = None, reps: int = 2000, ax=None):
    """One curve per group (``{label: scores [runs] or [runs, tasks]}``): fraction of runs with score > tau, 95% bands.

    Draws on ``ax`` when given (the caller saves the figure), else on a new
    figure saved to ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    allx = np.concatenate([_as_matrix(v).ravel() for v in groups.values()])
    if taus is None:
        taus = np.linspace(min(0.0, allx.min()), allx.max() * 1.05 + 1e-9, 101)
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(6.5, 4))
    for label, s in groups.items():
        f, lo, hi = performance_profile(s, taus, reps=reps)
        line, = ax.plot(taus, f, label=f"{label} ({_as_matrix(s).size})")
        ax.fill_between(taus, lo, hi, color=line.get_color(), alpha=0.15)
    if reference is not None:
        ax.axvline(reference, color="gray", ls="--", lw=1, label="behaviour data")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("fraction of runs > tau")
    ax.set_ylim(0, 1.02)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7)
    if own:
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
    return path


def summarize(scores, reps: int = DEFAULT_REPS, seed: int = 0) -> dict:
    """IQM with its 95% CI, mean, std and the per-run values of one cell: what every results table shows.

    Examples:
        >>> s = summarize([30.0, 35.0, 40.0, 45.0, 90.0], reps=1000)
        >>> s["iqm"], s["n"], s["per_run"]
        (40.0, 5, [30.0, 35.0, 40.0, 45.0, 90.0])
    """
    x = _as_matrix(scores)
    m, lo, hi = iqm_ci(x, reps=reps, seed=seed)
    return {"iqm": m, "ci": (lo, hi), "mean": float(x.mean()), "std": float(x.std(ddof=1)) if x.size > 1 else 0.0, "n": int(x.size),
            "per_run": [float(v) for v in x.ravel()]}
