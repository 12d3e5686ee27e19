"""The run statistics (torchrl_offhrl.stats) against hand-computed cases and known limits."""
from __future__ import annotations

import numpy as np
import pytest

from torchrl_offhrl.stats import bootstrap_ci, iqm, iqm_ci, paired_change, performance_profile, summarize


def test_iqm_hand_computed():
    # 8 scores: int(0.25 * 8) = 2 cut from each end -> mean of 3, 4, 5, 6
    assert iqm([8.0, 1.0, 7.0, 2.0, 6.0, 3.0, 5.0, 4.0]) == pytest.approx(4.5)
    # 10 scores: 2 cut from each end -> mean of the middle 6
    assert iqm(list(range(10))) == pytest.approx(np.mean([2, 3, 4, 5, 6, 7]))
    # fewer than 4: nothing cut
    assert iqm([1.0, 2.0, 9.0]) == pytest.approx(4.0)
    # [runs, tasks] pools every score
    assert iqm(np.array([[0.0, 10.0], [1.0, 11.0], [2.0, 12.0], [3.0, 13.0]])) == pytest.approx(np.mean([2.0, 3.0, 10.0, 11.0]))


def test_iqm_ignores_one_outlier_where_the_mean_does_not():
    x = [40.0, 41.0, 42.0, 43.0, 1000.0]
    assert iqm(x) == pytest.approx(42.0)
    assert np.mean(x) > 200


def test_iqm_matches_scipy_trim_mean():
    scipy_stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(3)
    for n in (4, 5, 7, 10, 30):
        x = rng.normal(size=n)
        assert iqm(x) == pytest.approx(scipy_stats.trim_mean(x, 0.25))


def test_bootstrap_ci_limits():
    # identical runs: no spread, the interval is the point
    assert bootstrap_ci([5.0] * 6, reps=500) == (5.0, 5.0)
    # one run: nothing to resample
    assert bootstrap_ci([7.0], reps=500) == (7.0, 7.0)
    # the mean's interval lies within the data's range and contains the mean
    x = np.array([1.0, 2.0, 3.0, 4.0, 10.0])
    lo, hi = bootstrap_ci(x, "mean", reps=5000, seed=1)
    assert x.min() <= lo < x.mean() < hi <= x.max()
    # deterministic for a seed
    assert bootstrap_ci(x, reps=1000, seed=4) == bootstrap_ci(x, reps=1000, seed=4)


def test_bootstrap_ci_mean_matches_normal_theory():
    # 200 draws of N(0, 1): the bootstrap 95% interval of the mean is about +-1.96 / sqrt(200) around the sample mean
    x = np.random.default_rng(0).normal(size=200)
    lo, hi = bootstrap_ci(x, "mean", reps=20000, seed=0)
    half = 1.96 * x.std(ddof=1) / np.sqrt(x.size)
    assert (hi - lo) / 2 == pytest.approx(half, rel=0.1)


def test_bootstrap_is_stratified_by_task():
    # two tasks on very different scales: a stratified resample keeps 3 runs of each task in every replicate, so the
    # pooled mean can never be all of one task; unstratified resampling could reach 0 or 100
    x = np.array([[0.0, 100.0], [0.0, 100.0], [0.0, 100.0]])
    assert bootstrap_ci(x, "mean", reps=2000) == (50.0, 50.0)


def test_paired_change_and_summarize():
    d = paired_change([50.0, 60.0, 40.0, 70.0], [30.0, 30.0, 45.0, 20.0], reps=2000)
    assert d["mean"] == pytest.approx((20 + 30 - 5 + 50) / 4)
    assert d["up"] == 3 and d["per_run"] == [20.0, 30.0, -5.0, 50.0]
    assert min(d["per_run"]) <= d["ci"][0] <= d["mean"] <= d["ci"][1] <= max(d["per_run"])
    with pytest.raises(ValueError, match="equally long"):
        paired_change([1.0, 2.0], [1.0])
    s = summarize([1.0, 2.0, 3.0, 4.0, 5.0], reps=500)
    assert s["iqm"] == pytest.approx(3.0) and s["n"] == 5 and s["std"] == pytest.approx(np.std([1, 2, 3, 4, 5], ddof=1))
    assert iqm_ci([1.0, 2.0, 3.0, 4.0, 5.0], reps=500)[0] == s["iqm"]


def test_performance_profile_hand_computed():
    frac, lo, hi = performance_profile([10.0, 20.0, 30.0, 40.0], [0.0, 15.0, 35.0, 50.0], reps=500)
    assert frac.tolist() == [1.0, 0.75, 0.25, 0.0]
    assert (lo <= frac).all() and (frac <= hi).all()
    assert lo[0] == hi[0] == 1.0 and lo[-1] == hi[-1] == 0.0


def test_bad_scores_are_refused():
    with pytest.raises(ValueError, match="non-finite"):
        iqm([1.0, float("nan")])
    with pytest.raises(ValueError, match="at least one run"):
        iqm([])
