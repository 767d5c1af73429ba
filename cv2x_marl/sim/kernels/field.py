"""The shadowing field that follows the vehicles, compiled (:mod:`cv2x_marl.sim.shadow_field`).

One pair's field value (TR 36.885 A.1.4's exponential correlation, spectral method), the field of
every pair for one set of positions, and the field of one vehicle's links for many candidate positions
of it with the others fixed. The numpy reference is
:meth:`cv2x_marl.sim.shadow_field.ShadowField.shadow_db` (``compiled=False``); numba's ``cos`` / ``exp``
may differ from numpy's in the last ulps, so the two agree to a stated tolerance (1e-9 dB, tested),
not bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.sim.kernels.trig import cos_into

FloatArray = NDArray[np.float64]


@njit(cache=True)
def wave_args_into(
    lo_dx: float,
    lo_dy: float,
    hi_dx: float,
    hi_dy: float,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    out: FloatArray,
) -> None:
    """Into ``out`` [W]: the arguments ``k_lo_w . dx_lo + k_hi_w . dx_hi + phi_w`` (rad) of one pair's
    cosines, its ends moved by ``(lo_dx, lo_dy)`` and ``(hi_dx, hi_dy)`` (m); ``k_lo``, ``k_hi`` [W, 2]
    (rad/m), ``phase`` [W] (rad)."""
    for w in range(phase.shape[0]):
        out[w] = k_lo[w, 0] * lo_dx + k_lo[w, 1] * lo_dy + k_hi[w, 0] * hi_dx + k_hi[w, 1] * hi_dy + phase[w]


@njit(cache=True)
def pair_value_db(
    lo_dx: float,
    lo_dy: float,
    hi_dx: float,
    hi_dy: float,
    s0_db: float,
    sigma_db: float,
    decorrelation_m: float,
    cosines: FloatArray,
    g0: float,
) -> float:
    """Shadowing (dB) of one pair from its ``W`` cosines ``cosines`` [W] (:func:`wave_args_into` through
    :func:`~cv2x_marl.sim.kernels.trig.cos_into`): ``rho s0 + sigma (G - rho G0)`` with
    ``G = sqrt(2 / W) sum_w cos_w`` (summed in wave order) and
    ``rho = exp(-(|dx_lo| + |dx_hi|) / d)``. Neither end moved: exactly ``s0``."""
    if lo_dx == 0.0 and lo_dy == 0.0 and hi_dx == 0.0 and hi_dy == 0.0:
        return s0_db
    w_count = cosines.shape[0]
    g = 0.0
    for w in range(w_count):
        g += cosines[w]
    g *= math.sqrt(2.0 / w_count)
    rho = math.exp(-(math.hypot(lo_dx, lo_dy) + math.hypot(hi_dx, hi_dy)) / decorrelation_m)
    return rho * s0_db + sigma_db * (g - rho * g0)


@njit(cache=True)
def pair_field_db(
    lo_dx: float,
    lo_dy: float,
    hi_dx: float,
    hi_dy: float,
    s0_db: float,
    sigma_db: float,
    decorrelation_m: float,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    g0: float,
) -> float:
    """Shadowing (dB) of one pair whose ends moved by ``(lo_dx, lo_dy)`` (the lower index) and
    ``(hi_dx, hi_dy)`` (the higher) from the field's start positions.

    ``s = rho s0 + sigma (G - rho G0)`` with ``rho = exp(-(|dx_lo| + |dx_hi|) / d)`` and
    ``G = sqrt(2 / W) sum_w cos(k_lo_w . dx_lo + k_hi_w . dx_hi + phi_w)`` (module docstring of
    :mod:`cv2x_marl.sim.shadow_field`): :func:`wave_args_into`, the cosines by
    :func:`~cv2x_marl.sim.kernels.trig.cos_into`, then :func:`pair_value_db`. Neither end moved:
    exactly ``s0``.

    Args:
        lo_dx, lo_dy, hi_dx, hi_dy: displacements of the two ends (m).
        s0_db: the snapshot's shadowing of the pair (dB).
        sigma_db: the pair's standard deviation (dB).
        decorrelation_m: ``d`` (m).
        k_lo, k_hi: [W, 2] the pair's wave vectors (rad/m).
        phase: [W] the pair's phases (rad).
        g0: ``G`` at the start (the pair's :attr:`ShadowField.g0`).
    """
    w = phase.shape[0]
    return pair_field_scratch_db(
        lo_dx, lo_dy, hi_dx, hi_dy, s0_db, sigma_db, decorrelation_m, k_lo, k_hi, phase, g0, np.empty(w), np.empty(w)
    )


@njit(cache=True)
def pair_field_scratch_db(
    lo_dx: float,
    lo_dy: float,
    hi_dx: float,
    hi_dy: float,
    s0_db: float,
    sigma_db: float,
    decorrelation_m: float,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    g0: float,
    args: FloatArray,
    cosines: FloatArray,
) -> float:
    """:func:`pair_field_db` with the caller's scratch ``args``, ``cosines`` [W] (two arrays: in place, the
    cosine pass would not vectorise), so a loop over pairs allocates once."""
    if lo_dx == 0.0 and lo_dy == 0.0 and hi_dx == 0.0 and hi_dy == 0.0:
        return s0_db
    wave_args_into(lo_dx, lo_dy, hi_dx, hi_dy, k_lo, k_hi, phase, args)
    cos_into(args, cosines)
    return pair_value_db(lo_dx, lo_dy, hi_dx, hi_dy, s0_db, sigma_db, decorrelation_m, cosines, g0)


@njit(cache=True)
def field_shadow_db(
    positions_m: FloatArray,
    start_m: FloatArray,
    shadow0_db: FloatArray,
    sigma_db: FloatArray,
    decorrelation_m: float,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    g0: FloatArray,
) -> FloatArray:
    """[N, N] shadowing of every pair with the vehicles at ``positions_m`` [N, 2] (dB; the pairs
    ``a < b`` computed, mirrored; 0 on the diagonal). Arrays as :class:`ShadowField`'s."""
    n = positions_m.shape[0]
    out = np.zeros((n, n))
    args = np.empty(phase.shape[-1])
    cosines = np.empty(phase.shape[-1])
    for a in range(n):
        ax = positions_m[a, 0] - start_m[a, 0]
        ay = positions_m[a, 1] - start_m[a, 1]
        for b in range(a + 1, n):
            s = pair_field_scratch_db(
                ax, ay, positions_m[b, 0] - start_m[b, 0], positions_m[b, 1] - start_m[b, 1], shadow0_db[a, b],
                sigma_db[a, b], decorrelation_m, k_lo[a, b], k_hi[a, b], phase[a, b], g0[a, b], args, cosines,
            )  # fmt: skip
            out[a, b] = s
            out[b, a] = s
    return out


@njit(cache=True)
def gather_mover_pairs(
    mover: int,
    shadow0_db: FloatArray,
    sigma_db: FloatArray,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    g0: FloatArray,
    s0_out: FloatArray,
    sigma_out: FloatArray,
    k_lo_out: FloatArray,
    k_hi_out: FloatArray,
    phase_out: FloatArray,
    g0_out: FloatArray,
) -> None:
    """The field arrays of ``mover``'s pairs, by the other end ``j``: entry ``j`` of each output is the pair
    ``(min(mover, j), max(mover, j))``'s (``s0_out``, ``sigma_out``, ``g0_out`` [N]; ``k_lo_out``,
    ``k_hi_out`` [N, W, 2]; ``phase_out`` [N, W]; zeros at ``j = mover``). Inputs as
    :class:`~cv2x_marl.sim.shadow_field.ShadowField`'s ([N, N], [N, N, W, 2], [N, N, W])."""
    n = shadow0_db.shape[0]
    for j in range(n):
        if j == mover:
            s0_out[j] = 0.0
            sigma_out[j] = 0.0
            g0_out[j] = 0.0
            k_lo_out[j] = 0.0
            k_hi_out[j] = 0.0
            phase_out[j] = 0.0
            continue
        a = min(mover, j)
        b = max(mover, j)
        s0_out[j] = shadow0_db[a, b]
        sigma_out[j] = sigma_db[a, b]
        g0_out[j] = g0[a, b]
        k_lo_out[j] = k_lo[a, b]
        k_hi_out[j] = k_hi[a, b]
        phase_out[j] = phase[a, b]


@njit(cache=True)
def field_pairs_row_into(
    cx: float,
    cy: float,
    positions_m: FloatArray,
    mover: int,
    start_m: FloatArray,
    s0_db: FloatArray,
    sigma_db: FloatArray,
    decorrelation_m: float,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    g0: FloatArray,
    out: FloatArray,
) -> None:
    """Into ``out`` [N]: the shadowing of ``mover``'s links with it at ``(cx, cy)`` (m), every other vehicle
    at ``positions_m`` [N, 2] (its own row there is ignored); 0 at ``mover``. The pair arrays are
    :func:`gather_mover_pairs`' (indexed by the other end). Equal to row ``mover`` of :func:`field_shadow_db`
    with the mover there (the same arithmetic as :func:`pair_field_db`, the lower index's displacement first,
    with the cosines of all pairs in one :func:`~cv2x_marl.sim.kernels.trig.cos_into` pass)."""
    n = positions_m.shape[0]
    w_count = phase.shape[1]
    mx = cx - start_m[mover, 0]
    my = cy - start_m[mover, 1]
    args = np.empty((n, w_count))  # every pair's wave arguments, then their cosines in one pass
    cosines = np.empty((n, w_count))  # not in place: an aliased output keeps the pass from vectorising
    for j in range(n):
        jx = positions_m[j, 0] - start_m[j, 0]
        jy = positions_m[j, 1] - start_m[j, 1]
        if mover < j:
            wave_args_into(mx, my, jx, jy, k_lo[j], k_hi[j], phase[j], args[j])
        else:
            wave_args_into(jx, jy, mx, my, k_lo[j], k_hi[j], phase[j], args[j])
    cos_into(args.reshape(n * w_count), cosines.reshape(n * w_count))
    for j in range(n):
        if j == mover:
            out[j] = 0.0
            continue
        jx = positions_m[j, 0] - start_m[j, 0]
        jy = positions_m[j, 1] - start_m[j, 1]
        if mover < j:
            out[j] = pair_value_db(mx, my, jx, jy, s0_db[j], sigma_db[j], decorrelation_m, cosines[j], g0[j])
        else:
            out[j] = pair_value_db(jx, jy, mx, my, s0_db[j], sigma_db[j], decorrelation_m, cosines[j], g0[j])


@njit(cache=True)
def field_row_db(
    candidates_m: FloatArray,
    positions_m: FloatArray,
    mover: int,
    start_m: FloatArray,
    shadow0_db: FloatArray,
    sigma_db: FloatArray,
    decorrelation_m: float,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    g0: FloatArray,
) -> FloatArray:
    """[M, N] shadowing of ``mover``'s links with it at each candidate [M, 2] (m): the mover's pairs
    gathered once (:func:`gather_mover_pairs`), then :func:`field_pairs_row_into` per candidate; 0 in
    column ``mover``."""
    m_count = candidates_m.shape[0]
    n = positions_m.shape[0]
    w = phase.shape[-1]
    s0 = np.empty(n)
    sig = np.empty(n)
    kl = np.empty((n, w, 2))
    kh = np.empty((n, w, 2))
    ph = np.empty((n, w))
    g = np.empty(n)
    gather_mover_pairs(mover, shadow0_db, sigma_db, k_lo, k_hi, phase, g0, s0, sig, kl, kh, ph, g)
    out = np.zeros((m_count, n))
    for m in range(m_count):
        field_pairs_row_into(
            candidates_m[m, 0], candidates_m[m, 1], positions_m, mover, start_m, s0, sig, decorrelation_m, kl, kh,
            ph, g, out[m],
        )  # fmt: skip
    return out


@njit(cache=True)
def field_row_lattice_db(
    x0_m: float,
    y0_m: float,
    pitch_m: float,
    nx: int,
    ny: int,
    positions_m: FloatArray,
    mover: int,
    start_m: FloatArray,
    shadow0_db: FloatArray,
    sigma_db: FloatArray,
    decorrelation_m: float,
    k_lo: FloatArray,
    k_hi: FloatArray,
    phase: FloatArray,
    g0: FloatArray,
) -> FloatArray:
    """:func:`field_row_db` on the lattice ``(x0 + ix p, y0 + iy p)``, ``ix < nx``, ``iy < ny`` (candidate
    ``ix * ny + iy``, the order of ``meshgrid(..., indexing="ij")``): [nx * ny, N].

    Along ``y`` each cosine's argument grows by the same ``k_y p``, so the cosines of a lattice column
    follow by rotation, ``(c, s) <- (c cos D - s sin D, s cos D + c sin D)``, from one ``cos`` / ``sin``
    at its first point: two transcendental calls per column instead of one per point. The rotation's
    rounding grows with the steps (about ``ny`` ulps), far inside the 1e-9 dB tolerance against
    :func:`field_row_db` (tested).
    """
    n = positions_m.shape[0]
    w_count = phase.shape[-1]
    scale = math.sqrt(2.0 / w_count)
    m_count = nx * ny
    out = np.zeros((m_count, n))
    g = np.empty(m_count)
    sx = start_m[mover, 0]
    sy = start_m[mover, 1]
    for j in range(n):
        if j == mover:
            continue
        jx = positions_m[j, 0] - start_m[j, 0]
        jy = positions_m[j, 1] - start_m[j, 1]
        a = min(mover, j)
        b = max(mover, j)
        kv = k_lo[a, b] if mover < j else k_hi[a, b]  # [W, 2]: the mover's end
        ko = k_hi[a, b] if mover < j else k_lo[a, b]  # the other end
        g[:] = 0.0
        for w in range(w_count):
            base = ko[w, 0] * jx + ko[w, 1] * jy + phase[a, b, w]
            step = kv[w, 1] * pitch_m
            cd = math.cos(step)
            sd = math.sin(step)
            for ix in range(nx):
                theta = kv[w, 0] * (x0_m + ix * pitch_m - sx) + kv[w, 1] * (y0_m - sy) + base
                c = math.cos(theta)
                s = math.sin(theta)
                row = ix * ny
                for iy in range(ny):
                    g[row + iy] += c
                    c, s = c * cd - s * sd, s * cd + c * sd
        s0 = shadow0_db[a, b]
        sig = sigma_db[a, b]
        r_j = math.hypot(jx, jy)
        for ix in range(nx):
            dx = x0_m + ix * pitch_m - sx
            for iy in range(ny):
                dy = y0_m + iy * pitch_m - sy
                m = ix * ny + iy
                if dx == 0.0 and dy == 0.0 and r_j == 0.0:
                    out[m, j] = s0
                    continue
                rho = math.exp(-(math.hypot(dx, dy) + r_j) / decorrelation_m)
                out[m, j] = rho * s0 + sig * (scale * g[m] - rho * g0[a, b])
    return out
