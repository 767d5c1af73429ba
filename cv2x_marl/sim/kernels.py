"""Compiled (numba) kernels for the hot path of the env: every link of a snapshot in one pass.

The env evaluates all N x N links of a 21-vehicle snapshot once per step. In numpy that is some
40 small array operations whose fixed cost (about 1 us each) dominates; these kernels fuse them
into one compiled pass. They are not a second model. :func:`winner_b1_pair_db` is the one WINNER+
B1 implementation (the simulator calls it through :func:`cv2x_marl.sim.channel.winner_b1_db`) and
is tested against the numpy LOS / NLOS / free-space formulas of ``channel`` and hand values
(``tests/sim/test_channel.py``); :func:`snapshot_links` is tested equal (to 1e-9 relative) to the
numpy composition in :class:`cv2x_marl.sim.evaluate.SnapshotLinks` (``compiled=False``: received
power, interference sums, PER interpolation) and to the simulator's own link outcomes
(``tests/sim/test_evaluate.py``). ``NUMBA_DISABLE_JIT=1`` runs them as plain Python for debugging.

Compiled code is cached on disk (``cache=True``): the first call in a fresh checkout compiles
(a few seconds), later processes load the cache.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.units import SPEED_OF_LIGHT_MPS

FloatArray = NDArray[np.float64]

#: order of the WINNER+ B1 constants in the ``wb1`` argument of :func:`snapshot_links`
WB1_CONSTANTS = ("breakpoint_m", "c_near_db", "c_far_db", "c_nlos_db", "c_free_db", "min_distance_m")
MODEL_PER_TABLE = 0
MODEL_THRESHOLD = 1
#: ``per_table`` with ``link.per_interpolation=log``: ``ln PER`` interpolated linearly in SINR (dB)
MODEL_PER_TABLE_LOG = 2
_DB_TO_NEPER = math.log(10.0) / 10.0


def winner_b1_constants(carrier_hz: float, effective_height_m: float, min_distance_m: float) -> FloatArray:
    """[6] WINNER+ B1 constants (:data:`WB1_CONSTANTS`) of :func:`cv2x_marl.sim.channel.winner_b1_db`.

    Breakpoint ``4 h'^2 f_c / c``; LOS ``22.7 log10 d + 41 + 20 log10(f/5)`` below it and
    ``40 log10 d + 9.45 - 17.3 log10(h'^2) + 2.7 log10(f/5)`` above; NLOS ``PL_LOS(d1) + 20 - 12.5 n
    + 10 n log10 d2 + 3 log10(f/5)``, ``n = max(2.8 - 0.0024 d1, 1.84)``; free space ``20 log10 d +
    46.4 + 20 log10(f/5)`` (IST-WINNER D1.1.2 / 3GPP TR 36.885 A.1.4), f in GHz.
    """
    fc_ghz = carrier_hz / 1e9
    h = effective_height_m
    return np.array(
        [
            4.0 * h * h * carrier_hz / SPEED_OF_LIGHT_MPS,
            41.0 + 20.0 * math.log10(fc_ghz / 5.0),
            9.45 - 34.6 * math.log10(h) + 2.7 * math.log10(fc_ghz / 5.0),
            20.0 + 3.0 * math.log10(fc_ghz / 5.0),
            46.4 + 20.0 * math.log10(fc_ghz / 5.0),
            min_distance_m,
        ]
    )


@njit(cache=True)
def _winner_los_db(d: float, log10_d: float, d_bp: float, c_near: float, c_far: float) -> float:
    if d < d_bp:
        return 22.7 * log10_d + c_near
    return 40.0 * log10_d + c_far


@njit(cache=True)
def winner_b1_pair_db(
    dx_m: float,
    dy_m: float,
    los: bool,
    d_bp: float,
    c_near: float,
    c_far: float,
    c_nlos: float,
    c_free: float,
    dmin: float,
) -> float:
    """WINNER+ B1 loss (dB) of one displacement, LOS or Manhattan NLOS, with the free-space floor
    (constants from :func:`winner_b1_constants`)."""
    d = max(math.sqrt(dx_m * dx_m + dy_m * dy_m), dmin)
    ld = math.log10(d)
    pl = _winner_los_db(d, ld, d_bp, c_near, c_far)
    if not los:
        ax = max(abs(dx_m), dmin)
        ay = max(abs(dy_m), dmin)
        lx = math.log10(ax)
        ly = math.log10(ay)
        nx = max(2.8 - 0.0024 * ax, 1.84)
        ny = max(2.8 - 0.0024 * ay, 1.84)
        n1 = _winner_los_db(ax, lx, d_bp, c_near, c_far) + c_nlos - 12.5 * nx + 10.0 * nx * ly
        n2 = _winner_los_db(ay, ly, d_bp, c_near, c_far) + c_nlos - 12.5 * ny + 10.0 * ny * lx
        pl = min(n1, n2)
    return max(pl, 20.0 * ld + c_free)


@njit(cache=True)
def winner_b1_array_db(dx_m: FloatArray, dy_m: FloatArray, los: NDArray[np.bool_], wb1: FloatArray) -> FloatArray:
    """[K] :func:`winner_b1_pair_db` of K displacements (1-D arrays; ``wb1`` from :func:`winner_b1_constants`)."""
    out = np.empty(dx_m.shape[0])
    for k in range(dx_m.shape[0]):
        out[k] = winner_b1_pair_db(dx_m[k], dy_m[k], los[k], wb1[0], wb1[1], wb1[2], wb1[3], wb1[4], wb1[5])
    return out


@njit(cache=True)
def _per_success(sinr_db: float, per_sinr_db: FloatArray, per: FloatArray, log_domain: bool = False) -> float:
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
def _pair_powers(
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
def _interference_mw(
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
def _success_at_level(
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
        return _per_success(sinr_db, per_sinr_db, per)
    if model == MODEL_PER_TABLE_LOG:
        return _per_success(sinr_db, per_sinr_db, per, True)
    return 1.0 if sinr_db >= threshold_db else 0.0


@njit(cache=True)
def _link_success(
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
    return _success_at_level(s_dbm, level_db, model, per_sinr_db, per, threshold_db, sensitivity_dbm)


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
    disp, dist2, rx_dbm, rx_mw = _pair_powers(positions_m, period_m, los, gain_db, wb1, range2_m2)
    p = np.zeros((n, n))
    for tx in range(n):
        for rx in range(n):
            if not target[tx, rx]:
                continue
            interference = _interference_mw(rx_mw, interferer_idx, interferer_weight, tx, rx)
            p[tx, rx] = _link_success(
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
    _, _, _, rx_mw = _pair_powers(positions_m, period_m, los, gain_db, wb1, range2_m2)
    out = np.zeros(n)
    for rx in range(n):
        out[rx] = _interference_mw(rx_mw, interferer_idx, interferer_weight, mover, rx)
    return out


@njit(cache=True)
def _moved_signal_dbm(
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
def _levels_db(interference_mw: FloatArray, noise_mw: float) -> FloatArray:
    """[N] noise-plus-interference level (dB) of each receiver, as :func:`_link_success` computes it."""
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
        los_row, gain_row_db, target_row: row ``mover`` of the arrays of :func:`snapshot_links`.
        interference_mw: [N] :func:`mover_interference` of the mover.
    """
    m_count = candidates_m.shape[0]
    n = positions_m.shape[0]
    level_db = _levels_db(interference_mw, noise_mw)
    p = np.zeros((m_count, n))
    for m in range(m_count):
        for j in range(n):
            if target_row[j]:
                s_dbm = _moved_signal_dbm(
                    candidates_m[m, 0], candidates_m[m, 1], positions_m, mover, j, period_m, los_row,
                    gain_row_db, wb1, range2_m2,
                )  # fmt: skip
                p[m, j] = _success_at_level(s_dbm, level_db[j], model, per_sinr_db, per, threshold_db, sensitivity_dbm)
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
    """[M] eq. 12 utility of ``mover`` at each candidate: :func:`row_utility` of
    :func:`mover_row_success`, fused (no [M, N] table; the noise-plus-interference level of each
    receiver computed once). The same operations in the same order, so bit-identical (tested); the
    global searches of the optimum and the sensing plan run on it.
    """
    m_count = candidates_m.shape[0]
    n = positions_m.shape[0]
    level_db = _levels_db(interference_mw, noise_mw)
    out = np.zeros(m_count)
    for m in range(m_count):
        u = 0.0
        for j in range(n):
            if target_row[j]:
                s_dbm = _moved_signal_dbm(
                    candidates_m[m, 0], candidates_m[m, 1], positions_m, mover, j, period_m, los_row,
                    gain_row_db, wb1, range2_m2,
                )  # fmt: skip
                x = _success_at_level(s_dbm, level_db[j], model, per_sinr_db, per, threshold_db, sensitivity_dbm)
                u += math.log(max(x, p_min))
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
                u += math.log(max(p[m, j], p_min))
        out[m] = u
    return out


@njit(cache=True)
def link_summaries(p: FloatArray, target: NDArray[np.bool_], p_min: float) -> FloatArray:
    """[3, N] per transmitter: eq. 12 utility, PRR and Jain's index over its target receivers.

    Row 0: ``sum_{j in R_i} log(max(P_ij, p_min))`` (eq. 12, natural log); row 1: the mean of
    ``P_ij`` over ``R_i``; row 2: Jain's index ``(sum P)^2 / (|R_i| sum P^2)``. Rows 1 and 2 are 0
    where undefined (no targets, or all P = 0). The same quantities as
    :func:`cv2x_marl.utility.utility_log`, :func:`~cv2x_marl.utility.per_node_prr` and
    :func:`~cv2x_marl.utility.jain_fairness` (tested equal) in one pass.

    Args:
        p: [N(tx), N(rx)] link success probabilities.
        target: [N(tx), N(rx)] target receivers ``R_i``.
        p_min: clip of P inside the log.
    """
    n_tx, n_rx = p.shape
    out = np.zeros((3, n_tx))
    for i in range(n_tx):
        count = 0
        s1 = 0.0
        s2 = 0.0
        u = 0.0
        for j in range(n_rx):
            if target[i, j]:
                x = p[i, j]
                count += 1
                s1 += x
                s2 += x * x
                u += math.log(max(x, p_min))
        out[0, i] = u
        if count > 0:
            out[1, i] = s1 / count
            if s2 > 0.0:
                out[2, i] = s1 * s1 / (count * s2)
    return out


@njit(cache=True)
def _grow(a: NDArray[np.int64], size: int) -> NDArray[np.int64]:
    out = np.empty(size, dtype=np.int64)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def _min_image(d: float, box: float) -> float:
    if math.isfinite(box):
        return d - box * round(d / box)
    return d


@njit(cache=True)
def pairs_within_range(
    pos_m: FloatArray, box_m: FloatArray, range_m: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Unordered vehicle pairs at most ``range_m`` apart, sorted by ``(i, j)``, ``i < j``.

    A sweep over the vehicles sorted along x (wrapped when the x axis is periodic): for each vehicle,
    the others within ``range_m`` along x ahead and behind (each at most once, so a ring shorter than
    twice the range is fine), kept when the minimum-image distance satisfies ``dx^2 + dy^2 <= r^2``.
    The pairs of scipy's KD-tree query (``query_pairs``, tested), in ``(i, j)`` order; cost
    ``O(N log N + N k)`` with k the vehicles within range along x.

    Args:
        pos_m: [N, 2] positions, m.
        box_m: [2] period of each axis, m (inf: not periodic).
        range_m: the cut-off, m.

    Returns:
        ``(i, j)``, each [P] int64.
    """
    n = pos_m.shape[0]
    bx, by = box_m[0], box_m[1]
    px = math.isfinite(bx)
    x = pos_m[:, 0].copy()
    if px:
        x = x - bx * np.floor(x / bx)
    order = np.argsort(x, kind="mergesort")
    sx = x[order]
    rank = np.empty(n, dtype=np.int64)
    rank[order] = np.arange(n)
    r2 = range_m * range_m
    slack = range_m * (1.0 + 1e-9) + 1e-9  # the sweep along x never cuts a pair the distance test keeps
    cap = max(1024, 16 * n)
    out_i = np.empty(cap, dtype=np.int64)
    out_j = np.empty(cap, dtype=np.int64)
    tmp = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        k = rank[i]
        cnt = 0
        visited = 0
        for s in range(1, n):
            kk = k + s
            shift = 0.0
            if kk >= n:
                if not px:
                    break
                kk -= n
                shift = bx
            if sx[kk] + shift - sx[k] > slack:
                break
            visited += 1
            j = order[kk]
            if j > i:
                dx = _min_image(pos_m[j, 0] - pos_m[i, 0], bx)
                dy = _min_image(pos_m[j, 1] - pos_m[i, 1], by)
                if dx * dx + dy * dy <= r2:
                    tmp[cnt] = j
                    cnt += 1
        for s in range(1, n - visited):
            kk = k - s
            shift = 0.0
            if kk < 0:
                if not px:
                    break
                kk += n
                shift = bx
            if sx[k] + shift - sx[kk] > slack:
                break
            j = order[kk]
            if j > i:
                dx = _min_image(pos_m[j, 0] - pos_m[i, 0], bx)
                dy = _min_image(pos_m[j, 1] - pos_m[i, 1], by)
                if dx * dx + dy * dy <= r2:
                    tmp[cnt] = j
                    cnt += 1
        if m + cnt > cap:
            cap = max(2 * cap, m + cnt)
            out_i = _grow(out_i, cap)
            out_j = _grow(out_j, cap)
        row = np.sort(tmp[:cnt])
        for c in range(cnt):
            out_i[m + c] = i
            out_j[m + c] = row[c]
        m += cnt
    return out_i[:m].copy(), out_j[:m].copy()


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
_LIN_MARGIN = 1e-9


@njit(cache=True)
def _db_below(x: float, x_lin_threshold: float, threshold_db: float) -> bool:
    """``10 log10(x) < threshold_db`` with the logarithm taken only within :data:`_LIN_MARGIN` of the
    threshold (``x_lin_threshold = 10^(threshold_db / 10)``): the same answer, most often without it."""
    if x < x_lin_threshold * (1.0 - _LIN_MARGIN):
        return True
    if x > x_lin_threshold * (1.0 + _LIN_MARGIN):
        return False
    return 10.0 * math.log10(x) < threshold_db


@njit(cache=True)
def _success_of_ratio(
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
    table (:func:`_per_success` on ``10 log10(ratio)``, numpy's dB value), the logarithm taken
    only when the ratio is within the table (``per_lin_lo``, ``per_lin_hi``: its ends in linear
    units) or near the threshold: outside, the constant the dB formula gives."""
    if model == MODEL_THRESHOLD:
        return 0.0 if _db_below(ratio, threshold_lin, threshold_db) else 1.0
    if ratio < per_lin_lo * (1.0 - _LIN_MARGIN):
        return 0.0
    if ratio > per_lin_hi * (1.0 + _LIN_MARGIN):
        return 1.0 - per[per.shape[0] - 1]
    return _per_success(10.0 * math.log10(ratio), per_sinr_db, per, model == MODEL_PER_TABLE_LOG)


@njit(cache=True)
def _interp_clamped(x: float, xp: FloatArray, fp: FloatArray, left: float, right: float) -> float:
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


#: bytes of one tile's power-sum scratch in :func:`period_chunk` (N receivers x the tile's resources,
#: float64; the tile's SCI maxima take as much again): one subframe per tile from about 820 vehicles with
#: 5 subchannels (2**16 // (8 x 5 N)) (measured fastest at 2,000 and 10,000 vehicles, against 2-6 subframes); a small
#: scenario runs a few tiles of many subframes
CHUNK_TILE_BYTES = 2**16


def chunk_tile_subframes(n: int, n_sub: int, rri: int, tile_bytes: int | None = None) -> int:
    """Subframes per tile of :func:`period_chunk`: as many as keep the tile's scratch (``8 N n_sub`` bytes per
    subframe) within ``tile_bytes`` (default :data:`CHUNK_TILE_BYTES`, read at the call), at least 1, at most
    ``rri`` (one tile: the whole period)."""
    budget = CHUNK_TILE_BYTES if tile_bytes is None else tile_bytes
    return max(1, min(rri, budget // max(1, 8 * n * n_sub)))


@njit(cache=True)
def period_chunk(
    rx: NDArray[np.int64],
    tx: NDArray[np.int64],
    distance_m: FloatArray,
    rx_mw: FloatArray,
    active: NDArray[np.bool_],
    resource: NDArray[np.int64],
    slot: NDArray[np.int64],
    n_res: int,
    noise_mw: float,
    link_rng: np.random.Generator,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
    releasing: NDArray[np.bool_],
    period_rssi_mw: FloatArray,
    period_sci_mw: FloatArray,
    bin_m: float,
    n_bins: int,
    n_causes: int,
    subset: bool,
    links: NDArray[np.int64],
    total: FloatArray,
    sci_rng: np.random.Generator,
    sci_sinr_lin: FloatArray,
    sci_bler: FloatArray,
    sci_offset_db: float,
    sci_gates_pssch: bool,
    n_sub: int,
    flat_inband_lin: float,
    total_slot: FloatArray,
    leakage: FloatArray,
    tile_subframes: int,
) -> tuple[
    NDArray[np.int64],
    NDArray[np.int64],
    FloatArray,
    NDArray[np.int8],
    NDArray[np.int64],
    NDArray[np.int64],
    FloatArray,
    NDArray[np.int64],
    NDArray[np.int64],
    NDArray[np.int64],
    FloatArray,
]:
    """One chunk of the simulator's period (``Simulator._chunk``) in compiled passes over the links, tile by tile.

    Pass 1: the power each receiver gets on each resource from the active transmitters,
    ``total[rx * n_res + resource[tx]] += rx_mw`` in link order (``np.bincount``'s additions, so equal
    to the last bit; flat in-band: the same per receiver and subframe). Pass 2, for each link whose
    transmitter is active, in order: interference ``I = max(total - S, 0)`` on the link's resource,
    ``SINR = S / (I + N)``, one uniform ``u`` from ``link_rng`` (the numpy path's
    ``rng.link.random(L)``, drawn in the same order: the same numbers), success ``P`` (``model``:
    per_table linear / log on the dB SINR, threshold) and ``P0`` (on the SNR), outcome ``u < P`` and
    cause (half duplex, below sensitivity, propagation ``u >= P0``, collision), the strongest decodable
    SCI per receiver and resource (``period_sci_mw``, linear: the sensing takes its RSRP in dBm when it
    reads it; a releasing UE's SCI reserves nothing, TS 36.213 14.1.1.6) and the PRR accumulators of
    :class:`cv2x_marl.sim.metrics.PrrAccumulator`. Last, ``total`` (and the 3gpp leakage) is added to the
    period's S-RSSI ``period_rssi_mw`` and the scratches are zeroed. The dB values (``10 log10``: libm's, equal to
    numpy's on the CPUs tested) are taken only where a comparison needs them (:func:`_db_below`,
    :func:`_success_of_ratio`): equal to the numpy path (tested), at a fraction of the cost when most
    links are far below the PER table.

    Tiles: every sum of a key (receiver, resource) comes from transmitters on that resource, hence from
    one subframe, and the flat model's sums and the 3gpp leakage read only the same receiver's subframe.
    So the links are gathered by their transmitter's tile of ``tile_subframes`` subframes (a stable
    counting sort: increasing link order within a tile), the uniforms drawn in link order as they are
    gathered, and passes 1 and 2 and the S-RSSI / SCI commit run tile by tile on an ``N x tile``
    scratch (the first entries of ``total``, cache-sized at corridor scale instead of ``N x n_res``):
    each key's additions happen in the same order as in one pass over the chunk, so the same bits.
    A last pass in link order writes the outputs and sums the PRR accumulators (float sums in link
    order). Memory beyond the outputs: 9 B per link (the tile-ordered ``P`` and cause; the other
    tile-ordered inputs live in the outputs' arrays until that pass) and ``8 N tile n_sub`` bytes.

    Args:
        rx, tx, distance_m, rx_mw: [L_all] the period's ordered pairs, their distance (m) and received
            power (mW, faded).
        active, resource, slot, releasing: [N] per vehicle.
        n_res: resources per period.
        noise_mw: noise power, mW.
        link_rng: the simulator's ``link`` stream (advanced by one draw per active link).
        model: :data:`MODEL_PER_TABLE`, :data:`MODEL_PER_TABLE_LOG` or :data:`MODEL_THRESHOLD`.
        per_sinr_db, per: [K] the PER table.
        threshold_db: SINR threshold of the threshold model, dB.
        sensitivity_dbm: received power below which a link fails (-inf: none), dBm.
        period_rssi_mw: [N * n_res] the period's S-RSSI sums, updated in place.
        period_sci_mw: [N * n_res] the period's strongest decoded SCI (PSSCH power, mW), in place.
        bin_m, n_bins, n_causes: the accumulator's distance bins and causes.
        subset, links: with ``subset``, ``links`` are the indices of the links whose transmitter is
            active, increasing (from :func:`active_links`: a chunk of a few transmitters visits only their
            links, possibly none); without, every link is visited and checked against ``active``.
        total: [N * n_res] zeros, a scratch for the power sums (the first ``N * tile_subframes * n_sub``
            entries used): left zero again on return.
        sci_rng, sci_sinr_lin, sci_bler, sci_offset_db: ``sps.sci_decoding=sinr``: the SCI stream (one
            draw per active link, as ``Simulator._sci_draws``), the PSCCH BLER curve (points in linear
            SINR, :class:`cv2x_marl.sim.link.PscchCurve`) and ``sps.sci_sinr_offset_db``; an SCI counts
            only if ``u < 1 - BLER(SINR + offset)``. Empty curve: every SCI (``always``).
        sci_gates_pssch: ``sps.sci_gates_pssch``: a link succeeds only if its SCI decodes too (``P`` times
            the SCI's decoding probability; ``P0`` likewise with the SCI at the SNR).
        n_sub: subchannels per subframe (resource ``r`` is slot ``r // n_sub``, subchannel ``r % n_sub``).
        flat_inband_lin: ``link.inband_emission_db`` in linear units (flat in-band emission: that share of
            the power of the subframe's other subchannels adds to the interference); 0: none.
        total_slot: [N * RRI] zeros, the scratch for the flat model's power per receiver and subframe
            (summed link by link, as the numpy path's ``bincount``): left zero again on return.
        leakage: [n_sub, n_sub] the 3gpp in-band leakage ``M[victim, interferer]``
            (:func:`cv2x_marl.sim.inband.pool_leakage_weights`), empty: none. The leakage into subchannel
            ``v`` of a receiver's subframe, ``sum_i M[v, i] total[i]`` (summed in ``i`` order, as
            ``Simulator._chunk``), adds to the interference and to the S-RSSI.
        tile_subframes: subframes per tile (:func:`chunk_tile_subframes`), >= 1; any value gives the same
            results.

    Returns:
        ``tx, rx, p, cause`` [L] of the active links, then the chunk's ``bin_n, bin_decoded,
        bin_expected`` [n_bins], ``bin_causes`` [n_causes * n_bins] (cause-major), ``node_n,
        node_decoded, node_expected`` [N].
    """
    n = active.shape[0]
    n_visit = links.shape[0] if subset else rx.shape[0]
    rri = n_res // n_sub
    n_tiles = (rri + tile_subframes - 1) // tile_subframes
    width = tile_subframes * n_sub  # resources per tile (the last tile may hold fewer)
    # per vehicle (no division per link): its tile (-1: not transmitting in the chunk), its resource,
    # subchannel and subframe within the tile
    veh = np.full((n, 4), -1, dtype=np.int32)
    for t in range(n):
        if active[t]:
            g = resource[t] // width
            veh[t, 0] = g
            veh[t, 1] = resource[t] - g * width
            veh[t, 2] = resource[t] % n_sub
            veh[t, 3] = resource[t] // n_sub - g * tile_subframes
    # the chunk's active links counted per tile (the transmitter's subframe // tile_subframes) ...
    tile_start = np.zeros(n_tiles + 1, dtype=np.int64)
    for q in range(n_visit):
        k = links[q] if subset else q
        g = veh[tx[k], 0]
        if g >= 0:
            tile_start[g + 1] += 1
    for g in range(n_tiles):
        tile_start[g + 1] += tile_start[g]
    n_links = tile_start[n_tiles]
    out_tx = np.empty(n_links, dtype=np.int64)
    out_rx = np.empty(n_links, dtype=np.int64)
    p_out = np.empty(n_links)
    cause_out = np.empty(n_links, dtype=np.int8)
    # ... and gathered tile by tile (a stable counting sort: increasing link order within a tile), with
    # the uniforms drawn in link order. The outputs' memory holds the tile-ordered inputs until the
    # final pass writes the outputs: receiver and transmitter (int32 pairs) in out_tx, power in p_out,
    # the SCI uniform in out_rx; the PSSCH uniform, then P, and the cause in their own arrays.
    tile_rt = out_tx.view(np.int32)
    tile_s = p_out
    tile_u_sci = out_rx.view(np.float64)
    tile_u = np.empty(n_links)  # the PSSCH uniform, then P
    tile_cause = np.empty(n_links, dtype=np.int8)
    sci_sinr = sci_bler.shape[0] > 0
    fill = tile_start[:n_tiles].copy()
    for q in range(n_visit):
        k = links[q] if subset else q
        t = tx[k]
        g = veh[t, 0]
        if g >= 0:
            j = fill[g]
            fill[g] = j + 1
            tile_rt[2 * j] = rx[k]
            tile_rt[2 * j + 1] = t
            tile_s[j] = rx_mw[k]
            tile_u[j] = link_rng.random()
            if sci_sinr:  # the SCI draw is taken for every link, as the numpy path's
                tile_u_sci[j] = sci_rng.random()
    flat = flat_inband_lin > 0.0
    three_gpp = leakage.shape[0] > 0
    k_per = per_sinr_db.shape[0]
    lin_lo = 10.0 ** (per_sinr_db[0] / 10.0)
    lin_hi = 10.0 ** (per_sinr_db[k_per - 1] / 10.0)
    thr_lin = 10.0 ** (threshold_db / 10.0)
    sens_lin = 10.0 ** (sensitivity_dbm / 10.0)  # 0.0 for -inf
    sci_lo, sci_hi = 0.0, 0.0  # the PSCCH curve's ends as linear SINR before the offset
    if sci_sinr:
        sci_lo = sci_sinr_lin[0] / 10.0 ** (sci_offset_db / 10.0)
        sci_hi = sci_sinr_lin[sci_sinr_lin.shape[0] - 1] / 10.0 ** (sci_offset_db / 10.0)
    # a tile's scratches: the power sums per receiver and resource of the tile (the first N x width
    # entries of total), the flat model's per receiver and subframe (of total_slot), the SCI maxima
    sum_t = total[: n * width]
    slot_t = total_slot[: n * tile_subframes] if flat else total_slot
    sci_t = np.zeros(n * width)
    leak_row = np.empty(n_sub)
    for g in range(n_tiles):
        lo, hi = tile_start[g], tile_start[g + 1]
        if lo == hi:
            continue
        res0 = g * width  # the tile's first resource
        n_slots = min(rri, (g + 1) * tile_subframes) - g * tile_subframes
        # pass 1: the sums, in link order
        for j in range(lo, hi):
            r = tile_rt[2 * j]
            t = tile_rt[2 * j + 1]
            sum_t[r * width + veh[t, 1]] += tile_s[j]
            if flat:
                slot_t[r * tile_subframes + veh[t, 3]] += tile_s[j]
        # pass 2: each link's outcome
        for j in range(lo, hi):
            r = tile_rt[2 * j]
            t = tile_rt[2 * j + 1]
            sub = veh[t, 2]
            key = r * width + veh[t, 1]
            s = tile_s[j]
            i_mw = max(sum_t[key] - s, 0.0)
            if flat:
                i_mw = i_mw + flat_inband_lin * max(slot_t[r * tile_subframes + veh[t, 3]] - sum_t[key], 0.0)
            if three_gpp:
                i_mw = i_mw + _leak_mw(sum_t, key - sub, leakage, sub, n_sub)
            u = tile_u[j]
            ratio = s / (i_mw + noise_mw)
            p = _success_of_ratio(ratio, model, per_sinr_db, per, lin_lo, lin_hi, threshold_db, thr_lin)
            outcome = u < p
            sci_decoded = True
            u_sci = 0.0
            if sci_sinr:
                p_sci = _sci_probability(ratio, sci_offset_db, sci_sinr_lin, sci_bler, sci_lo, sci_hi)
                u_sci = tile_u_sci[j]
                sci_decoded = u_sci < p_sci
                if sci_gates_pssch:  # the PSSCH needs its SCI: both decode, P the product
                    outcome = outcome and sci_decoded
                    p = p * p_sci
            would0 = True  # read only when the link fails: then P0 decides propagation or collision
            if not outcome:
                p0 = _success_of_ratio(s / noise_mw, model, per_sinr_db, per, lin_lo, lin_hi, threshold_db, thr_lin)
                would0 = u < p0
                if sci_gates_pssch:
                    would0 = would0 and u_sci < _sci_probability(
                        s / noise_mw, sci_offset_db, sci_sinr_lin, sci_bler, sci_lo, sci_hi
                    )
            hd = slot[r] == slot[t]
            below = sensitivity_dbm > -np.inf and _db_below(s, sens_lin, sensitivity_dbm)
            fail = hd or below
            if fail:
                p = 0.0
                outcome = False
            c = 0
            if not outcome:
                c = 4 if would0 else 3  # collision, propagation
            if below:
                c = 2
            if hd:
                c = 1
            if not fail and not releasing[t] and sci_decoded and s > sci_t[key]:
                sci_t[key] = s
            tile_u[j] = p
            tile_cause[j] = c
        # the tile's S-RSSI and SCI maxima into the period's, the scratches zeroed again: a tile with fewer
        # links than receiver-subframes through its links (each receiver's subframe once), a larger one
        # by a scan of the scratches in order
        if hi - lo < n * n_slots:
            for j in range(lo, hi):
                r = tile_rt[2 * j]
                t = tile_rt[2 * j + 1]
                sub = veh[t, 2]
                key = r * width + veh[t, 1]
                if flat:
                    slot_t[r * tile_subframes + veh[t, 3]] = 0.0
                _commit_rssi(
                    sum_t,
                    key - sub,
                    period_rssi_mw,
                    r * n_res + res0 + veh[t, 1] - sub,
                    leakage,
                    n_sub,
                    three_gpp,
                    leak_row,
                )
                if sci_t[key] > period_sci_mw[r * n_res + res0 + veh[t, 1]]:
                    period_sci_mw[r * n_res + res0 + veh[t, 1]] = sci_t[key]
                sci_t[key] = 0.0
        else:
            for r in range(n):
                for a in range(n_slots):
                    _commit_rssi(
                        sum_t,
                        r * width + a * n_sub,
                        period_rssi_mw,
                        r * n_res + res0 + a * n_sub,
                        leakage,
                        n_sub,
                        three_gpp,
                        leak_row,
                    )
                for e in range(n_slots * n_sub):
                    if sci_t[r * width + e] > period_sci_mw[r * n_res + res0 + e]:
                        period_sci_mw[r * n_res + res0 + e] = sci_t[r * width + e]
                    sci_t[r * width + e] = 0.0
            if flat:
                slot_t[: n * tile_subframes] = 0.0
    # the outputs and the PRR accumulators in link order (the tiles' outputs merged back: the float sums
    # in the order of the numpy path)
    bin_n = np.zeros(n_bins, dtype=np.int64)
    bin_dec = np.zeros(n_bins, dtype=np.int64)
    bin_exp = np.zeros(n_bins)
    bin_causes = np.zeros(n_causes * n_bins, dtype=np.int64)
    node_n = np.zeros(n, dtype=np.int64)
    node_dec = np.zeros(n, dtype=np.int64)
    node_exp = np.zeros(n)
    fill[:] = tile_start[:n_tiles]
    m = 0
    for q in range(n_visit):
        k = links[q] if subset else q
        t = tx[k]
        g = veh[t, 0]
        if g < 0:
            continue
        j = fill[g]
        fill[g] = j + 1
        p = tile_u[j]
        c = tile_cause[j]
        outcome = c == 0
        out_tx[m] = t
        out_rx[m] = rx[k]
        p_out[m] = p
        cause_out[m] = c
        b = math.floor(distance_m[k] / bin_m)  # numba: an int64
        if b < n_bins:
            bin_n[b] += 1
            bin_dec[b] += outcome
            bin_exp[b] += p
            bin_causes[c * n_bins + b] += 1
        if c != 1:
            node_n[t] += 1
            node_dec[t] += outcome
            node_exp[t] += p
        m += 1
    return out_tx, out_rx, p_out, cause_out, bin_n, bin_dec, bin_exp, bin_causes, node_n, node_dec, node_exp


@njit(cache=True)
def _sci_probability(
    ratio: float, offset_db: float, sinr_lin: FloatArray, bler: FloatArray, ratio_lo: float, ratio_hi: float
) -> float:
    """``1 - BLER(10 log10(ratio) + offset)`` of the PSCCH curve (points ``sinr_lin`` in linear units),
    :meth:`cv2x_marl.sim.link.PscchCurve.decoding_probability`'s arithmetic (0 for NaN). Outside the
    curve, the constant that arithmetic gives (0 below: BLER 1; ``1 - bler[-1]`` above) without the
    logarithm and the power: ``ratio_lo``, ``ratio_hi`` are the curve's ends as linear SINR before the
    offset (``sinr_lin[0] / 10^(offset / 10)``, ``sinr_lin[-1] / 10^(offset / 10)``), and within
    :data:`_LIN_MARGIN` of them the exact arithmetic decides."""
    if ratio < ratio_lo * (1.0 - _LIN_MARGIN):
        return 0.0
    if ratio > ratio_hi * (1.0 + _LIN_MARGIN):
        return 1.0 - bler[-1]
    x = 10.0 * math.log10(ratio) + offset_db
    if math.isnan(x):
        return 0.0
    return 1.0 - _interp_clamped(10.0 ** (x / 10.0), sinr_lin, bler, 1.0, bler[-1])


@njit(cache=True)
def _commit_rssi(
    total: FloatArray,
    base: int,
    period_rssi_mw: FloatArray,
    rssi_base: int,
    leakage: FloatArray,
    n_sub: int,
    three_gpp: bool,
    leak_row: FloatArray,
) -> None:
    """Add one receiver's subframe (``total[base : base + n_sub]``) to the period's S-RSSI
    (``period_rssi_mw[rssi_base : rssi_base + n_sub]``) and zero it: ``rssi + total`` entry by entry, then
    (3gpp) ``+ leak`` into every subchannel of a subframe that heard something (the numpy path's
    ``rssi += total; rssi += leak``: the same bits); ``leak_row`` [n_sub] is scratch."""
    if three_gpp:
        heard = False
        for v in range(n_sub):
            heard = heard or total[base + v] != 0.0
        if not heard:
            return
        for v in range(n_sub):
            leak_row[v] = _leak_mw(total, base, leakage, v, n_sub)
        for v in range(n_sub):
            period_rssi_mw[rssi_base + v] = (period_rssi_mw[rssi_base + v] + total[base + v]) + leak_row[v]
            total[base + v] = 0.0
        return
    for v in range(n_sub):
        if total[base + v] != 0.0:
            period_rssi_mw[rssi_base + v] += total[base + v]
            total[base + v] = 0.0


@njit(cache=True)
def _leak_mw(total: FloatArray, base: int, leakage: FloatArray, victim: int, n_sub: int) -> float:
    """In-band leakage into subchannel ``victim`` of one receiver's subframe: ``sum_i M[victim, i]
    total[base + i]``, summed in ``i`` order (``Simulator._inband_leakage``'s arithmetic)."""
    acc = total[base] * leakage[victim, 0]
    for i in range(1, n_sub):
        acc = acc + total[base + i] * leakage[victim, i]
    return acc


@njit(cache=True)
def links_by_transmitter(tx: NDArray[np.int64], n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The period's links grouped by transmitter (a counting sort, ``O(L + N)``).

    Args:
        tx: [L] the transmitter of each link.
        n: N.

    Returns:
        ``start`` [N + 1] and ``index`` [L]: the links of transmitter ``t`` are
        ``index[start[t]:start[t + 1]]``, increasing.
    """
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(tx.shape[0]):
        start[tx[k] + 1] += 1
    for t in range(n):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    index = np.empty(tx.shape[0], dtype=np.int64)
    for k in range(tx.shape[0]):
        t = tx[k]
        index[fill[t]] = k
        fill[t] += 1
    return start, index


@njit(cache=True)
def active_links(start: NDArray[np.int64], index: NDArray[np.int64], senders: NDArray[np.int64]) -> NDArray[np.int64]:
    """The links of the transmitters ``senders``, in increasing link order (the order the numpy period
    visits them in), from :func:`links_by_transmitter`'s grouping.

    Args:
        start, index: :func:`links_by_transmitter`.
        senders: [A] the transmitters of a chunk.

    Returns:
        [L_A] link indices, increasing.
    """
    count = 0
    for a in range(senders.shape[0]):
        count += start[senders[a] + 1] - start[senders[a]]
    out = np.empty(count, dtype=np.int64)
    m = 0
    for a in range(senders.shape[0]):
        t = senders[a]
        for q in range(start[t], start[t + 1]):
            out[m] = index[q]
            m += 1
    radix_sort(out, index.shape[0])
    return out


@njit(cache=True)
def radix_sort(a: NDArray[np.int64], bound: int) -> None:
    """Sort ``a`` in place, ascending, for values in ``[0, bound)``: an LSD radix sort in 12-bit digits
    (two passes below 2^24, each a count and a stable scatter: ``O(len(a))``; numba's quicksort costs
    ``O(len(a) log len(a))`` with a branch miss per comparison). Short arrays use ``a.sort()``.

    Args:
        a: [M] int64, each in ``[0, bound)``.
        bound: one past the largest value ``a`` may hold.
    """
    n = a.shape[0]
    if n < 256:
        a.sort()
        return
    bits = 1
    while (1 << bits) < bound:
        bits += 1
    src = a
    dst = np.empty_like(a)
    count = np.empty(4097, dtype=np.int64)
    shift = 0
    swapped = False
    while shift < bits:
        count[:] = 0
        for i in range(n):
            count[((src[i] >> shift) & 4095) + 1] += 1
        for d in range(4096):
            count[d + 1] += count[d]
        for i in range(n):
            d = (src[i] >> shift) & 4095
            dst[count[d]] = src[i]
            count[d] += 1
        src, dst = dst, src
        swapped = not swapped
        shift += 12
    if swapped:  # the last pass wrote into the scratch
        a[:] = src


@njit(cache=True)
def pair_geometry(
    pos_m: FloatArray, vel_mps: FloatArray, i: NDArray[np.int64], j: NDArray[np.int64], box_m: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Displacement, distance and relative speed of the pairs ``(i, j)`` in one pass.

    The numpy path's arithmetic element by element: ``pos[j] - pos[i]`` folded onto the torus where an
    axis is periodic (``d - box * round(d / box)``, round half to even as ``np.round``), ``hypot`` of it,
    and ``hypot`` of ``vel[i] - vel[j]``: equal to the last bit.

    Args:
        pos_m: [N, 2] positions, m.
        vel_mps: [N, 2] velocities, m/s.
        i, j: [P] the pairs.
        box_m: [2] period of each axis, m (inf: not periodic, or distances not wrapped).

    Returns:
        ``dx, dy, distance`` [P] (m) and relative speed [P] (m/s).
    """
    p = i.shape[0]
    dx = np.empty(p)
    dy = np.empty(p)
    dist = np.empty(p)
    rel = np.empty(p)
    bx, by = box_m[0], box_m[1]
    for k in range(p):
        a, b = i[k], j[k]
        x = _min_image(pos_m[b, 0] - pos_m[a, 0], bx)
        y = _min_image(pos_m[b, 1] - pos_m[a, 1], by)
        dx[k] = x
        dy[k] = y
        dist[k] = math.hypot(x, y)
        rel[k] = math.hypot(vel_mps[a, 0] - vel_mps[b, 0], vel_mps[a, 1] - vel_mps[b, 1])
    return dx, dy, dist, rel


@njit(cache=True)
def shadowing_update_dense(
    z_flat: FloatArray,
    last_flat: FloatArray,
    a: NDArray[np.int64],
    b: NDArray[np.int64],
    n: int,
    reference: FloatArray,
    normals: FloatArray,
    decorrelation_m: float,
    pair_distance: bool,
) -> FloatArray:
    """The AR(1) step of :class:`cv2x_marl.sim.channel.Shadowing` for the pairs ``(a, b)``, in place.

    ``rho = exp(-D / d_c)`` with ``D = reference - last`` (``travelled``: odometer sums) or
    ``|reference - last|`` (``pair_distance``: pair distances; 0 at a first read, ``last`` NaN);
    ``z = rho z_last + sqrt(1 - rho^2) w`` with ``w`` = ``normals``; ``z`` and ``reference`` stored at
    ``(a, b)`` and ``(b, a)``. The numpy path's arithmetic, element by element (equal to the last bit).

    Args:
        z_flat, last_flat: [N * N] the state, updated in place.
        a, b: [P] the pairs.
        n: N.
        reference: [P] the odometer sum or the pair distance now, m.
        normals: [P] standard normal innovations.
        decorrelation_m: d_c, m.
        pair_distance: which distance D is.

    Returns:
        [P] the pairs' unit-variance shadowing.
    """
    p = a.shape[0]
    z = np.empty(p)
    for k in range(p):
        ab = a[k] * n + b[k]
        ba = b[k] * n + a[k]
        if pair_distance:
            change = abs(reference[k] - last_flat[ab])
            rho = math.exp(-(0.0 if math.isnan(change) else change) / decorrelation_m)
        else:
            rho = math.exp(-(reference[k] - last_flat[ab]) / decorrelation_m)
        v = rho * z_flat[ab] + math.sqrt(1.0 - rho * rho) * normals[k]
        z[k] = v
        z_flat[ab] = v
        z_flat[ba] = v
        last_flat[ab] = reference[k]
        last_flat[ba] = reference[k]
    return z


@njit(cache=True)
def received_powers(
    eirp_dbm: float,
    path_loss_db: FloatArray,
    z: FloatArray,
    los: NDArray[np.bool_],
    std_los_db: float,
    std_nlos_db: float,
    gains: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Mean received power of the unordered pairs and the faded power of both directions.

    ``mean = EIRP - (PL + sigma(LOS) z)`` (dBm; ``z`` empty: no shadowing), ``10^(mean / 10)`` (mW)
    for both directions (the pairs ``(i, j)`` then ``(j, i)``), times the Rayleigh gains ``gains``
    [2P] (empty: no fading). The numpy path's arithmetic (equal to the last bit).

    Returns:
        ``mean_dbm`` [P] and ``rx_mw`` [2P].
    """
    p = path_loss_db.shape[0]
    mean = np.empty(p)
    out = np.empty(2 * p)
    shadow = z.shape[0] > 0
    faded = gains.shape[0] > 0
    for k in range(p):
        pl = path_loss_db[k]
        if shadow:
            pl = pl + (std_los_db if los[k] else std_nlos_db) * z[k]
        m = eirp_dbm - pl
        mean[k] = m
        w = 10.0 ** (m / 10.0)
        out[k] = w * gains[k] if faded else w
        out[p + k] = w * gains[p + k] if faded else w
    return mean, out


@njit(cache=True)
def shadowing_update_sparse(
    keys_prev: NDArray[np.int64],
    z_state: FloatArray,
    last_state: FloatArray,
    keys: NDArray[np.int64],
    reference: FloatArray,
    decorrelation_m: float,
    pair_distance: bool,
    rng: np.random.Generator,
) -> FloatArray:
    """The AR(1) step of :class:`cv2x_marl.sim.channel.SparseShadowing` for the pairs ``keys``.

    A merge of the two ascending key lists finds each pair's last read (the numpy path's
    ``searchsorted``); a pair not in the state gets a fresh ``Z`` (one ``rng`` normal each, in pair
    order, before the update's innovations: the numpy path's ``standard_normal(n_new)`` then
    ``standard_normal(P)``, the same numbers) and ``last`` 0 (``travelled``) or none (``pair_distance``:
    ``rho = 1``); then ``z = rho z_last + sqrt(1 - rho^2) w`` as :func:`shadowing_update_dense`.

    Args:
        keys_prev: [Q] the state's pair keys, strictly ascending.
        z_state, last_state: [Q] their Z and last reference.
        keys: [P] this read's pair keys, strictly ascending.
        reference: [P] odometer sums (``travelled``) or pair distances (``pair_distance``), m.
        decorrelation_m: d_c, m.
        pair_distance: which distance D is.
        rng: the channel stream.

    Returns:
        [P] the pairs' unit-variance shadowing.
    """
    m = keys.shape[0]
    q = keys_prev.shape[0]
    pos = np.full(m, -1, dtype=np.int64)
    j = 0
    for k in range(m):
        while j < q and keys_prev[j] < keys[k]:
            j += 1
        if j < q and keys_prev[j] == keys[k]:
            pos[k] = j
    z_prev = np.empty(m)
    for k in range(m):  # fresh draws first, in pair order
        if pos[k] < 0:
            z_prev[k] = rng.standard_normal()
        else:
            z_prev[k] = z_state[pos[k]]
    z = np.empty(m)
    for k in range(m):
        if pair_distance:
            change = abs(reference[k] - last_state[pos[k]]) if pos[k] >= 0 else math.nan
            rho = math.exp(-(0.0 if math.isnan(change) else change) / decorrelation_m)
        else:
            last = last_state[pos[k]] if pos[k] >= 0 else 0.0
            rho = math.exp(-(reference[k] - last) / decorrelation_m)
        z[k] = rho * z_prev[k] + math.sqrt(1.0 - rho * rho) * rng.standard_normal()
    return z


@njit(cache=True)
def filter_pairs_within_range(
    pos_m: FloatArray, box_m: FloatArray, range_m: float, cand_i: NDArray[np.int32], cand_j: NDArray[np.int32]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """The candidate pairs at most ``range_m`` apart, in candidate order: a Verlet list's step.

    The acceptance test is :func:`pairs_within_range`'s, to the bit (minimum-image ``dx``, ``dy``,
    ``dx^2 + dy^2 <= r^2``), so when the candidates hold every pair in range, sorted by ``(i, j)``
    (``pairs_within_range`` at a larger radius, while no vehicle has moved more than half the
    difference since), the result equals ``pairs_within_range(pos_m, box_m, range_m)``.

    Args:
        pos_m: [N, 2] positions, m.
        box_m: [2] period of each axis, m (inf: not periodic).
        range_m: the cut-off, m.
        cand_i, cand_j: [C] candidate pairs, ``i < j`` (int32: the list is kept between periods).

    Returns:
        ``(i, j)``, each [P] int64, ``P <= C``.
    """
    bx, by = box_m[0], box_m[1]
    r2 = range_m * range_m
    c = cand_i.shape[0]
    out_i = np.empty(c, dtype=np.int64)
    out_j = np.empty(c, dtype=np.int64)
    m = 0
    for k in range(c):
        i = cand_i[k]
        j = cand_j[k]
        dx = _min_image(pos_m[j, 0] - pos_m[i, 0], bx)
        dy = _min_image(pos_m[j, 1] - pos_m[i, 1], by)
        if dx * dx + dy * dy <= r2:
            out_i[m] = i
            out_j[m] = j
            m += 1
    return out_i[:m].copy(), out_j[:m].copy()
