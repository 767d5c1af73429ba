"""One period of the simulator's subframe loop, compiled: SCI decoding, sensing RSSI, PSSCH outcomes.

Its named tuples in and out are :mod:`cv2x_marl.sim.kernels.period_tuples`' (re-exported here), its compiled
passes :mod:`cv2x_marl.sim.kernels.period_passes`'."""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.interrupts import signals_deferred
from cv2x_marl.sim.kernels.period_passes import (
    chunk_outputs,
    commit_tile,
    gather_links,
    tile_outcomes,
    tile_starts,
    tile_sums,
    vehicle_tiles,
)
from cv2x_marl.sim.kernels.period_tuples import (
    ChunkBuffers,
    ChunkLinks,
    ChunkResult,
    ChunkVehicles,
    DistanceBins,
    LinkModel,
    SciModel,
)

FloatArray = NDArray[np.float64]


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


def period_chunk(
    pairs: ChunkLinks,
    vehicles: ChunkVehicles,
    link_model: LinkModel,
    sci: SciModel,
    buffers: ChunkBuffers,
    bins: DistanceBins,
    link_rng: np.random.Generator,
    sci_rng: np.random.Generator,
) -> ChunkResult:
    """One chunk of the simulator's period (:meth:`cv2x_marl.sim.chunk.ChunkRunner.run`) in compiled passes
    over the links, tile by tile.

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
    numpy's on the CPUs tested) are taken only where a comparison needs them (:func:`db_below`,
    :func:`success_of_ratio`): equal to the numpy path (tested), at a fraction of the cost when most
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
        pairs: the period's ordered pairs and the chunk's links (:class:`ChunkLinks`).
        vehicles: per vehicle, who transmits and its resource (:class:`ChunkVehicles`).
        link_model: noise, PER table or threshold, sensitivity, in-band emission (:class:`LinkModel`).
        sci: the SCI decoding model (:class:`SciModel`).
        buffers: the period's sensing sums and the scratches, updated in place (:class:`ChunkBuffers`).
        bins: the accumulator's distance bins and causes (:class:`DistanceBins`).
        link_rng: the simulator's ``link`` stream (advanced by one draw per active link).
        sci_rng: ``sps.sci_decoding=sinr``: the SCI stream (one draw per active link, as
            :meth:`cv2x_marl.sim.chunk.ChunkRunner.sci_draws`); unused otherwise.

    Returns:
        :class:`ChunkResult`: ``tx, rx, p, cause`` [L] of the active links, then the chunk's ``bin_n,
        bin_decoded, bin_expected`` [n_bins], ``bin_causes`` [n_causes * n_bins] (cause-major), ``node_n,
        node_decoded, node_expected`` [N].
    """
    # the named tuples' fields as plain arguments: numba dispatches a named tuple through its Python typeof
    # (about 2 us per call and tuple, measured), plain arguments through its C fast path
    with signals_deferred():  # a Generator argument: see cv2x_marl.interrupts
        out = _period_chunk(
            pairs.rx,
            pairs.tx,
            pairs.distance_m,
            pairs.rx_mw,
            pairs.subset,
            pairs.links,
            vehicles.active,
            vehicles.resource,
            vehicles.slot,
            vehicles.releasing,
            link_model.n_res,
            link_model.n_sub,
            link_model.noise_mw,
            link_model.model,
            link_model.per_sinr_db,
            link_model.per,
            link_model.threshold_db,
            link_model.sensitivity_dbm,
            link_model.flat_inband_lin,
            link_model.leakage,
            sci.sinr_lin,
            sci.bler,
            sci.offset_db,
            sci.gates_pssch,
            buffers.period_rssi_mw,
            buffers.period_sci_mw,
            buffers.total,
            buffers.total_slot,
            buffers.tile_subframes,
            bins.bin_m,
            bins.n_bins,
            bins.n_causes,
            link_rng,
            sci_rng,
        )
    return ChunkResult._make(out)


@njit(cache=True)
def _period_chunk(
    rx: NDArray[np.int64],
    tx: NDArray[np.int64],
    distance_m: FloatArray,
    rx_mw: FloatArray,
    subset: bool,
    links: NDArray[np.int64],
    active: NDArray[np.bool_],
    resource: NDArray[np.int64],
    slot: NDArray[np.int64],
    releasing: NDArray[np.bool_],
    n_res: int,
    n_sub: int,
    noise_mw: float,
    model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
    flat_inband_lin: float,
    leakage: FloatArray,
    sci_sinr_lin: FloatArray,
    sci_bler: FloatArray,
    sci_offset_db: float,
    sci_gates_pssch: bool,
    period_rssi_mw: FloatArray,
    period_sci_mw: FloatArray,
    total: FloatArray,
    total_slot: FloatArray,
    tile_subframes: int,
    bin_m: float,
    n_bins: int,
    n_causes: int,
    link_rng: np.random.Generator,
    sci_rng: np.random.Generator,
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
    """The compiled body of :func:`period_chunk`: the fields of its named tuples in their order, the
    fields of :class:`ChunkResult` returned in theirs."""
    n = active.shape[0]
    n_visit = links.shape[0] if subset else rx.shape[0]
    rri = n_res // n_sub
    n_tiles = (rri + tile_subframes - 1) // tile_subframes
    width = tile_subframes * n_sub  # resources per tile (the last tile may hold fewer)
    veh = vehicle_tiles(active, resource, n_sub, width, tile_subframes)
    tile_start = tile_starts(tx, links, subset, n_visit, veh, n_tiles)
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
    gather_links(
        rx, tx, rx_mw, links, subset, n_visit, veh, tile_start, n_tiles, tile_rt, tile_s, tile_u, tile_u_sci,
        sci_sinr, link_rng, sci_rng,
    )  # fmt: skip
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
        tile_sums(lo, hi, tile_rt, tile_s, veh, sum_t, slot_t, width, tile_subframes, flat)
        tile_outcomes(
            lo, hi, tile_rt, tile_s, tile_u, tile_u_sci, tile_cause, veh, sum_t, slot_t, sci_t, width,
            tile_subframes, flat, flat_inband_lin, three_gpp, leakage, n_sub, noise_mw, model, per_sinr_db, per,
            lin_lo, lin_hi, threshold_db, thr_lin, sci_sinr, sci_offset_db, sci_sinr_lin, sci_bler, sci_lo, sci_hi,
            sci_gates_pssch, slot, sensitivity_dbm, sens_lin, releasing,
        )  # fmt: skip
        commit_tile(
            lo, hi, n, n_slots, res0, n_res, tile_rt, veh, sum_t, slot_t, sci_t, width, tile_subframes, flat,
            three_gpp, leakage, n_sub, leak_row, period_rssi_mw, period_sci_mw,
        )  # fmt: skip
    return chunk_outputs(
        rx, tx, distance_m, links, subset, n_visit, n, veh, tile_start, n_tiles, tile_u, tile_cause, out_tx, out_rx,
        p_out, cause_out, bin_m, n_bins, n_causes,
    )  # fmt: skip
