"""Aggregate statistics of the benchmark protocol: the interquartile mean (IQM) and its stratified
bootstrap confidence interval, as rliable defines them (Agarwal et al., "Deep Reinforcement Learning at
the Edge of the Statistical Precipice", NeurIPS 2021; ``rliable.metrics.aggregate_iqm`` and
``rliable.library.StratifiedBootstrap`` with the percentile interval).

rliable itself is not a dependency (it pulls ``arch``, ``seaborn`` and ``absl-py``); this module is the
tested numpy implementation (``tests/test_stats.py``: hand-computed cases, enumerated resamples, coverage).

Scores come per stratum (a task) as an array ``[runs, episodes]``: the runs are a method's training seeds
(one row for a scripted method), the episodes the task's evaluation episodes, the same for every run
(a crossed design). One bootstrap resample draws, independently in every stratum, ``runs`` row indices
and ``episodes`` column indices with replacement and keeps the sub-array ``scores[rows][:, cols]``;
the statistic is computed on every stratum's resampled scores pooled. With one episode per run this is
rliable's ``StratifiedBootstrap`` on a ``[runs, tasks]`` array (runs resampled within each task); with
one run it is the i.i.d. bootstrap over episodes. The interval is the percentile interval of the
resampled statistics (``numpy.percentile``, linear interpolation), as rliable's ``method="percentile"``.

Non-finite scores (a gain over a zero start utility, a share of a zero ceiling gain) are left out of
the statistic (not of the resampling).

numpy only: the bottom layer of the package.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: share of the sorted scores the IQM drops at each end (rliable: ``scipy.stats.trim_mean(x, 0.25)``)
TRIM = 0.25
#: bootstrap resamples of the protocol's intervals
N_RESAMPLES = 2000
#: the protocol's confidence level
LEVEL = 0.95


def iqm(scores: ArrayLike) -> float:
    """Interquartile mean of the pooled finite scores: the mean of the sorted values after dropping
    ``floor(n / 4)`` at each end (``scipy.stats.trim_mean(x, 0.25, axis=None)``, rliable's
    ``aggregate_iqm``). NaN when no score is finite.

    Args:
        scores: any shape; every finite entry is one score.
    """
    x = np.asarray(scores, dtype=float).ravel()
    return float(iqm_rows(x[None, :])[0])


def iqm_rows(scores: NDArray[np.float64]) -> NDArray[np.float64]:
    """[B] the IQM of each row of ``scores`` [B, n], each over its own finite entries (vectorised)."""
    x = np.asarray(scores, dtype=float)
    if x.ndim != 2:
        raise ValueError(f"scores must be a 2-D array [rows, n], got shape {x.shape}")
    x = np.where(np.isfinite(x), x, np.nan)
    s = np.sort(x, axis=1)  # NaN last
    m = np.sum(np.isfinite(s), axis=1)
    k = np.floor(TRIM * m).astype(np.int64)
    c = np.concatenate([np.zeros((len(s), 1)), np.cumsum(np.nan_to_num(s), axis=1)], axis=1)
    rows = np.arange(len(s))
    kept = m - 2 * k
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (c[rows, m - k] - c[rows, k]) / kept
    return np.where(kept > 0, out, np.nan)


def mean_rows(scores: NDArray[np.float64]) -> NDArray[np.float64]:
    """[B] the mean of each row's finite entries (NaN for a row with none)."""
    x = np.asarray(scores, dtype=float)
    ok = np.isfinite(x)
    m = ok.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(m > 0, np.where(ok, x, 0.0).sum(axis=1) / m, np.nan)


#: the statistics by name (each maps [B, n] to [B])
STATISTICS = {"iqm": iqm_rows, "mean": mean_rows}


def _strata(scores: ArrayLike | Sequence[ArrayLike]) -> list[NDArray[np.float64]]:
    """The strata as 2-D arrays [runs, episodes]: one array (1-D: one run) or a list of them."""
    if isinstance(scores, np.ndarray) or (isinstance(scores, Sequence) and len(scores) > 0 and np.isscalar(scores[0])):
        parts: list[ArrayLike] = [scores]  # type: ignore[list-item]
    else:
        parts = list(scores)  # type: ignore[arg-type]
    if not parts:
        raise ValueError("scores: give at least one stratum")
    out = []
    for i, p in enumerate(parts):
        a = np.asarray(p, dtype=float)
        if a.ndim == 1:
            a = a[None, :]
        if a.ndim != 2 or a.size == 0:
            raise ValueError(f"scores: stratum {i} must be a non-empty array [runs, episodes], got shape {a.shape}")
        out.append(a)
    return out


def resample(
    strata: Sequence[NDArray[np.float64]],
    rows: Sequence[NDArray[np.int64]],
    cols: Sequence[NDArray[np.int64]],
) -> NDArray[np.float64]:
    """[B, n] the pooled resampled scores: per stratum ``s``, ``strata[s][rows[s][b]][:, cols[s][b]]``
    flattened, the strata side by side.

    Args:
        strata: per stratum its scores [runs_s, episodes_s].
        rows: per stratum the drawn run indices [B, runs_s].
        cols: per stratum the drawn episode indices [B, episodes_s].
    """
    parts = []
    for x, r, c in zip(strata, rows, cols, strict=True):
        sub = x[r[:, :, None], c[:, None, :]]  # [B, runs_s, episodes_s]
        parts.append(sub.reshape(len(r), -1))
    return np.concatenate(parts, axis=1)


def bootstrap_ci(
    scores: ArrayLike | Sequence[ArrayLike],
    rng: np.random.Generator,
    statistic: str = "iqm",
    n_resamples: int = N_RESAMPLES,
    level: float = LEVEL,
) -> tuple[float, float, float]:
    """The statistic of the pooled scores and its stratified bootstrap percentile interval.

    Args:
        scores: one stratum [runs, episodes] (1-D: one run), or a list of strata (tasks), each
            [runs_s, episodes_s]; the statistic pools every stratum's scores.
        rng: the resampling's generator (the caller's; the protocol seeds it per task and method).
        statistic: ``iqm`` (:func:`iqm`) or ``mean``.
        n_resamples: bootstrap resamples B (>= 1).
        level: confidence level in (0, 1); the interval is the ``(1 - level) / 2`` and
            ``(1 + level) / 2`` percentiles of the B resampled statistics.

    Returns:
        ``(point, low, high)``; NaN where no score is finite.
    """
    if statistic not in STATISTICS:
        raise ValueError(f"statistic must be one of {', '.join(STATISTICS)}, got {statistic!r}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if isinstance(n_resamples, bool) or not isinstance(n_resamples, int | np.integer) or n_resamples < 1:
        raise ValueError(f"n_resamples must be an integer >= 1, got {n_resamples!r}")
    if not (isinstance(level, float | int) and 0.0 < level < 1.0):
        raise ValueError(f"level must be a number in (0, 1), got {level!r}")
    fn = STATISTICS[statistic]
    strata = _strata(scores)
    point = float(fn(np.concatenate([x.ravel() for x in strata])[None, :])[0])
    rows = [rng.integers(0, x.shape[0], size=(n_resamples, x.shape[0])) for x in strata]
    cols = [rng.integers(0, x.shape[1], size=(n_resamples, x.shape[1])) for x in strata]
    stats = fn(resample(strata, rows, cols))
    stats = stats[np.isfinite(stats)]
    if not np.isfinite(point) or stats.size == 0:
        return point, float("nan"), float("nan")
    lo, hi = np.percentile(stats, [50.0 * (1.0 - level), 50.0 * (1.0 + level)])
    return point, float(lo), float(hi)
