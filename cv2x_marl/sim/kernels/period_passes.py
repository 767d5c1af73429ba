"""The compiled passes of one chunk of a period (:func:`cv2x_marl.sim.kernels.period.period_chunk`), each an
``@njit`` helper of its compiled body: the vehicles' tiles, the links counted and gathered per tile with their
uniforms, per tile the power sums (pass 1), the links' outcomes (pass 2) and the S-RSSI / SCI commit, then the
outputs and the PRR accumulators in link order; and the SCI decoding probability, the S-RSSI commit of one
receiver's subframe and the in-band leakage they use. :mod:`cv2x_marl.sim.kernels.period` documents the
arithmetic (its docstring of :func:`~cv2x_marl.sim.kernels.period.period_chunk`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.sim.kernels.per import (
    LIN_MARGIN,
    db_below,
    interp_clamped,
    success_of_ratio,
)
from cv2x_marl.sim.kernels.period_tuples import ChunkResult

FloatArray = NDArray[np.float64]


@njit(cache=True)
def vehicle_tiles(
    active: NDArray[np.bool_], resource: NDArray[np.int64], n_sub: int, width: int, tile_subframes: int
) -> NDArray[np.int32]:
    """[N, 4] per vehicle (no division per link): its tile (-1: not transmitting in the chunk), its resource,
    subchannel and subframe within the tile."""
    n = active.shape[0]
    veh = np.full((n, 4), -1, dtype=np.int32)
    for t in range(n):
        if active[t]:
            g = resource[t] // width
            veh[t, 0] = g
            veh[t, 1] = resource[t] - g * width
            veh[t, 2] = resource[t] % n_sub
            veh[t, 3] = resource[t] // n_sub - g * tile_subframes
    return veh


@njit(cache=True)
def tile_starts(
    tx: NDArray[np.int64],
    links: NDArray[np.int64],
    subset: bool,
    n_visit: int,
    veh: NDArray[np.int32],
    n_tiles: int,
) -> NDArray[np.int64]:
    """[n_tiles + 1] where each tile's links start in tile order: the chunk's active links counted per tile
    (the transmitter's subframe // tile_subframes), cumulated."""
    tile_start = np.zeros(n_tiles + 1, dtype=np.int64)
    for q in range(n_visit):
        k = links[q] if subset else q
        g = veh[tx[k], 0]
        if g >= 0:
            tile_start[g + 1] += 1
    for g in range(n_tiles):
        tile_start[g + 1] += tile_start[g]
    return tile_start


@njit(cache=True)
def gather_links(
    rx: NDArray[np.int64],
    tx: NDArray[np.int64],
    rx_mw: FloatArray,
    links: NDArray[np.int64],
    subset: bool,
    n_visit: int,
    veh: NDArray[np.int32],
    tile_start: NDArray[np.int64],
    n_tiles: int,
    tile_rt: NDArray[np.int32],
    tile_s: FloatArray,
    tile_u: FloatArray,
    tile_u_sci: FloatArray,
    sci_sinr: bool,
    link_rng: np.random.Generator,
    sci_rng: np.random.Generator,
) -> None:
    """The chunk's active links gathered tile by tile (a stable counting sort: increasing link order within a
    tile) into ``tile_rt`` (receiver, transmitter), ``tile_s`` (power) and their uniforms, drawn in link order:
    ``tile_u`` from ``link_rng`` and, with ``sci_sinr``, ``tile_u_sci`` from ``sci_rng``."""
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


@njit(cache=True)
def tile_sums(
    lo: int,
    hi: int,
    tile_rt: NDArray[np.int32],
    tile_s: FloatArray,
    veh: NDArray[np.int32],
    sum_t: FloatArray,
    slot_t: FloatArray,
    width: int,
    tile_subframes: int,
    flat: bool,
) -> None:
    """Pass 1 of a tile's links ``[lo, hi)``: the power sums per receiver and resource (and per receiver and
    subframe with ``flat``), in link order."""
    for j in range(lo, hi):
        r = tile_rt[2 * j]
        t = tile_rt[2 * j + 1]
        sum_t[r * width + veh[t, 1]] += tile_s[j]
        if flat:
            slot_t[r * tile_subframes + veh[t, 3]] += tile_s[j]


@njit(cache=True)
def tile_outcomes(
    lo: int,
    hi: int,
    tile_rt: NDArray[np.int32],
    tile_s: FloatArray,
    tile_u: FloatArray,
    tile_u_sci: FloatArray,
    tile_cause: NDArray[np.int8],
    veh: NDArray[np.int32],
    sum_t: FloatArray,
    slot_t: FloatArray,
    sci_t: FloatArray,
    width: int,
    tile_subframes: int,
    flat: bool,
    flat_inband_lin: float,
    three_gpp: bool,
    leakage: FloatArray,
    n_sub: int,
    noise_mw: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    lin_lo: float,
    lin_hi: float,
    threshold_db: float,
    thr_lin: float,
    sci_sinr: bool,
    sci_offset_db: float,
    sci_sinr_lin: FloatArray,
    sci_bler: FloatArray,
    sci_lo: float,
    sci_hi: float,
    sci_gates_pssch: bool,
    slot: NDArray[np.int64],
    sensitivity_dbm: float,
    sens_lin: float,
    releasing: NDArray[np.bool_],
) -> None:
    """Pass 2 of a tile's links ``[lo, hi)``: each link's outcome, its ``P`` (over its uniform in ``tile_u``)
    and cause (``tile_cause``), and the strongest decodable SCI per receiver and resource (``sci_t``)."""
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
        p = success_of_ratio(ratio, model, per_sinr_db, per, lin_lo, lin_hi, threshold_db, thr_lin)
        outcome = u < p
        sci_decoded = True
        u_sci = 0.0
        if sci_sinr:
            p_sci = sci_probability(ratio, sci_offset_db, sci_sinr_lin, sci_bler, sci_lo, sci_hi)
            u_sci = tile_u_sci[j]
            sci_decoded = u_sci < p_sci
            if sci_gates_pssch:  # the PSSCH needs its SCI: both decode, P the product
                outcome = outcome and sci_decoded
                p = p * p_sci
        would0 = True  # read only when the link fails: then P0 decides propagation or collision
        if not outcome:
            p0 = success_of_ratio(s / noise_mw, model, per_sinr_db, per, lin_lo, lin_hi, threshold_db, thr_lin)
            would0 = u < p0
            if sci_gates_pssch:
                would0 = would0 and u_sci < sci_probability(
                    s / noise_mw, sci_offset_db, sci_sinr_lin, sci_bler, sci_lo, sci_hi
                )
        hd = slot[r] == slot[t]
        below = sensitivity_dbm > -np.inf and db_below(s, sens_lin, sensitivity_dbm)
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


@njit(cache=True)
def commit_tile(
    lo: int,
    hi: int,
    n: int,
    n_slots: int,
    res0: int,
    n_res: int,
    tile_rt: NDArray[np.int32],
    veh: NDArray[np.int32],
    sum_t: FloatArray,
    slot_t: FloatArray,
    sci_t: FloatArray,
    width: int,
    tile_subframes: int,
    flat: bool,
    three_gpp: bool,
    leakage: FloatArray,
    n_sub: int,
    leak_row: FloatArray,
    period_rssi_mw: FloatArray,
    period_sci_mw: FloatArray,
) -> None:
    """The tile's S-RSSI and SCI maxima into the period's, the scratches zeroed again: a tile with fewer links
    than receiver-subframes through its links (each receiver's subframe once), a larger one by a scan of the
    scratches in order."""
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


@njit(cache=True)
def chunk_outputs(
    rx: NDArray[np.int64],
    tx: NDArray[np.int64],
    distance_m: FloatArray,
    links: NDArray[np.int64],
    subset: bool,
    n_visit: int,
    n: int,
    veh: NDArray[np.int32],
    tile_start: NDArray[np.int64],
    n_tiles: int,
    tile_u: FloatArray,
    tile_cause: NDArray[np.int8],
    out_tx: NDArray[np.int64],
    out_rx: NDArray[np.int64],
    p_out: FloatArray,
    cause_out: NDArray[np.int8],
    bin_m: float,
    n_bins: int,
    n_causes: int,
) -> ChunkResult:
    """The outputs and the PRR accumulators in link order (the tiles' outputs merged back: the float sums in
    the order of the numpy path), as :class:`ChunkResult`."""
    bin_n = np.zeros(n_bins, dtype=np.int64)
    bin_dec = np.zeros(n_bins, dtype=np.int64)
    bin_exp = np.zeros(n_bins)
    bin_causes = np.zeros(n_causes * n_bins, dtype=np.int64)
    node_n = np.zeros(n, dtype=np.int64)
    node_dec = np.zeros(n, dtype=np.int64)
    node_exp = np.zeros(n)
    fill = tile_start[:n_tiles].copy()
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
    return ChunkResult(
        out_tx, out_rx, p_out, cause_out, bin_n, bin_dec, bin_exp, bin_causes, node_n, node_dec, node_exp
    )


@njit(cache=True)
def sci_probability(
    ratio: float, offset_db: float, sinr_lin: FloatArray, bler: FloatArray, ratio_lo: float, ratio_hi: float
) -> float:
    """``1 - BLER(10 log10(ratio) + offset)`` of the PSCCH curve (points ``sinr_lin`` in linear units),
    :meth:`cv2x_marl.sim.link.PscchCurve.decoding_probability`'s arithmetic (0 for NaN). Outside the
    curve, the constant that arithmetic gives (0 below: BLER 1; ``1 - bler[-1]`` above) without the
    logarithm and the power: ``ratio_lo``, ``ratio_hi`` are the curve's ends as linear SINR before the
    offset (``sinr_lin[0] / 10^(offset / 10)``, ``sinr_lin[-1] / 10^(offset / 10)``), and within
    :data:`LIN_MARGIN` of them the exact arithmetic decides."""
    if ratio < ratio_lo * (1.0 - LIN_MARGIN):
        return 0.0
    if ratio > ratio_hi * (1.0 + LIN_MARGIN):
        return 1.0 - bler[-1]
    x = 10.0 * math.log10(ratio) + offset_db
    if math.isnan(x):
        return 0.0
    return 1.0 - interp_clamped(10.0 ** (x / 10.0), sinr_lin, bler, 1.0, bler[-1])


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
    total[base + i]``, summed in ``i`` order (the arithmetic of :func:`cv2x_marl.sim.chunk.inband_leakage`)."""
    acc = total[base] * leakage[victim, 0]
    for i in range(1, n_sub):
        acc = acc + total[base + i] * leakage[victim, i]
    return acc
