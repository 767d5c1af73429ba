"""The team objective when one vehicle moves, the others fixed: incremental, compiled.

The team objective of a snapshot's links is ``J = sum_i w_i sum_{j in T_i} ln max(P_ij, p_min)``
(eq. 12 per transmitter, weighted: ``w_i = 1 / (N |T_i|)`` for the mean of the per-receiver-normalised
utilities). When only vehicle ``v`` moves, the links that change are its own broadcasts (row ``v``: the
signal), the links it receives (column ``v``: the signal and the interference at it) and the links of the
transmitters it interferes with (its power at their receivers); every other term of ``J`` stays. So a
candidate position costs ``O(N G)`` link evaluations instead of ``O(N^2 G)``. The per-link arithmetic is
:func:`cv2x_marl.sim.kernels.snapshot.snapshot_links`'s (the same functions); only the order of the
additions of ``J`` differs, so the result equals a full evaluation to rounding (tested).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.sim.kernels.pathloss import winner_b1_pair_db
from cv2x_marl.sim.kernels.per import _DB_TO_NEPER
from cv2x_marl.sim.kernels.snapshot import link_interference_mw, link_success, pair_powers, success_at_level
from cv2x_marl.utility import eq12_term

FloatArray = NDArray[np.float64]


@njit(cache=True)
def team_terms(
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
    weight: FloatArray,
    p_min: float,
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """The state :func:`team_move_objective` starts from: received powers ``rx_dbm``, ``rx_mw`` [N, N],
    eq. 12 terms [N, N] (0 off ``target``) and ``J`` (arguments as
    :func:`~cv2x_marl.sim.kernels.snapshot.snapshot_links`; ``weight`` [N] the ``w_i``)."""
    n = positions_m.shape[0]
    _, _, rx_dbm, rx_mw = pair_powers(positions_m, period_m, los, gain_db, wb1, range2_m2)
    term = np.zeros((n, n))
    total = 0.0
    for tx in range(n):
        row = 0.0
        for rx in range(n):
            if target[tx, rx]:
                interference = link_interference_mw(rx_mw, interferer_idx, interferer_weight, tx, rx)
                p = link_success(
                    rx_dbm[tx, rx], interference, noise_mw, model, per_sinr_db, per, threshold_db, sensitivity_dbm
                )
                term[tx, rx] = eq12_term(p, p_min)
                row += term[tx, rx]
        total += weight[tx] * row
    return rx_dbm, rx_mw, term, total


# not split (136 lines): @njit helpers called per candidate measured 2-9 % slower (TeamObjective.move_values, N = 21)
@njit(cache=True)
def team_move_objective(
    candidates_m: FloatArray,
    mover: int,
    gain_out_db: FloatArray,
    gain_in_db: FloatArray,
    positions_m: FloatArray,
    period_m: FloatArray,
    los: NDArray[np.bool_],
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
    weight: FloatArray,
    p_min: float,
    rx_dbm: FloatArray,
    rx_mw: FloatArray,
    term: FloatArray,
    total: float,
) -> FloatArray:
    """[M] team objective ``J`` with ``mover`` at each candidate [M, 2] (m), the others at ``positions_m``.

    Args:
        candidates_m: [M, 2] positions of the mover (m).
        mover: the vehicle that moves.
        gain_out_db, gain_in_db: [G, N] EIRP minus shadowing of the mover's links to / from each vehicle
            (dBm): G = 1 (the snapshot's shadowing, whatever the candidate) or G = M (a field, per candidate).
        positions_m ... p_min: as :func:`team_terms` (``positions_m`` the current positions; the
            mover's own row is ignored).
        rx_dbm, rx_mw, term, total: :func:`team_terms` at ``positions_m``.
    """
    n = positions_m.shape[0]
    m_count = candidates_m.shape[0]
    per_candidate = gain_out_db.shape[0] > 1
    # transmitters whose interferers include the mover (their links change through its power)
    hit = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        for g in range(interferer_idx.shape[1]):
            if interferer_idx[i, g] == mover:
                hit[i] = True
    # the noise-plus-interference level of the mover's own packet at each receiver does not depend on it
    level_row = np.empty(n)
    for j in range(n):
        level_row[j] = 10.0 * math.log10(
            link_interference_mw(rx_mw, interferer_idx, interferer_weight, mover, j) + noise_mw
        )
    out_dbm = np.empty(n)  # mover -> j
    in_dbm = np.empty(n)  # j -> mover
    out_mw = np.empty(n)
    in_mw = np.empty(n)
    result = np.empty(m_count)
    for m in range(m_count):
        g_row = m if per_candidate else 0
        cx = candidates_m[m, 0]
        cy = candidates_m[m, 1]
        for j in range(n):
            if j == mover:
                out_dbm[j] = -np.inf
                in_dbm[j] = -np.inf
                out_mw[j] = 0.0
                in_mw[j] = 0.0
                continue
            # the displacement from the lower to the higher index, as pair_powers takes it
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
            if dx * dx + dy * dy <= range2_m2:
                pl = winner_b1_pair_db(dx, dy, los[mover, j], wb1[0], wb1[1], wb1[2], wb1[3], wb1[4], wb1[5])
                a = gain_out_db[g_row, j] - pl
                b = gain_in_db[g_row, j] - pl
            else:
                a = -np.inf
                b = -np.inf
            out_dbm[j] = a
            in_dbm[j] = b
            out_mw[j] = math.exp(a * _DB_TO_NEPER)
            in_mw[j] = math.exp(b * _DB_TO_NEPER)
        delta = 0.0
        # the mover's broadcasts: new signal, same interference
        row = 0.0
        for j in range(n):
            if target[mover, j]:
                p = success_at_level(out_dbm[j], level_row[j], model, per_sinr_db, per, threshold_db, sensitivity_dbm)
                row += eq12_term(p, p_min) - term[mover, j]
        delta += weight[mover] * row
        # the links of the others
        for i in range(n):
            if i == mover:
                continue
            row = 0.0
            if hit[i]:  # every receiver of i: the mover's power is in the interference
                for j in range(n):
                    if not target[i, j]:
                        continue
                    interference = 0.0
                    for g in range(interferer_idx.shape[1]):
                        c = interferer_idx[i, g]
                        if c < 0:
                            break
                        if j == mover:
                            pw = in_mw[c]
                        elif c == mover:
                            pw = out_mw[j]
                        else:
                            pw = rx_mw[c, j]
                        interference += interferer_weight[i, g] * pw
                    s = in_dbm[i] if j == mover else rx_dbm[i, j]
                    p = link_success(s, interference, noise_mw, model, per_sinr_db, per, threshold_db, sensitivity_dbm)
                    row += eq12_term(p, p_min) - term[i, j]
            elif target[i, mover]:  # only the link to the mover: its signal and the interference at it
                interference = 0.0
                for g in range(interferer_idx.shape[1]):
                    c = interferer_idx[i, g]
                    if c < 0:
                        break
                    interference += interferer_weight[i, g] * in_mw[c]
                p = link_success(
                    in_dbm[i], interference, noise_mw, model, per_sinr_db, per, threshold_db, sensitivity_dbm
                )
                row += eq12_term(p, p_min) - term[i, mover]
            delta += weight[i] * row
        result[m] = total + delta
    return result
