"""Mean received power in the numpy reference's arithmetic, and one mover's column of the links.

:meth:`cv2x_marl.sim.ground_truth.SnapshotLinks.rx_dbm` computes the mean received power of every pair
as ``EIRP - path loss - shadowing`` (numpy, in that order); :func:`pair_rx_dbm` is the same arithmetic
compiled (the WINNER+ B1 loss of :func:`winner_b1_pair_db`, which the numpy path calls too), so the two
are equal bit for bit (tested). :func:`mover_column` gives, for one vehicle (the mover) at a new
position with the others fixed, what the mover receives: the expected success of every other
transmitter's packet at it (column ``mover`` of :func:`cv2x_marl.sim.kernels.snapshot_links`, the same
additions in the same order) and the mean received power of those links (column ``mover`` of
:func:`pair_rx_dbm`). The env's one-mover step (observation version 3: the mover's measurements) reads it.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.sim.kernels.pathloss import winner_b1_pair_db
from cv2x_marl.sim.kernels.per import _DB_TO_NEPER
from cv2x_marl.sim.kernels.snapshot import link_success

FloatArray = NDArray[np.float64]


@njit(cache=True)
def _fold(d: float, period: float) -> float:
    """A displacement on the torus of ``period`` (inf: none), the minimum image (``np.rint``)."""
    if period < np.inf:
        d -= period * np.rint(d / period)
    return d


@njit(cache=True)
def pair_rx_dbm(
    positions_m: FloatArray,
    period_m: FloatArray,
    los: NDArray[np.bool_],
    shadow_db: FloatArray,
    eirp_dbm: float,
    wb1: FloatArray,
    range2_m2: float,
) -> FloatArray:
    """[N(tx), N(rx)] mean received power (dBm): ``(eirp - PL) - shadow`` with PL the WINNER+ B1 loss of
    ``position_rx - position_tx`` (folded), ``los[tx, rx]``; -inf on the diagonal and beyond
    ``range2_m2`` (squared m; inf: none). The arithmetic of ``SnapshotLinks.rx_dbm`` (numpy), compiled.

    Args:
        positions_m: [N, 2] vehicle positions (m).
        period_m: [2] torus period per axis (inf: no wrap).
        los: [N, N] LOS state of each pair.
        shadow_db: [N, N] shadowing of each pair (dB).
        eirp_dbm: transmit power plus both antenna gains (dBm).
        wb1: [6] :func:`cv2x_marl.sim.kernels.winner_b1_constants`.
        range2_m2: squared link cut-off (m^2).
    """
    n = positions_m.shape[0]
    out = np.empty((n, n))
    for tx in range(n):
        for rx in range(n):
            if tx == rx:
                out[tx, rx] = -np.inf
                continue
            dx = _fold(positions_m[rx, 0] - positions_m[tx, 0], period_m[0])
            dy = _fold(positions_m[rx, 1] - positions_m[tx, 1], period_m[1])
            pl = winner_b1_pair_db(dx, dy, los[tx, rx], wb1[0], wb1[1], wb1[2], wb1[3], wb1[4], wb1[5])
            out[tx, rx] = (eirp_dbm - pl) - shadow_db[tx, rx]
            if range2_m2 < np.inf and not dx * dx + dy * dy <= range2_m2:
                out[tx, rx] = -np.inf
    return out


@njit(cache=True)
def _kernel_rx_dbm(
    cx: float,
    cy: float,
    positions_m: FloatArray,
    mover: int,
    c: int,
    period_m: FloatArray,
    los: NDArray[np.bool_],
    gain_col_db: FloatArray,
    wb1: FloatArray,
    range2_m2: float,
) -> tuple[float, float]:
    """Received power (dBm) at the mover (at ``(cx, cy)``) of transmitter ``c``, as
    :func:`cv2x_marl.sim.kernels.snapshot_links` computes it: the pair's displacement from the lower to
    the higher index, ``los[lower, higher]``, ``gain[c, mover] - PL``; -inf beyond the cut-off. Also the
    path loss PL (dB; nan beyond the cut-off, where it is not computed)."""
    lo = min(c, mover)
    hi = max(c, mover)
    if c < mover:
        dx = cx - positions_m[c, 0]
        dy = cy - positions_m[c, 1]
    else:
        dx = positions_m[c, 0] - cx
        dy = positions_m[c, 1] - cy
    if period_m[0] < np.inf:
        dx -= period_m[0] * np.rint(dx / period_m[0])
    if period_m[1] < np.inf:
        dy -= period_m[1] * np.rint(dy / period_m[1])
    if not dx * dx + dy * dy <= range2_m2:
        return -np.inf, np.nan
    pl = winner_b1_pair_db(dx, dy, los[lo, hi], wb1[0], wb1[1], wb1[2], wb1[3], wb1[4], wb1[5])
    return gain_col_db[c] - pl, pl


@njit(cache=True)
def mover_column(
    cx: float,
    cy: float,
    positions_m: FloatArray,
    mover: int,
    period_m: FloatArray,
    los: NDArray[np.bool_],
    gain_col_db: FloatArray,
    shadow_col_db: FloatArray,
    eirp_dbm: float,
    wb1: FloatArray,
    range2_m2: float,
    interferer_idx: NDArray[np.int64],
    interferer_weight: FloatArray,
    noise_mw: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
    target_col: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray]:
    """What ``mover``, moved to ``(cx, cy)``, receives from every other vehicle (the others where
    ``positions_m`` [N, 2] puts them; its own row there is ignored).

    Args:
        gain_col_db: [N] EIRP minus the shadowing of each pair ``(j, mover)`` (dBm), as
            :func:`cv2x_marl.sim.kernels.snapshot_links`'s ``gain_db[:, mover]`` with the mover here.
        shadow_col_db: [N] the shadowing of those pairs (dB), for the received power in
            :func:`pair_rx_dbm`'s arithmetic.
        target_col: [N] column ``mover`` of the target mask.
        others: as :func:`cv2x_marl.sim.kernels.snapshot_links` (``los`` [N, N], the interferer table).

    Returns:
        ``p`` [N]: expected success of ``j``'s packet at the mover (0 off ``target_col``; bit-identical to
        column ``mover`` of ``snapshot_links`` with the mover here); ``rx_dbm`` [N]: the mean received
        power of ``j`` at the mover (bit-identical to column ``mover`` of :func:`pair_rx_dbm`).
    """
    n = positions_m.shape[0]
    p = np.zeros(n)
    rx = np.empty(n)
    at_mover_dbm = np.empty(n)  # snapshot_links' rx_dbm[c, mover] and rx_mw[c, mover], each computed once
    at_mover_mw = np.zeros(n)
    pl_pair = np.empty(n)  # the pair's WINNER+ B1 loss from the first loop (nan: not computed)
    for c in range(n):
        if c == mover:
            at_mover_dbm[c] = -np.inf
            continue
        at_mover_dbm[c], pl_pair[c] = _kernel_rx_dbm(
            cx, cy, positions_m, mover, c, period_m, los, gain_col_db, wb1, range2_m2
        )
        at_mover_mw[c] = math.exp(at_mover_dbm[c] * _DB_TO_NEPER)
    for j in range(n):
        if j == mover:
            rx[j] = -np.inf
            continue
        dx = _fold(cx - positions_m[j, 0], period_m[0])
        dy = _fold(cy - positions_m[j, 1], period_m[1])
        # the same pair's loss as in the first loop where its LOS state is the same: the displacement there
        # is this one or its negative (folded alike), and the loss depends on |dx|, |dy| alone
        lo = min(j, mover)
        hi = max(j, mover)
        if los[j, mover] == los[lo, hi] and not np.isnan(pl_pair[j]):
            pl = pl_pair[j]
        else:
            pl = winner_b1_pair_db(dx, dy, los[j, mover], wb1[0], wb1[1], wb1[2], wb1[3], wb1[4], wb1[5])
        rx[j] = (eirp_dbm - pl) - shadow_col_db[j]
        if range2_m2 < np.inf and not dx * dx + dy * dy <= range2_m2:
            rx[j] = -np.inf
        if not target_col[j]:
            continue
        interference = 0.0
        for g in range(interferer_idx.shape[1]):
            c = interferer_idx[j, g]
            if c < 0:
                break
            interference += interferer_weight[j, g] * at_mover_mw[c]
        p[j] = link_success(
            at_mover_dbm[j], interference, noise_mw, model, per_sinr_db, per, threshold_db, sensitivity_dbm
        )
    return p, rx
