"""WINNER+ B1 path loss (TR 36.885 A.1.2 / IST-WINNER II D1.1.2 B1): the one compiled implementation."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.units import SPEED_OF_LIGHT_MPS

FloatArray = NDArray[np.float64]


#: order of the WINNER+ B1 constants in the ``wb1`` argument of :func:`snapshot_links`
WB1_CONSTANTS = ("breakpoint_m", "c_near_db", "c_far_db", "c_nlos_db", "c_free_db", "min_distance_m")


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
