"""Utilities of the paper (eq. 9, 12, 17), per-node PRR and Jain's fairness index.

Arrays are ``[..., R]`` over receivers with an optional boolean ``mask`` of the same shape
selecting the target receivers ``R_i`` (vehicles in range not transmitting in i's subframe).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def _masked(p: ArrayLike, mask: ArrayLike | None) -> tuple[FloatArray, NDArray[np.bool_]]:
    arr = np.asarray(p, dtype=np.float64)
    m = np.ones(arr.shape, dtype=bool) if mask is None else np.broadcast_to(np.asarray(mask, dtype=bool), arr.shape)
    return arr, m


def utility_sum(p: ArrayLike, mask: ArrayLike | None = None) -> FloatArray:
    """Eq. 9: ``U_i = sum_j P_ij`` (no fairness)."""
    arr, m = _masked(p, mask)
    return np.asarray(np.where(m, arr, 0.0).sum(axis=-1))


def utility_log(p: ArrayLike, mask: ArrayLike | None = None, p_min: float = 1e-3) -> FloatArray:
    """Eq. 12: ``U_i = sum_j log(max(P_ij, p_min))`` (natural log; proportional fairness)."""
    arr, m = _masked(p, mask)
    return np.asarray(np.where(m, np.log(np.maximum(arr, p_min)), 0.0).sum(axis=-1))


def normalised_gain(u_k: ArrayLike, u_0: ArrayLike) -> FloatArray:
    """Eq. 17: ``(U(k) - U(0)) / |U(0)|`` (NaN where ``U(0) = 0``)."""
    uk = np.asarray(u_k, dtype=np.float64)
    u0 = np.asarray(u_0, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(np.where(u0 != 0, (uk - u0) / np.abs(u0), np.nan))


def per_node_prr(p: ArrayLike, mask: ArrayLike | None = None) -> FloatArray:
    """Mean success probability over the target receivers (READING.md, Sec. 3)."""
    arr, m = _masked(p, mask)
    n = m.sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(np.where(n > 0, np.where(m, arr, 0.0).sum(axis=-1) / n, np.nan))


def jain_fairness(x: ArrayLike, mask: ArrayLike | None = None) -> FloatArray:
    """Jain's index ``(sum x)^2 / (n sum x^2)`` in ``[1/n, 1]`` (NaN when all are zero)."""
    arr, m = _masked(x, mask)
    xs = np.where(m, arr, 0.0)
    n = m.sum(axis=-1)
    num = xs.sum(axis=-1) ** 2
    den = n * (xs**2).sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.asarray(np.where(den > 0, num / den, np.nan))
