"""One chunk of a period: the transmissions whose slot lies in ``[lo, hi)``, their outcomes, the sensing they
leave and the metrics (paper eq. 8; TS 36.213 14.1.1.6 for the sensing).

Two paths compute the same chunk: :meth:`ChunkRunner.run`'s numpy arrays over the chunk's links (the
reference, and the only path with the links table or ``link.model=rayleigh``), and the compiled
:func:`cv2x_marl.sim.kernels.period_chunk` (:meth:`ChunkRunner._run_compiled`), tested equal
(``tests/sim/conftest.py::compiled_and_numpy``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ScenarioConfig
from cv2x_marl.sim import channel, kernels, link
from cv2x_marl.sim.geometry import Geometry, displacement_m
from cv2x_marl.sim.metrics import CAUSE_CODE, PrrAccumulator
from cv2x_marl.sim.road import Road
from cv2x_marl.sim.sps import SpsScheduler
from cv2x_marl.units import db_to_linear

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: the links table's columns, in order (``metrics.record_links``)
LINK_COLUMNS: tuple[str, ...] = (
    "tx",
    "rx",
    "subframe",
    "subchannel",
    "distance_m",
    "nsv",
    "interferer_distance_m",
    "sinr_db",
    "rx_power_dbm",
    "p_success",
    "outcome",
    "cause",
    "los",
    "doppler_hz",
)

#: the period's ordered pairs from which a chunk runs compiled (Simulator.compiled_min_links)
COMPILED_CHUNK_MIN_LINKS = 1000

#: ``(tx, rx, p_success, cause)`` [L] of the links of a chunk
ChunkLinksOut = tuple[IntArray, IntArray, FloatArray, NDArray[np.int8]]


def joined(parts: list[ChunkLinksOut]) -> ChunkLinksOut:
    """``Simulator.last_links`` of the chunks ``parts`` of one period, in order (``tx, rx, p, cause``)."""
    tx, rx, p, cause = (np.concatenate(cols) for cols in zip(*parts, strict=True))
    return tx, rx, p, cause


def independent_interference_success(
    p0: FloatArray,
    success: Any,
    s_mw: FloatArray,
    i_each_mw: FloatArray,
    rep: IntArray,
    noise_mw: float,
) -> FloatArray:
    """``link.interference=independent``: the success probability of each link with its co-channel
    interferers taken one at a time, as the analytical model's eq. 14 (Gonzalez-Martin et al. 2019):
    ``P = P0 prod_i (P_i / P0)``, ``P_i = success(S / (I_i + N))`` the success with interferer ``i`` alone
    and ``P0 = success(S / N)`` without interference (so ``1 - P/P0 = 1 - prod_i (1 - p_INT,i)``, with
    ``p_INT,i = 1 - P_i / P0`` eq. 18's probability that ``i`` alone makes the packet fail).

    Args:
        p0: [L] success without interference.
        success: the link curve, SINR (dB) -> success probability (:meth:`cv2x_marl.sim.link.PerCurve.success`).
        s_mw: [L] received power of each link, mW.
        i_each_mw: [K] power of one interferer at the link's receiver, mW, one row per (link, interferer).
        rep: [K] the link of each row.
        noise_mw: noise power, mW.

    Returns:
        [L] ``P``.
    """
    p_each = success(10.0 * np.log10(s_mw[rep] / (i_each_mw + noise_mw)))
    p0_rep = p0[rep]
    ratio = np.where(p0_rep > 0.0, p_each / np.where(p0_rep > 0.0, p0_rep, 1.0), 1.0)
    out = p0.copy()
    np.multiply.at(out, rep, ratio)
    return np.asarray(out)


class ChunkRunner:
    """Runs the chunks of a period for a :class:`~cv2x_marl.sim.simulator.Simulator`.

    It holds the link model (PER curve, PSCCH curve, in-band leakage, noise), the ``link`` and SCI random
    streams (:meth:`reset`) and the compiled chunk's zeroed scratches; the SPS state it reads and the
    sensing sums it adds to are the :class:`~cv2x_marl.sim.sps.SpsScheduler`'s.
    """

    def __init__(
        self,
        config: ScenarioConfig,
        road: Road,
        n: int,
        noise_mw: float,
        curve: link.PerCurve,
        pscch_curve: link.PscchCurve | None,
        leakage: FloatArray | None,
        sparse_state: bool,
    ) -> None:
        self.config, self.road, self.n = config, road, n
        self.rri = config.traffic.rri_ms
        self.n_sub = config.sps.n_subchannels
        self.n_res = self.rri * self.n_sub
        self.noise_mw = noise_mw
        self.curve = curve
        self.pscch_curve = pscch_curve
        #: the PSCCH curve's SINR points in linear units (where its BLER is interpolated), for the kernel
        self.pscch_lin = np.power(10.0, pscch_curve.sinr_db / 10.0) if pscch_curve is not None else None
        #: [n_sub, n_sub] in-band leakage M[victim, interferer] (link.inband_emission_model=3gpp; None otherwise)
        self.leakage = leakage
        self.sparse_state = sparse_state
        # the compiled chunk's constant inputs, built once
        sens = config.radio.sensitivity_dbm
        flat = config.link.inband_emission_db
        self.link_model = kernels.LinkModel(
            self.n_res,
            self.n_sub,
            noise_mw,
            kernels.MODEL_THRESHOLD if config.link.model == "threshold" else curve.kernel_model,
            curve.sinr_db,
            curve.per,
            float(config.link.sinr_threshold_db),
            -np.inf if sens is None else float(sens),
            float(db_to_linear(flat)) if flat is not None else 0.0,
            leakage if leakage is not None else np.empty((0, 0)),
        )
        sci_lin, sci_bler = np.empty(0), np.empty(0)  # sps.sci_decoding=always: every SCI
        if pscch_curve is not None and self.pscch_lin is not None:
            sci_lin, sci_bler = self.pscch_lin, pscch_curve.bler
        self.sci_model = kernels.SciModel(
            sci_lin, sci_bler, float(config.sps.sci_sinr_offset_db), bool(config.sps.sci_gates_pssch)
        )

    def reset(self, link_rng: np.random.Generator, sci_rng: np.random.Generator | None) -> None:
        """The episode's ``link`` stream and SCI stream (``sps.sci_decoding=sinr``; None otherwise), and zeroed
        scratches of the compiled chunk."""
        self.link_rng = link_rng
        self.sci_rng = sci_rng
        #: the compiled chunk's scratch for the power sums per receiver and resource (zero between chunks)
        self.total = np.zeros(self.n * self.n_res)
        #: ... and for the flat in-band model's power per receiver and subframe
        self.total_slot = np.zeros(self.n * self.rri if self.config.link.inband_emission_db is not None else 0)

    def run(
        self,
        lo: int,
        hi: int,
        subframe: int,
        geo: Geometry,
        sched: SpsScheduler,
        acc: PrrAccumulator | None,
        cols: dict[str, list[np.ndarray]] | None,
        compiled: bool,
    ) -> ChunkLinksOut | None:
        """All transmissions of the current period whose slot lies in ``[lo, hi)``.

        Args:
            lo, hi: the chunk's slots within the period.
            subframe: absolute subframe of slot ``lo``.
            geo: the period's pair geometry.
            sched: the SPS state (resources, releases) and the period's sensing sums, updated.
            acc: the PRR accumulator to add to (None: warm-up).
            cols: the links table's columns to append to (None: no table).
            compiled: the compiled chunk where it applies (no links table, ``link.model`` not rayleigh).

        Returns:
            ``(tx, rx, p_success, cause)`` [L] of the chunk's links, or None when no vehicle transmits in it.
        """
        cfg = self.config
        slot = sched.slot
        active = (slot >= lo) & (slot < hi)
        if not np.any(active):
            return None
        if compiled and cols is None and cfg.link.model != "rayleigh" and cfg.link.interference == "sum":
            return self._run_compiled(geo, sched, active, acc)
        sel = active[geo.tx]
        rx, tx = geo.rx[sel], geo.tx[sel]
        s_mw = geo.rx_mw[sel]
        res_tx = sched.resource[tx]
        key = rx * self.n_res + res_tx
        total = np.bincount(key, weights=s_mw, minlength=self.n * self.n_res)
        i_mw = np.maximum(total[key] - s_mw, 0.0)
        if cfg.link.inband_emission_db is not None:
            slot_key = rx * self.rri + slot[tx]
            total_slot = np.bincount(slot_key, weights=s_mw, minlength=self.n * self.rri)
            i_mw = i_mw + db_to_linear(cfg.link.inband_emission_db) * np.maximum(total_slot[slot_key] - total[key], 0.0)
        leak_mw: FloatArray | None = None
        if self.leakage is not None:  # 3gpp: leak[rx, slot, v] = sum_i M[v, i] total[rx, slot, i]
            leak_mw = self.inband_leakage(total)
            i_mw = i_mw + leak_mw[key]
        hd = slot[rx] == slot[tx]
        sinr_db = 10.0 * np.log10(s_mw / (i_mw + self.noise_mw))
        snr_db = 10.0 * np.log10(s_mw / self.noise_mw)
        rx_dbm = 10.0 * np.log10(s_mw)
        n_links = rx.shape[0]

        need_triples = cols is not None or cfg.link.model == "rayleigh"
        rep: IntArray | None = None
        partner: IntArray | None = None
        if need_triples:
            rep, partner = self.group_terms(tx, rx, active, sched.resource)  # co-channel
        model = cfg.link.model
        p, p0 = self._success(geo, sel, rx, tx, active, sched, s_mw, sinr_db, snr_db, rep, partner)
        u = self.link_rng.random(n_links)
        if model == "rayleigh":
            theta = cfg.link.sinr_threshold_db
            outcome, would0 = sinr_db >= theta, snr_db >= theta
        else:
            outcome, would0 = u < p, u < p0
        sci_ok: NDArray[np.bool_] | None = None
        if self.pscch_curve is not None:  # sps.sci_decoding=sinr: one SCI draw per link
            u_sci, q = self.sci_draws(sinr_db)
            sci_ok = u_sci < q
            if cfg.sps.sci_gates_pssch:  # the PSSCH needs its SCI: both decode, P the product
                q0 = self.pscch_curve.decoding_probability(snr_db + cfg.sps.sci_sinr_offset_db)
                outcome, would0, p = outcome & sci_ok, would0 & (u_sci < q0), p * q
        below = np.zeros(n_links, dtype=bool)
        if cfg.radio.sensitivity_dbm is not None:
            below = rx_dbm < cfg.radio.sensitivity_dbm
        fail = hd | below
        p = np.where(fail, 0.0, p)
        outcome = outcome & ~fail
        cause = np.zeros(n_links, dtype=np.int8)
        cause[~outcome & ~would0] = CAUSE_CODE["propagation"]
        cause[~outcome & would0] = CAUSE_CODE["collision"]
        cause[below] = CAUSE_CODE["sensitivity"]
        cause[hd] = CAUSE_CODE["half_duplex"]

        # sensing: S-RSSI of every resource heard in this chunk, SCI RSRP of every decodable SCI
        sched.period_rssi_mw += total
        if leak_mw is not None:  # 3gpp: S-RSSI is the energy in the subchannel, leakage included (as WiLabV2Xsim)
            sched.period_rssi_mw += leak_mw
        sci = ~fail & ~sched.releasing[tx]  # a UE's last SCI before reselecting reserves nothing (standard)
        if sci_ok is not None:  # sps.sci_decoding=sinr: only a decoded PSCCH reserves
            sci &= sci_ok
        np.maximum.at(sched.period_sci_mw, key[sci], s_mw[sci])

        if acc is not None:
            acc.add(tx, geo.distance_m[sel], p, outcome, cause, int(active.sum()))
        if cols is not None:
            assert rep is not None and partner is not None  # need_triples
            links = (tx, rx, sinr_db, rx_dbm, p, outcome, cause)
            self._append_columns(cols, geo, sel, active, sched, subframe - lo, rep, partner, links)
        return tx, rx, p, cause

    def _success(
        self,
        geo: Geometry,
        sel: NDArray[np.bool_],
        rx: IntArray,
        tx: IntArray,
        active: NDArray[np.bool_],
        sched: SpsScheduler,
        s_mw: FloatArray,
        sinr_db: FloatArray,
        snr_db: FloatArray,
        rep: IntArray | None,
        partner: IntArray | None,
    ) -> tuple[FloatArray, FloatArray]:
        """:meth:`run`'s success probabilities ``P`` (at the SINR) and ``P0`` (at the SNR, no interference) of the
        chunk's links under ``link.model`` and ``link.interference``; ``rep``, ``partner``: the co-channel terms
        (:meth:`group_terms`; needed by the rayleigh model)."""
        cfg = self.config
        model = cfg.link.model
        if cfg.link.interference == "independent":  # the analytical model's eq. 14 (config: per_table, no fading)
            p0 = self.curve.success(snr_db)
            rep_i, partner_i = self.group_terms(tx, rx, active, sched.resource)
            i_each_mw = self._mean_power_lookup(geo, rx[rep_i], partner_i)
            p = independent_interference_success(p0, self.curve.success, s_mw, i_each_mw, rep_i, self.noise_mw)
        elif model == "per_table":
            p = self.curve.success(sinr_db)
            p0 = self.curve.success(snr_db)
        elif model == "threshold":
            p = link.threshold_success(sinr_db, cfg.link.sinr_threshold_db)
            p0 = link.threshold_success(snr_db, cfg.link.sinr_threshold_db)
        else:
            assert rep is not None and partner is not None  # need_triples
            mean_s = db_to_linear(geo.mean_rx_dbm[sel])
            mean_i = self._mean_power_lookup(geo, rx[rep], partner)
            p = link.rayleigh_success(mean_s, self.noise_mw, mean_i, rep, cfg.link.sinr_threshold_db)
            p0 = link.rayleigh_success(mean_s, self.noise_mw, np.empty(0), rep[:0], cfg.link.sinr_threshold_db)
        return p, p0

    def _append_columns(
        self,
        cols: dict[str, list[np.ndarray]],
        geo: Geometry,
        sel: NDArray[np.bool_],
        active: NDArray[np.bool_],
        sched: SpsScheduler,
        period_start: int,
        rep: IntArray,
        partner: IntArray,
        links: tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.int8]],
    ) -> None:
        """Append the chunk's links to the links table's columns (``metrics.record_links``): ``links`` is
        ``(tx, rx, sinr_db, rx_power_dbm, p_success, outcome, cause)``, ``rep`` / ``partner`` the co-channel terms
        (the NSV and the main interferer's distance; replaced by the subframe's with ``metrics.nsv_scope``
        concurrent), ``period_start`` the absolute subframe of the period's slot 0."""
        cfg = self.config
        tx, rx, sinr_db, rx_dbm, p, outcome, cause = links
        slot = sched.slot
        n_links = rx.shape[0]
        rng_i = cfg.metrics.interferer_range_m
        if cfg.metrics.nsv_scope == "concurrent":  # every transmitter of the subframe, any subchannel
            rep, partner = self.group_terms(tx, rx, active, slot)
        dpart = displacement_m(self.config, self.road, geo.positions_m[rx[rep]], geo.positions_m[partner])
        dist_i = np.hypot(dpart[:, 0], dpart[:, 1])
        near = dist_i <= rng_i
        nsv = np.bincount(rep[near], minlength=n_links)
        l_m = np.full(n_links, rng_i)
        np.minimum.at(l_m, rep[near], dist_i[near])
        cols["tx"].append(tx.astype(np.int32))
        cols["rx"].append(rx.astype(np.int32))
        cols["subframe"].append(period_start + slot[tx])
        cols["subchannel"].append(sched.subchannel[tx].astype(np.int16))
        cols["distance_m"].append(geo.distance_m[sel])
        cols["nsv"].append(nsv.astype(np.int16))
        cols["interferer_distance_m"].append(l_m)
        cols["sinr_db"].append(sinr_db)
        cols["rx_power_dbm"].append(rx_dbm)
        cols["p_success"].append(p)
        cols["outcome"].append(outcome)
        cols["cause"].append(cause)
        cols["los"].append(geo.los[sel])
        cols["doppler_hz"].append(channel.doppler_hz(cfg.radio.carrier_hz, geo.rel_speed_mps[sel]))

    def _run_compiled(
        self, geo: Geometry, sched: SpsScheduler, active: NDArray[np.bool_], acc: PrrAccumulator | None
    ) -> ChunkLinksOut:
        """:meth:`run` in compiled passes over the chunk's links (:func:`kernels.period_chunk`; no links
        table, ``link.model`` per_table or threshold, either in-band emission model): the same draws
        from the same streams, the same sums in the same order, the dB values and the PER and PSCCH
        interpolation with numpy's formulas, taken only where a comparison needs them; tested equal to the
        numpy path (``tests/sim/test_scale.py``, ``tests/sim/test_sci_decoding.py``)."""
        subset, links = self._chunk_links(geo, active)
        out = kernels.period_chunk(
            kernels.ChunkLinks(geo.rx, geo.tx, geo.distance_m, geo.rx_mw, subset, links),
            kernels.ChunkVehicles(active, sched.resource, sched.slot, sched.releasing),
            self.link_model,
            self.sci_model,
            kernels.ChunkBuffers(
                sched.period_rssi_mw,
                sched.period_sci_mw,
                self.total,
                self.total_slot,
                # looked up through the package facade at each call (tests force the tile size there)
                kernels.chunk_tile_subframes(self.n, self.n_sub, self.rri),
            ),
            kernels.DistanceBins(
                acc.bin_m if acc is not None else 1.0, acc.n_bins if acc is not None else 1, len(CAUSE_CODE)
            ),
            self.link_rng,
            self.sci_rng if self.sci_rng is not None else self.link_rng,
        )
        if acc is not None:
            acc.add_counts(int(active.sum()), out)
        return out.tx, out.rx, out.p, out.cause

    def inband_leakage(self, total: NDArray[Any]) -> FloatArray:
        """``link.inband_emission_model=3gpp``: the leakage into each resource of each receiver,
        ``leak[rx, slot, v] = sum_i M[v, i] total[rx, slot, i]`` (mW, [N * R]), summed in ``i`` order
        element by element (so the compiled chunk's ``kernels.period_passes._leak_mw`` gives the same bits; a BLAS
        product may sum in another order).

        Args:
            total: [N * R] power per receiver and resource of the chunk, mW.
        """
        assert self.leakage is not None
        t2 = total.reshape(self.n * self.rri, self.n_sub)
        m = self.leakage
        leak = t2[:, :1] * m[:, 0]
        for i in range(1, self.n_sub):
            leak = leak + t2[:, i : i + 1] * m[:, i]
        return leak.reshape(-1)

    def _chunk_links(self, geo: Geometry, active: NDArray[np.bool_]) -> tuple[bool, IntArray]:
        """The links of a chunk with fewer transmitters than half the vehicles (the parts of a period
        that ``sps.reselection_timing=per_ue`` cuts, a run that ends mid-period), increasing, possibly
        none: ``(True, links)``; otherwise ``(False, empty)``, the kernel visiting every link and scanning
        the N x R sums. The grouping by transmitter is built once per period, on the first such chunk."""
        senders = np.flatnonzero(active)
        if 2 * senders.shape[0] >= self.n:
            return False, np.empty(0, dtype=np.int64)
        if geo.tx_start is None or geo.tx_index is None:
            geo.tx_start, geo.tx_index = kernels.links_by_transmitter(geo.tx, self.n)
        return True, kernels.active_links(geo.tx_start, geo.tx_index, senders)

    def sci_draws(self, sinr_db: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``sps.sci_decoding=sinr``: whether each link's receiver decodes the transmitter's SCI.

        The PSCCH (2 RBs of the subchannel next to the PSSCH in the same subframe, TS 36.211 9.4, pools
        with ``adjacencyPSCCH-PSSCH-r14`` of TS 36.331) is taken to see the link's SINR plus
        ``sps.sci_sinr_offset_db``: the same co-channel transmitters (their PSCCHs lie in the same
        RBs), in-band emission and noise per unit bandwidth as the PSSCH (docs/model.md, SCI
        decoding). Decoded iff ``u < 1 - BLER(SINR + offset)`` (:class:`cv2x_marl.sim.link.PscchCurve`),
        one uniform per link from :func:`cv2x_marl.sim.simulator.sci_stream`, independent of the PSSCH
        outcome's uniform.

        Args:
            sinr_db: [L] the PSSCH SINR of the chunk's links, in link order (dB).

        Returns:
            ``u`` [L] the uniforms and ``q`` [L] the decoding probabilities: decoded iff ``u < q``.
        """
        assert self.pscch_curve is not None and self.sci_rng is not None
        u = np.asarray(self.sci_rng.random(sinr_db.shape[0]), dtype=np.float64)
        return u, self.pscch_curve.decoding_probability(sinr_db + self.config.sps.sci_sinr_offset_db)

    def group_terms(
        self, tx: IntArray, rx: IntArray, active: NDArray[np.bool_], group: IntArray
    ) -> tuple[IntArray, IntArray]:
        """For every link, the other active transmitters with its transmitter's ``group`` value
        (the resource: co-channel; the slot: concurrent); one row per (link, partner).

        Args:
            tx, rx: [L] the links' transmitters and receivers.
            active: [N] which vehicles transmit in the chunk.
            group: [N] the grouping key per vehicle.

        Returns:
            ``rep`` [K]: index of the link; ``partner`` [K]: the other transmitter (never the
            link's own transmitter nor its receiver).
        """
        act = np.flatnonzero(active)
        order = act[np.argsort(group[act], kind="stable")]
        r_sorted = group[order]
        starts = np.flatnonzero(np.r_[True, r_sorted[1:] != r_sorted[:-1]])
        sizes = np.diff(np.r_[starts, order.shape[0]])
        group_start = np.zeros(self.n, dtype=np.int64)
        group_size = np.zeros(self.n, dtype=np.int64)
        pos_in_group = np.zeros(self.n, dtype=np.int64)
        gid = np.repeat(np.arange(starts.shape[0]), sizes)
        group_start[order] = starts[gid]
        group_size[order] = sizes[gid]
        pos_in_group[order] = np.arange(order.shape[0]) - starts[gid]
        deg = group_size[tx] - 1
        rep = np.repeat(np.arange(tx.shape[0]), deg)
        first = np.cumsum(deg) - deg
        k = np.arange(rep.shape[0]) - first[rep]
        a = tx[rep]
        k = k + (k >= pos_in_group[a])
        partner = order[group_start[a] + k]
        keep = partner != rx[rep]
        return rep[keep], partner[keep]

    def _mean_power_lookup(self, geo: Geometry, rx: IntArray, tx: IntArray) -> FloatArray:
        """Mean (unfaded) received power of arbitrary (rx, tx) pairs; 0 beyond the cut-off."""
        if self.sparse_state:  # pairs sorted by a * N + b (a < b); mean power symmetric
            h = geo.rx.shape[0] // 2
            keys = geo.rx[:h] * self.n + geo.tx[:h]
            want = np.minimum(rx, tx) * self.n + np.maximum(rx, tx)
            pos = np.minimum(np.searchsorted(keys, want), max(h - 1, 0))
            found = keys[pos] == want if h else np.zeros(want.shape[0], dtype=bool)
            return np.where(found, db_to_linear(geo.mean_rx_dbm_half[pos]) if h else 0.0, 0.0)
        dense = np.zeros((self.n, self.n))
        dense[geo.rx, geo.tx] = db_to_linear(geo.mean_rx_dbm)
        return dense[rx, tx]
