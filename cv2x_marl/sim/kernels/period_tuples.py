"""The named tuples in and out of :func:`cv2x_marl.sim.kernels.period.period_chunk`: the chunk's links, its
vehicles, the link and SCI models, the buffers it updates, the PRR accumulator's bins, and its result.
:mod:`cv2x_marl.sim.kernels.period` re-exports them (and the compiled body builds :class:`ChunkResult`)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


class ChunkLinks(NamedTuple):
    """The period's ordered pairs and the links a chunk visits (:func:`~cv2x_marl.sim.kernels.period.period_chunk`).

    Attributes:
        rx, tx, distance_m, rx_mw: [L_all] the period's ordered pairs, their distance (m) and received
            power (mW, faded).
        subset, links: with ``subset``, ``links`` are the indices of the links whose transmitter is
            active, increasing (from :func:`~cv2x_marl.sim.kernels.pairs.active_links`: a chunk of a few
            transmitters visits only their links, possibly none); without, every link is visited and
            checked against ``active``.
    """

    rx: NDArray[np.int64]
    tx: NDArray[np.int64]
    distance_m: FloatArray
    rx_mw: FloatArray
    subset: bool
    links: NDArray[np.int64]


class ChunkVehicles(NamedTuple):
    """Per vehicle [N]: who transmits in the chunk and the SPS state the links read.

    Attributes:
        active: [N] transmits in the chunk.
        resource, slot: [N] reserved resource and its subframe.
        releasing: [N] will reselect: its SCI reserves nothing (TS 36.213 14.1.1.6).
    """

    active: NDArray[np.bool_]
    resource: NDArray[np.int64]
    slot: NDArray[np.int64]
    releasing: NDArray[np.bool_]


class LinkModel(NamedTuple):
    """The PSSCH link model of a chunk.

    Attributes:
        n_res: resources per period; n_sub: subchannels per subframe (resource ``r`` is slot
            ``r // n_sub``, subchannel ``r % n_sub``).
        noise_mw: noise power, mW.
        model: :data:`~cv2x_marl.sim.kernels.per.MODEL_PER_TABLE`,
            :data:`~cv2x_marl.sim.kernels.per.MODEL_PER_TABLE_LOG` or
            :data:`~cv2x_marl.sim.kernels.per.MODEL_THRESHOLD`.
        per_sinr_db, per: [K] the PER table.
        threshold_db: SINR threshold of the threshold model, dB.
        sensitivity_dbm: received power below which a link fails (-inf: none), dBm.
        flat_inband_lin: ``link.inband_emission_db`` in linear units (flat in-band emission: that share of
            the power of the subframe's other subchannels adds to the interference); 0: none.
        leakage: [n_sub, n_sub] the 3gpp in-band leakage ``M[victim, interferer]``
            (:func:`cv2x_marl.sim.inband.pool_leakage_weights`), empty: none. The leakage into subchannel
            ``v`` of a receiver's subframe, ``sum_i M[v, i] total[i]`` (summed in ``i`` order, as
            :func:`cv2x_marl.sim.chunk.inband_leakage`), adds to the interference and to the S-RSSI.
    """

    n_res: int
    n_sub: int
    noise_mw: float
    model: int
    per_sinr_db: FloatArray
    per: FloatArray
    threshold_db: float
    sensitivity_dbm: float
    flat_inband_lin: float
    leakage: FloatArray


class SciModel(NamedTuple):
    """``sps.sci_decoding``: which SCIs a receiver decodes.

    Attributes:
        sinr_lin, bler: the PSCCH BLER curve (points in linear SINR, :class:`cv2x_marl.sim.link.PscchCurve`);
            an SCI counts only if ``u < 1 - BLER(SINR + offset)``. Empty curve: every SCI (``always``).
        offset_db: ``sps.sci_sinr_offset_db``.
        gates_pssch: ``sps.sci_gates_pssch``: a link succeeds only if its SCI decodes too (``P`` times
            the SCI's decoding probability; ``P0`` likewise with the SCI at the SNR).
    """

    sinr_lin: FloatArray
    bler: FloatArray
    offset_db: float
    gates_pssch: bool


class ChunkBuffers(NamedTuple):
    """The arrays :func:`~cv2x_marl.sim.kernels.period.period_chunk` updates in place.

    Attributes:
        period_rssi_mw: [N * n_res] the period's S-RSSI sums, mW.
        period_sci_mw: [N * n_res] the period's strongest decoded SCI (PSSCH power, mW).
        total: [N * n_res] zeros, a scratch for the power sums (the first ``N * tile_subframes * n_sub``
            entries used): left zero again on return.
        total_slot: [N * RRI] zeros, the scratch for the flat model's power per receiver and subframe
            (summed link by link, as the numpy path's ``bincount``): left zero again on return.
        tile_subframes: subframes per tile (:func:`~cv2x_marl.sim.kernels.period.chunk_tile_subframes`), >= 1;
            any value gives the same results.
    """

    period_rssi_mw: FloatArray
    period_sci_mw: FloatArray
    total: FloatArray
    total_slot: FloatArray
    tile_subframes: int


class DistanceBins(NamedTuple):
    """The PRR accumulator's layout (:class:`cv2x_marl.sim.metrics.PrrAccumulator`): ``n_bins`` distance
    bins of ``bin_m`` metres and ``n_causes`` loss causes."""

    bin_m: float
    n_bins: int
    n_causes: int


class ChunkResult(NamedTuple):
    """What :func:`~cv2x_marl.sim.kernels.period.period_chunk` returns.

    Attributes:
        tx, rx, p, cause: [L] the active links, in link order: transmitter, receiver, success probability
            and cause code (:data:`cv2x_marl.sim.metrics.CAUSE_CODE`).
        bin_n, bin_decoded, bin_expected: [n_bins] the chunk's per-distance-bin sums.
        bin_causes: [n_causes * n_bins] links per cause and bin, cause-major.
        node_n, node_decoded, node_expected: [N] the chunk's per-transmitter sums.
    """

    tx: NDArray[np.int64]
    rx: NDArray[np.int64]
    p: FloatArray
    cause: NDArray[np.int8]
    bin_n: NDArray[np.int64]
    bin_decoded: NDArray[np.int64]
    bin_expected: FloatArray
    bin_causes: NDArray[np.int64]
    node_n: NDArray[np.int64]
    node_decoded: NDArray[np.int64]
    node_expected: FloatArray
