"""Correlated shadowing updates (AR(1) in distance, TR 36.885 A.1.4) and received powers of the pairs."""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.interrupts import signals_deferred

FloatArray = NDArray[np.float64]


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
    with signals_deferred():  # a Generator argument: see cv2x_marl.interrupts
        return _shadowing_update_sparse(
            keys_prev, z_state, last_state, keys, reference, decorrelation_m, pair_distance, rng
        )


@njit(cache=True)
def _shadowing_update_sparse(
    keys_prev: NDArray[np.int64],
    z_state: FloatArray,
    last_state: FloatArray,
    keys: NDArray[np.int64],
    reference: FloatArray,
    decorrelation_m: float,
    pair_distance: bool,
    rng: np.random.Generator,
) -> FloatArray:
    """The compiled body of :func:`shadowing_update_sparse`."""
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
