"""cv2x_marl.stats: the IQM and the stratified bootstrap interval against hand-computed cases,
enumerated resamples, rliable's resampling and a coverage check."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.stats

from cv2x_marl import stats


def test_iqm_hand_cases() -> None:
    assert stats.iqm([1.0, 2.0, 3.0, 4.0]) == 2.5  # n = 4: drop 1 each side, mean of 2 and 3
    assert stats.iqm([5.0, 1.0, 4.0, 2.0, 3.0]) == 3.0  # n = 5: drop 1 each side, mean of 2, 3, 4
    assert stats.iqm([0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 100.0]) == 3.5  # n = 8: drop 2: (2+3+4+5)/4
    assert stats.iqm([0.0, 3.0, 9.0]) == 4.0  # n = 3: floor(0.75) = 0, the mean
    assert stats.iqm([1.0, np.nan, 2.0, np.inf, 3.0, 4.0]) == 2.5  # non-finite scores left out
    assert np.isnan(stats.iqm([np.nan, np.nan]))
    assert stats.iqm([[1.0, 2.0], [3.0, 4.0]]) == 2.5  # pooled over every axis


@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 13, 48, 101])
def test_iqm_is_scipy_trim_mean(n: int) -> None:
    x = np.random.default_rng(n).standard_cauchy(n)
    assert stats.iqm(x) == pytest.approx(scipy.stats.trim_mean(x, 0.25, axis=None), rel=1e-12, abs=1e-12)


def test_iqm_rows_each_row_on_its_own_finite_entries() -> None:
    x = np.array([[1.0, 2.0, 3.0, 4.0], [np.nan, 2.0, 4.0, 9.0], [np.nan] * 4])
    got = stats.iqm_rows(x)
    assert got[0] == 2.5 and got[1] == 5.0 and np.isnan(got[2])  # row 1: n = 3, the mean of 2, 4, 9


def test_two_episodes_by_hand() -> None:
    # one run, episodes [0, 1]: resamples {00, 01, 10, 11} -> means 0, .5, .5, 1 (IQM of 2 = the mean);
    # P(0) = P(1) = 1/4 > 2.5 %: the percentile interval is [0, 1]
    point, lo, hi = stats.bootstrap_ci([0.0, 1.0], np.random.default_rng(0))
    assert (point, lo, hi) == (0.5, 0.0, 1.0)


def test_two_runs_by_hand() -> None:
    # two runs of one episode, [[0], [4]]: runs resampled {00, 04, 40, 44} -> 0, 2, 2, 4
    point, lo, hi = stats.bootstrap_ci(np.array([[0.0], [4.0]]), np.random.default_rng(1), statistic="mean")
    assert (point, lo, hi) == (2.0, 0.0, 4.0)


def test_degenerate_strata_have_no_width() -> None:
    # two strata of one score each: every resample is the same -> the interval is the point
    assert stats.bootstrap_ci([[3.0], [5.0]], np.random.default_rng(2)) == (4.0, 4.0, 4.0)
    assert stats.bootstrap_ci(np.full((3, 5), 0.25), np.random.default_rng(3)) == (0.25, 0.25, 0.25)


def _enumerated(x: np.ndarray) -> np.ndarray:
    """The IQM of every equally likely resample of one stratum [R, E] (R^R x E^E of them), by loops."""
    r, e = x.shape
    out = []
    for rows in itertools.product(range(r), repeat=r):
        for cols in itertools.product(range(e), repeat=e):
            vals = [x[i, j] for i in rows for j in cols]
            out.append(scipy.stats.trim_mean(vals, 0.25))
    return np.array(out)


def test_resample_matches_enumeration_and_monte_carlo_converges() -> None:
    x = np.array([[0.0, 1.0, 3.0], [2.0, 10.0, 4.0]])
    exact = _enumerated(x)  # 2^2 x 3^3 = 108 resamples
    rows = np.array(list(itertools.product(range(2), repeat=2)))
    cols = np.array(list(itertools.product(range(3), repeat=3)))
    rr = np.repeat(rows, len(cols), axis=0)
    cc = np.tile(cols, (len(rows), 1))
    got = stats.iqm_rows(stats.resample([x], [rr], [cc]))
    np.testing.assert_allclose(got, exact, rtol=0, atol=1e-12)
    # the Monte Carlo interval converges to the ideal bootstrap's quantiles: with 200k resamples the
    # empirical 2.5 / 97.5 % points lie within the atoms bracketing the exact ones
    point, lo, hi = stats.bootstrap_ci(x, np.random.default_rng(4), n_resamples=200_000)
    assert point == pytest.approx(scipy.stats.trim_mean(x.ravel(), 0.25))
    atoms = np.unique(exact)
    cdf = np.array([np.mean(exact <= a) for a in atoms])
    for q, value in ((0.025, lo), (0.975, hi)):
        i = int(np.searchsorted(cdf, q))  # the exact q-quantile is atoms[i]
        assert atoms[max(i - 1, 0)] <= value <= atoms[min(i + 1, len(atoms) - 1)]
        if not np.any(np.isclose(cdf, q, atol=0.01)):  # no jump near q: the atom itself
            assert value == pytest.approx(atoms[i])


def test_one_episode_per_run_is_rliable_resampling() -> None:
    # rliable's StratifiedBootstrap on scores [runs, tasks]: indices = choice(runs, (runs, tasks)) and
    # scores[indices, arange(tasks)]; here each task is a stratum [runs, 1]: the same pooled values
    rng = np.random.default_rng(5)
    scores = rng.normal(size=(5, 3))
    idx = rng.integers(0, 5, size=(5, 3))
    rliable = scores[idx, np.arange(3)[None, :]]
    strata = [scores[:, t][:, None] for t in range(3)]
    ours = stats.resample(strata, [idx[:, t][None, :] for t in range(3)], [np.zeros((1, 1), int)] * 3)
    np.testing.assert_array_equal(np.sort(ours[0]), np.sort(rliable.ravel()))


def test_strata_resampled_independently_and_pooled() -> None:
    # two strata of one run: the pooled IQM of every resample stays inside the range each stratum allows
    a, b = np.array([0.0, 0.0, 0.0, 1.0]), np.array([10.0, 10.0, 10.0, 10.0])
    point, lo, hi = stats.bootstrap_ci([a, b], np.random.default_rng(6), statistic="mean")
    assert point == pytest.approx(5.125)
    assert 5.0 <= lo <= hi <= 5.5  # stratum b never moves: the mean is 5 + mean(a*) / 2


def test_coverage_of_the_iqm_interval() -> None:
    # N(0, 1) scores, 40 episodes of one run: the population IQM is 0; 400 data sets, 1000 resamples each
    rng = np.random.default_rng(7)
    hits = 0
    trials = 400
    for _ in range(trials):
        _, lo, hi = stats.bootstrap_ci(rng.normal(size=40), rng, n_resamples=1000)
        hits += lo <= 0.0 <= hi
    # binomial sd at 95 %: 1.1 points; the percentile interval runs slightly short at n = 40
    assert 0.89 <= hits / trials <= 0.99


def test_same_generator_state_same_interval() -> None:
    x = np.random.default_rng(8).normal(size=(3, 12))
    assert stats.bootstrap_ci(x, np.random.default_rng(9)) == stats.bootstrap_ci(x, np.random.default_rng(9))


def test_refusals() -> None:
    g = np.random.default_rng(0)
    with pytest.raises(ValueError, match="statistic must be one of iqm, mean"):
        stats.bootstrap_ci([1.0, 2.0], g, statistic="median")
    with pytest.raises(ValueError, match=r"rng must be a numpy\.random\.Generator"):
        stats.bootstrap_ci([1.0, 2.0], 0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="level must be"):
        stats.bootstrap_ci([1.0, 2.0], g, level=95)
    with pytest.raises(ValueError, match="n_resamples"):
        stats.bootstrap_ci([1.0, 2.0], g, n_resamples=0)
    with pytest.raises(ValueError, match="stratum 0"):
        stats.bootstrap_ci([np.zeros((2, 2, 2))], g)
