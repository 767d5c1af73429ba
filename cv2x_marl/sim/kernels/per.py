"""PER lookup of the link-level curves (TR 36.885 A.2; ``link.per_interpolation``) and the threshold model."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


MODEL_PER_TABLE = 0


MODEL_THRESHOLD = 1


#: ``per_table`` with ``link.per_interpolation=log``: ``ln PER`` interpolated linearly in SINR (dB)
MODEL_PER_TABLE_LOG = 2


_DB_TO_NEPER = math.log(10.0) / 10.0


@njit(cache=True)
def per_success(sinr_db: float, per_sinr_db: FloatArray, per: FloatArray, log_domain: bool = False) -> float:
    """``1 - PER`` interpolated (PER 1 below the table, the last PER above): np.interp's formula,
    on PER (``log_domain`` False) or on ``ln PER`` (True; :meth:`cv2x_marl.sim.link.PerCurve.success`),
    the table position by a scalar bisection (:func:`_segment`, ``np.searchsorted(side="right") - 1``)."""
    k = per_sinr_db.shape[0]
    if not sinr_db >= per_sinr_db[0]:  # also -inf and NaN
        return 0.0
    if sinr_db >= per_sinr_db[k - 1]:
        return 1.0 - per[k - 1]
    j = _segment(per_sinr_db, sinr_db)
    if log_domain:
        lo, hi = math.log(per[j]), math.log(per[j + 1])
        slope = (hi - lo) / (per_sinr_db[j + 1] - per_sinr_db[j])
        return 1.0 - math.exp(slope * (sinr_db - per_sinr_db[j]) + lo)
    slope = (per[j + 1] - per[j]) / (per_sinr_db[j + 1] - per_sinr_db[j])
    return 1.0 - (slope * (sinr_db - per_sinr_db[j]) + per[j])


@njit(cache=True)
def _segment(xs: FloatArray, x: float) -> int:
    """The index ``j`` with ``xs[j] <= x < xs[j + 1]`` of ascending ``xs`` (``np.searchsorted(xs, x,
    side="right") - 1``) by a scalar bisection, for ``xs[0] <= x < xs[-1]``."""
    lo, hi = 0, xs.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if xs[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


#: relative margin of the linear-domain tests that decide a dB comparison without a logarithm: far
#: larger than the error of ``10 log10`` (a few ulps), so inside it the logarithm decides, as numpy's
LIN_MARGIN = 1e-9


@njit(cache=True)
def db_below(x: float, x_lin_threshold: float, threshold_db: float) -> bool:
    """``10 log10(x) < threshold_db`` with the logarithm taken only within :data:`LIN_MARGIN` of the
    threshold (``x_lin_threshold = 10^(threshold_db / 10)``): the same answer, most often without it."""
    if x < x_lin_threshold * (1.0 - LIN_MARGIN):
        return True
    if x > x_lin_threshold * (1.0 + LIN_MARGIN):
        return False
    return 10.0 * math.log10(x) < threshold_db


@njit(cache=True)
def success_of_ratio(
    ratio: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    per_lin_lo: float,
    per_lin_hi: float,
    threshold_db: float,
    threshold_lin: float,
) -> float:
    """Success probability of a link at linear SINR (or SNR) ``ratio``: the threshold model or the PER
    table (:func:`per_success` on ``10 log10(ratio)``, numpy's dB value), the logarithm taken
    only when the ratio is within the table (``per_lin_lo``, ``per_lin_hi``: its ends in linear
    units) or near the threshold: outside, the constant the dB formula gives."""
    if model == MODEL_THRESHOLD:
        return 0.0 if db_below(ratio, threshold_lin, threshold_db) else 1.0
    if ratio < per_lin_lo * (1.0 - LIN_MARGIN):
        return 0.0
    if ratio > per_lin_hi * (1.0 + LIN_MARGIN):
        return 1.0 - per[per.shape[0] - 1]
    return per_success(10.0 * math.log10(ratio), per_sinr_db, per, model == MODEL_PER_TABLE_LOG)


@njit(cache=True)
def interp_clamped(x: float, xp: FloatArray, fp: FloatArray, left: float, right: float) -> float:
    """``np.interp(x, xp, fp, left, right)`` for one ``x`` (numpy's formula: ``fp[j]`` at a point,
    ``slope * (x - xp[j]) + fp[j]`` between points, ``left`` / ``right`` outside, NaN for NaN)."""
    k = xp.shape[0]
    if math.isnan(x):
        return x
    if x < xp[0]:
        return left
    if x > xp[k - 1]:
        return right
    if x == xp[k - 1]:
        return fp[k - 1]
    j = _segment(xp, x)
    if x == xp[j]:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    return slope * (x - xp[j]) + fp[j]
