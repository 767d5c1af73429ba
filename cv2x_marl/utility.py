"""Utilities of the paper (eq. 9, 12, 17), per-node PRR and Jain's fairness index.

Eq. 12 is defined once, compiled: :func:`eq12_term` is the per-link term ``log(max(P_ij, p_min))``
and :func:`link_summary` the per-transmitter sum (with PRR and Jain's index) in index order. Every
compiled reader calls them: the snapshot-link kernels (``link_summaries``, ``row_utility``,
``mover_row_utility`` in :mod:`cv2x_marl.sim.kernels.snapshot`) and the env's step
(:mod:`cv2x_marl.env.step`, full, one-mover and batched), so they are bit-identical by construction.

The numpy functions below (:func:`utility_log`, :func:`per_node_prr`, :func:`jain_fairness`) are the
vectorised *reference* of the same definitions for ``[..., R]`` arrays (GBMU, the studies, tests):
numpy's pairwise summation and vectorised ``log`` may differ from the compiled sequential sums in the
last bits, so they agree to ~1e-12 relative (``tests/env/test_observation.py``), not bit for bit.

Arrays are ``[..., R]`` over receivers with an optional boolean ``mask`` of the same shape
selecting the target receivers ``R_i`` (vehicles in range not transmitting in i's subframe).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@njit(cache=True)
def eq12_term(p_success: float, p_min: float) -> float:
    """Eq. 12's per-link term ``ln max(P_ij, p_min)`` (natural log; ``p_min`` keeps a lost link finite).

    Args:
        p_success: expected success probability ``P_ij`` of one link, in [0, 1].
        p_min: clip of P inside the log, in (0, 1).
    """
    return math.log(max(p_success, p_min))


@njit(cache=True)
def link_summary(p_row: FloatArray, target_row: NDArray[np.bool_], p_min: float) -> tuple[float, float, float, int]:
    """Eq. 12 utility, PRR and Jain's index of one transmitter over its target receivers.

    One pass in receiver order: ``u = sum_{j in R_i} ln max(P_ij, p_min)`` (eq. 12,
    :func:`eq12_term`), ``prr = mean_{R_i} P_ij`` and Jain's index ``(sum P)^2 / (|R_i| sum P^2)``
    (0 where undefined: no targets, or all P = 0).

    Args:
        p_row: [N(rx)] link success probabilities of the transmitter.
        target_row: [N(rx)] its target receivers ``R_i``.
        p_min: clip of P inside the log.

    Returns:
        ``(u, prr, jain, count)`` with ``count = |R_i|``.
    """
    count = 0
    s1 = 0.0
    s2 = 0.0
    u = 0.0
    for j in range(p_row.shape[0]):
        if target_row[j]:
            x = p_row[j]
            count += 1
            s1 += x
            s2 += x * x
            u += eq12_term(x, p_min)
    prr = 0.0
    jain = 0.0
    if count > 0:
        prr = s1 / count
        if s2 > 0.0:
            jain = s1 * s1 / (count * s2)
    return u, prr, jain, count


def _masked(p: ArrayLike, mask: ArrayLike | None) -> tuple[FloatArray, NDArray[np.bool_]]:
    arr = np.asarray(p, dtype=np.float64)
    m = np.ones(arr.shape, dtype=bool) if mask is None else np.broadcast_to(np.asarray(mask, dtype=bool), arr.shape)
    return arr, m


def utility_sum(p: ArrayLike, mask: ArrayLike | None = None) -> FloatArray:
    """Eq. 9: ``U_i = sum_j P_ij`` (no fairness)."""
    arr, m = _masked(p, mask)
    return np.asarray(np.where(m, arr, 0.0).sum(axis=-1))


def utility_log(p: ArrayLike, mask: ArrayLike | None = None, p_min: float = 1e-3) -> FloatArray:
    """Eq. 12: ``U_i = sum_j log(max(P_ij, p_min))`` (natural log; proportional fairness).

    The numpy reference of :func:`eq12_term` summed over ``R_i`` (pairwise summation: equal to
    :func:`link_summary`'s sequential sum to ~1e-12 relative)."""
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
