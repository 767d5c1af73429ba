"""Every link of a snapshot in one pass, and one mover's row of it: the env's link ground truth.

Received power, interference sums, PER (eq. 3-5), eq. 12's per-link term and the per-vehicle summaries
(utility, PRR, Jain's index) the env's step reads."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.sim.kernels.pathloss import winner_b1_pair_db
from cv2x_marl.sim.kernels.per import _DB_TO_NEPER, MODEL_PER_TABLE, MODEL_PER_TABLE_LOG, per_success
from cv2x_marl.utility import eq12_term, link_summary

FloatArray = NDArray[np.float64]


@njit(cache=True)
def pair_powers(
    positions_m: FloatArray,
    period_m: FloatArray,
    los: NDArray[np.bool_],
    gain_db: FloatArray,
    wb1: FloatArray,
    range2_m2: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Geometry and mean received power of every ordered pair (one pass over the unordered pairs)."""
    n = positions_m.shape[0]
    disp = np.empty((2, n, n))
    dist2 = np.empty((n, n))
    rx_dbm = np.empty((n, n))
    rx_mw = np.empty((n, n))
    for i in range(n):
        disp[0, i, i] = 0.0
        disp[1, i, i] = 0.0
        dist2[i, i] = 0.0
        rx_dbm[i, i] = -np.inf
        rx_mw[i, i] = 0.0
        for j in range(i + 1, n):
            dx = positions_m[j, 0] - positions_m[i, 0]
            dy = positions_m[j, 1] - positions_m[i, 1]
            if period_m[0] < np.inf:
                dx -= period_m[0] * np.rint(dx / period_m[0])
            if period_m[1] < np.inf:
                dy -= period_m[1] * np.rint(dy / period_m[1])
            d2 = dx * dx + dy * dy
            disp[0, i, j] = dx
            disp[1, i, j] = dy
            disp[0, j, i] = -dx
            disp[1, j, i] = -dy
            dist2[i, j] = d2
            dist2[j, i] = d2
            if d2 <= range2_m2:
                pl = winner_b1_pair_db(dx, dy, los[i, j], wb1[0], wb1[1], wb1[2], wb1[3], wb1[4], wb1[5])
                a = gain_db[i, j] - pl
                b = gain_db[j, i] - pl
            else:
                a = -np.inf
                b = -np.inf
            rx_dbm[i, j] = a
            rx_dbm[j, i] = b
            rx_mw[i, j] = math.exp(a * _DB_TO_NEPER)  # 10 ** (a / 10)
            rx_mw[j, i] = math.exp(b * _DB_TO_NEPER)
    return disp, dist2, rx_dbm, rx_mw


@njit(cache=True)
def link_interference_mw(
    rx_mw: FloatArray, interferer_idx: NDArray[np.int64], interferer_weight: FloatArray, tx: int, rx: int
) -> float:
    """Interference at ``rx`` on ``tx``'s packet: the weighted powers of tx's interferers, in table order."""
    interference = 0.0
    for g in range(interferer_idx.shape[1]):
        c = interferer_idx[tx, g]
        if c < 0:
            break
        interference += interferer_weight[tx, g] * rx_mw[c, rx]
    return interference


@njit(cache=True)
def success_at_level(
    s_dbm: float,
    level_db: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
) -> float:
    """Expected success of one link from its mean signal (dBm) and noise-plus-interference level (dB)."""
    if s_dbm < sensitivity_dbm or s_dbm == -np.inf:
        return 0.0
    sinr_db = s_dbm - level_db
    if model == MODEL_PER_TABLE:
        return per_success(sinr_db, per_sinr_db, per)
    if model == MODEL_PER_TABLE_LOG:
        return per_success(sinr_db, per_sinr_db, per, True)
    return 1.0 if sinr_db >= threshold_db else 0.0


@njit(cache=True)
def link_success(
    s_dbm: float,
    interference_mw: float,
    noise_mw: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
) -> float:
    """Expected success of one link from its mean signal (dBm) and interference (mW)."""
    level_db = 10.0 * math.log10(interference_mw + noise_mw)
    return success_at_level(s_dbm, level_db, model, per_sinr_db, per, threshold_db, sensitivity_dbm)


@njit(cache=True)
def snapshot_links(
    positions_m: FloatArray,
    period_m: FloatArray,
    los: NDArray[np.bool_],
    gain_db: FloatArray,
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
    target: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Geometry and expected success probability of every link (WINNER+ B1).

    Args:
        positions_m: [N, 2] vehicle positions (m).
        period_m: [2] torus period per axis (inf: that axis does not wrap); minimum image.
        los: [N, N] LOS state of each pair.
        gain_db: [N, N] EIRP minus shadowing of each pair (dBm): mean Rx power = gain - path loss.
        wb1: [6] :func:`winner_b1_constants`.
        range2_m2: squared link cut-off (inf: none); pairs beyond it carry no power.
        interferer_idx: [N, G] the vehicles whose power interferes with each transmitter's packet
            (its co-channel users, and with in-band emission the rest of its subframe), -1 padded.
        interferer_weight: [N, G] their weights (1 co-channel, the emission factor otherwise).
        noise_mw: thermal noise plus noise figure (mW).
        model: :data:`MODEL_PER_TABLE` (``1 - PER(SINR)``), :data:`MODEL_PER_TABLE_LOG` (the same,
            interpolated in ``ln PER``) or :data:`MODEL_THRESHOLD`.
        per_sinr_db, per: [K] the PER table (ascending SINR).
        threshold_db: SINR threshold of the threshold model.
        sensitivity_dbm: receivers below it decode nothing (-inf: no sensitivity).
        target: [N(tx), N(rx)] links that count (half duplex and the diagonal excluded).

    Returns:
        disp_m: [2, N, N] ``position_j - position_i`` (folded on the torus);
        dist2_m2: [N, N] squared distances;
        p: [N(tx), N(rx)] expected success, 0 off ``target``.
    """
    n = positions_m.shape[0]
    disp, dist2, rx_dbm, rx_mw = pair_powers(positions_m, period_m, los, gain_db, wb1, range2_m2)
    p = np.zeros((n, n))
    for tx in range(n):
        for rx in range(n):
            if not target[tx, rx]:
                continue
            interference = link_interference_mw(rx_mw, interferer_idx, interferer_weight, tx, rx)
            p[tx, rx] = link_success(
                rx_dbm[tx, rx], interference, noise_mw, model, per_sinr_db, per, threshold_db, sensitivity_dbm
            )
    return disp, dist2, p


@njit(cache=True)
def mover_interference(
    positions_m: FloatArray,
    period_m: FloatArray,
    los: NDArray[np.bool_],
    gain_db: FloatArray,
    wb1: FloatArray,
    range2_m2: float,
    interferer_idx: NDArray[np.int64],
    interferer_weight: FloatArray,
    mover: int,
) -> FloatArray:
    """[N] interference (mW) at every receiver on ``mover``'s packet, the other vehicles where they are.

    The interferers of a transmitter never include itself, so this row does not depend on the
    mover's own position: with the others fixed it is computed once and reused by
    :func:`mover_row_success` for every candidate position. Arguments as :func:`snapshot_links`;
    the sums are the same additions in the same order, so the results are bit-identical.
    """
    n = positions_m.shape[0]
    _, _, _, rx_mw = pair_powers(positions_m, period_m, los, gain_db, wb1, range2_m2)
    out = np.zeros(n)
    for rx in range(n):
        out[rx] = link_interference_mw(rx_mw, interferer_idx, interferer_weight, mover, rx)
    return out


@njit(cache=True)
def moved_signal_dbm(
    cx: float,
    cy: float,
    positions_m: FloatArray,
    mover: int,
    j: int,
    period_m: FloatArray,
    los_row: NDArray[np.bool_],
    gain_row_db: FloatArray,
    wb1: FloatArray,
    range2_m2: float,
) -> float:
    """Mean signal (dBm) at receiver ``j`` of ``mover`` placed at (cx, cy): the displacement as
    :func:`snapshot_links` takes it (from the lower to the higher index, folded on the torus),
    WINNER+ B1, EIRP - shadowing; -inf beyond the cut-off."""
    if mover < j:
        dx = positions_m[j, 0] - cx
        dy = positions_m[j, 1] - cy
    else:
        dx = cx - positions_m[j, 0]
        dy = cy - positions_m[j, 1]
    if period_m[0] < np.inf:
        dx -= period_m[0] * np.rint(dx / period_m[0])
    if period_m[1] < np.inf:
        dy -= period_m[1] * np.rint(dy / period_m[1])
    if dx * dx + dy * dy > range2_m2:
        return -np.inf
    pl = winner_b1_pair_db(dx, dy, los_row[j], wb1[0], wb1[1], wb1[2], wb1[3], wb1[4], wb1[5])
    return gain_row_db[j] - pl


@njit(cache=True)
def levels_db(interference_mw: FloatArray, noise_mw: float) -> FloatArray:
    """[N] noise-plus-interference level (dB) of each receiver, as :func:`link_success` computes it."""
    out = np.empty(interference_mw.shape[0])
    for j in range(out.shape[0]):
        out[j] = 10.0 * math.log10(interference_mw[j] + noise_mw)
    return out


@njit(cache=True)
def mover_row_success(
    candidates_m: FloatArray,
    positions_m: FloatArray,
    mover: int,
    period_m: FloatArray,
    los_row: NDArray[np.bool_],
    gain_row_db: FloatArray,
    wb1: FloatArray,
    range2_m2: float,
    interference_mw: FloatArray,
    noise_mw: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
    target_row: NDArray[np.bool_],
) -> FloatArray:
    """[M, N] expected success of ``mover``'s links with the mover at each of M candidate positions.

    The same per-link computation as :func:`snapshot_links` (pair displacement in index order,
    WINNER+ B1, EIRP - shadowing, the receiver's interference from :func:`mover_interference`,
    noise, PER / threshold, sensitivity), so a candidate equal to the mover's position in
    ``positions_m`` reproduces row ``mover`` of :func:`snapshot_links` bit for bit.

    Args:
        candidates_m: [M, 2] positions of the mover to evaluate (m).
        positions_m: [N, 2] positions of every vehicle (the mover's own row is ignored).
        mover: index of the moving transmitter.
        los_row, target_row: row ``mover`` of the arrays of :func:`snapshot_links`.
        gain_row_db: [G, N] EIRP minus the shadowing of the mover's links (dBm): G = 1, row ``mover``
            of :func:`snapshot_links`'s ``gain_db`` for every candidate (the snapshot's shadowing);
            G = M, one row per candidate (a shadowing field that follows the mover,
            :func:`cv2x_marl.sim.kernels.field.field_row_db`).
        interference_mw: [N] :func:`mover_interference` of the mover.
    """
    m_count = candidates_m.shape[0]
    n = positions_m.shape[0]
    level_db = levels_db(interference_mw, noise_mw)
    p = np.zeros((m_count, n))
    per_candidate = gain_row_db.shape[0] > 1
    for m in range(m_count):
        gain_m = gain_row_db[m if per_candidate else 0]
        for j in range(n):
            if target_row[j]:
                s_dbm = moved_signal_dbm(
                    candidates_m[m, 0], candidates_m[m, 1], positions_m, mover, j, period_m, los_row,
                    gain_m, wb1, range2_m2,
                )  # fmt: skip
                p[m, j] = success_at_level(s_dbm, level_db[j], model, per_sinr_db, per, threshold_db, sensitivity_dbm)
    return p


@njit(cache=True)
def mover_row_utility(
    candidates_m: FloatArray,
    positions_m: FloatArray,
    mover: int,
    period_m: FloatArray,
    los_row: NDArray[np.bool_],
    gain_row_db: FloatArray,
    wb1: FloatArray,
    range2_m2: float,
    interference_mw: FloatArray,
    noise_mw: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
    target_row: NDArray[np.bool_],
    p_min: float,
) -> FloatArray:
    """[M] eq. 12 utility of ``mover`` at each candidate (arguments as :func:`mover_row_success`,
    ``gain_row_db`` [G, N]): :func:`row_utility` of :func:`mover_row_success`, fused (no [M, N]
    table; the noise-plus-interference level of each receiver computed once). The same operations
    in the same order, so bit-identical (tested); the global searches of the optimum and the sensing
    plan run on it.
    """
    m_count = candidates_m.shape[0]
    n = positions_m.shape[0]
    level_db = levels_db(interference_mw, noise_mw)
    out = np.zeros(m_count)
    per_candidate = gain_row_db.shape[0] > 1
    for m in range(m_count):
        gain_m = gain_row_db[m if per_candidate else 0]
        u = 0.0
        for j in range(n):
            if target_row[j]:
                s_dbm = moved_signal_dbm(
                    candidates_m[m, 0], candidates_m[m, 1], positions_m, mover, j, period_m, los_row,
                    gain_m, wb1, range2_m2,
                )  # fmt: skip
                x = success_at_level(s_dbm, level_db[j], model, per_sinr_db, per, threshold_db, sensitivity_dbm)
                u += eq12_term(x, p_min)
        out[m] = u
    return out


@njit(cache=True)
def row_utility(p: FloatArray, target_row: NDArray[np.bool_], p_min: float) -> FloatArray:
    """[M] eq. 12 utility ``sum_j ln max(P_mj, p_min)`` over the targets of each row of ``p`` [M, N]
    (the additions of :func:`link_summaries`, in its order)."""
    out = np.zeros(p.shape[0])
    for m in range(p.shape[0]):
        u = 0.0
        for j in range(p.shape[1]):
            if target_row[j]:
                u += eq12_term(p[m, j], p_min)
        out[m] = u
    return out


@njit(cache=True)
def link_summaries(p: FloatArray, target: NDArray[np.bool_], p_min: float) -> FloatArray:
    """[3, N] per transmitter: eq. 12 utility, PRR and Jain's index over its target receivers.

    Row 0: ``sum_{j in R_i} log(max(P_ij, p_min))`` (eq. 12, natural log); row 1: the mean of
    ``P_ij`` over ``R_i``; row 2: Jain's index ``(sum P)^2 / (|R_i| sum P^2)``. Rows 1 and 2 are 0
    where undefined (no targets, or all P = 0). The same quantities as
    :func:`cv2x_marl.utility.utility_log`, :func:`~cv2x_marl.utility.per_node_prr` and
    :func:`~cv2x_marl.utility.jain_fairness` (tested equal) in one pass: each row is
    :func:`cv2x_marl.utility.link_summary`, eq. 12's one compiled definition.

    Args:
        p: [N(tx), N(rx)] link success probabilities.
        target: [N(tx), N(rx)] target receivers ``R_i``.
        p_min: clip of P inside the log.
    """
    out = np.zeros((3, p.shape[0]))
    for i in range(p.shape[0]):
        u, prr, jain, _count = link_summary(p[i], target[i], p_min)
        out[0, i] = u
        out[1, i] = prr
        out[2, i] = jain
    return out
