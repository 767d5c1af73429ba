"""The stage-1 network-level simulator of C-V2X sidelink Mode 4 (paper Sec. 3 and 6.1).

Time advances in reservation periods of ``traffic.rri_ms`` subframes. Within a period every
vehicle transmits once, on its reserved resource ``(slot, subchannel)``; positions are those at
the start of the period and the large-scale channel is computed once per period. So a period (or
the part of it a ``run`` covers) is one batch of array operations over vehicle pairs:

    geometry -> path loss + shadowing (+ fading) -> received powers [pairs]
    -> per (receiver, resource) power sums (bincount) -> SINR of eq. 8 for every link
    -> success probability + sampled outcome (+ loss cause, NSV, l) -> metrics, links table
    -> sensing (S-RSSI, SCI RSRP); at the end of the period: SPS counters and reselection,
       then mobility (``sps.reselection_timing=per_ue``: counters and reselections at each UE's
       packet arrival instead, the period cut after the slots where a counter expires).

Mobility (``vehicles.mobility``): the lane model of :mod:`cv2x_marl.sim.mobility` (default), or a
SUMO scenario stepped once per period through libsumo, or a replayed SUMO FCD trace
(:mod:`cv2x_marl.sim.sumo`, imported only then).

Interference at receiver b on link a -> b is the sum over the other vehicles transmitting on
a's subframe and subchannel, plus optionally in-band emission from the other subchannels of that
subframe (``link.inband_emission_model``: a flat ``link.inband_emission_db``, or the 3GPP mask of
:mod:`cv2x_marl.sim.inband`, weighted by the subchannel offset, which the S-RSSI sensing then
sees too); b receives nothing in a subframe where it transmits (half duplex).

Sensing records the PSSCH-RSRP of every SCI a receiver decodes (TS 36.213 14.1.1.6). Which SCIs it
decodes (``sps.sci_decoding``): ``always``, every one not lost to half duplex or below the
sensitivity; ``sinr``, a draw per link against the PSCCH BLER at the link's SINR
(:class:`cv2x_marl.sim.link.PscchCurve`), from a stream of its own (:func:`sci_stream`).

The :class:`Simulator` holds the pipeline and drives the parts that live in modules of their own: the
SPS state and procedures (:class:`cv2x_marl.sim.sps.SpsScheduler`), a period's chunks, numpy or compiled
(:class:`cv2x_marl.sim.chunk.ChunkRunner`), the pairs in range and their Verlet list
(:class:`cv2x_marl.sim.geometry.PairList`) and the snapshot types (:mod:`cv2x_marl.sim.snapshot`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.rng import STREAM_NAMES, RngStreams
from cv2x_marl.sim import channel, inband, kernels, link, mobility
from cv2x_marl.sim.chunk import COMPILED_CHUNK_MIN_LINKS, LINK_COLUMNS, ChunkLinksOut, ChunkRunner, joined
from cv2x_marl.sim.geometry import Geometry, PairList, displacement_m
from cv2x_marl.sim.memory import check_memory, uses_sparse_state
from cv2x_marl.sim.metrics import PrrAccumulator
from cv2x_marl.sim.road import Road
from cv2x_marl.sim.snapshot import LazySnapshot, PairMatrices, Snapshot, tx_eirp_dbm
from cv2x_marl.sim.sps import SpsScheduler
from cv2x_marl.units import db_to_linear, noise_power_dbm

if TYPE_CHECKING:
    from cv2x_marl.sim.sumo import MobilitySource

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["RunResult", "Simulator", "sci_stream"]


@dataclass
class RunResult:
    """What one :meth:`Simulator.run` measured."""

    metrics: PrrAccumulator
    links: dict[str, np.ndarray] | None
    n_subframes: int
    runtime_s: float
    extra: dict[str, float] = field(default_factory=dict)


def sci_stream(seed: int) -> np.random.Generator:
    """The random stream of the SCI decoding draws (``sps.sci_decoding=sinr``) for a root ``seed``.

    It is the child ``SeedSequence`` that follows the named streams of :class:`cv2x_marl.rng.RngStreams`
    (spawn key ``len(STREAM_NAMES)``): independent of them, so the SCI draws move no other draw (the
    PSSCH outcomes, the SPS choices, the mobility), and equal to the stream an eighth name appended to
    ``STREAM_NAMES`` would give.
    """
    child = np.random.SeedSequence(int(seed)).spawn(len(STREAM_NAMES) + 1)[-1]
    return np.random.default_rng(child)


class Simulator:
    """C-V2X Mode 4 network simulator.

    Example:
        >>> from cv2x_marl.config import preset
        >>> sim = Simulator(preset("paper"))
        >>> sim.reset(seed=1)
        >>> result = sim.run(1000)
        >>> 0.0 <= result.metrics.summary()["prr_mean"] <= 1.0
        True
    """

    def __init__(self, config: ScenarioConfig) -> None:
        if config.link.model == "rayleigh" and config.link.inband_emission_db is not None:
            raise ConfigError("link.inband_emission_db is not supported with link.model=rayleigh; set it to null")
        if config.link.model == "rayleigh" and config.link.inband_emission_model == "3gpp":
            raise ConfigError(
                "link.inband_emission_model=3gpp is not supported with link.model=rayleigh (its closed form "
                "counts co-channel interferers only); use link.inband_emission_model=flat"
            )
        self.config = config
        try:
            self.road = Road.from_config(config.road)
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
        #: vehicle slots: the vehicle count, or the capacity with vehicles.population=open
        self.n = config.n_slots
        self.open_population = config.vehicles.population == "open"
        self.rri = config.traffic.rri_ms
        self.n_sub = config.sps.n_subchannels
        self.n_res = self.rri * self.n_sub
        self.noise_mw = float(db_to_linear(noise_power_dbm(config.radio.noise_dbm, config.radio.noise_figure_db)))
        self.curve = link.load_per_curve(config.link.per_curve, config.link.per_interpolation)
        #: [n_sub, n_sub] in-band leakage M[victim, interferer] between different subchannels (zero
        #: diagonal) with link.inband_emission_model=3gpp; None otherwise (flat keeps its own arithmetic)
        leakage: FloatArray | None = None
        if config.link.inband_emission_model == "3gpp":
            leakage = inband.pool_leakage_weights(config)
        #: sps.sci_decoding=sinr: the PSCCH BLER curve that decides which SCIs a receiver decodes (None: all)
        self.pscch_curve: link.PscchCurve | None = None
        if config.sps.sci_decoding == "sinr":
            self.pscch_curve = link.load_pscch_curve()
        check_memory(config)  # refuse (ConfigError) before the N x N arrays: pair index here, shadowing in reset
        self.sparse_state = uses_sparse_state(config)
        #: the SPS state and procedures (TS 36.213 14.1.1.6, TS 36.321 5.14.1.1); its arrays are set by reset
        self.scheduler = SpsScheduler(config, self.n, self.noise_mw)
        #: the chunks of a period: the links' outcomes, the sensing sums, the metrics
        self.chunks = ChunkRunner(
            config, self.road, self.n, self.noise_mw, self.curve, self.pscch_curve, leakage, self.sparse_state
        )
        #: the compiled chunk (ChunkRunner._run_compiled) where it applies: no links table, link.model not
        #: rayleigh, at least compiled_min_links links in the period; False forces the numpy chunk (the
        #: reference the tests compare it with). Below the size the numpy chunk is as fast or faster (its calls
        #: cost less than the kernel's dispatch): measured 148 vs 168 us per period at 420 links, 283 vs 267 us
        #: at 1,560
        self.compiled_period = True
        self.compiled_min_links = COMPILED_CHUNK_MIN_LINKS
        #: the pairs in range, through a Verlet list (link.max_range_m set; PairList.skin_m)
        self.pair_list = PairList(config, self.road, self.n)
        self._source: MobilitySource | None = None
        #: keep the geometry of the period just ended (:attr:`last_geometry`) for the caller to read (the env's
        #: ``cv2x/Traffic-v1`` measures each period's received powers); off by default: it holds a second
        #: period's pair arrays in memory
        self.keep_period_geometry = False
        #: with :attr:`keep_period_geometry`: the pair geometry and received powers of the last period that ended
        #: (the period :attr:`last_links` describes), None before the first one
        self.last_geometry: Geometry | None = None
        if config.vehicles.mobility != "model":  # SUMO installed, files there: refuse now, not at reset
            from cv2x_marl.sim import sumo

            sumo.check_source(config)
        self._ready = False

    # ------------------------------------------------------------------ state
    def reset(self, seed: int, warmup_subframes: int | None = None) -> Snapshot:
        """Place the vehicles, draw initial resources, run the warm-up; return the snapshot."""
        cfg = self.config
        self.rng = RngStreams.from_seed(seed)
        self._ready = False  # until this reset completes (starting SUMO can fail)
        self.close()
        self.pair_list.clear()  # the Verlet list belongs to the previous episode's positions
        self.state: mobility.MobilityState
        if cfg.vehicles.mobility == "model":
            self.state = mobility.place(self.road, cfg.vehicles, self.n, self.rng.placement)
        else:  # SUMO lockstep or trace replay (docs/mobility.md); draws from the mobility stream only
            from cv2x_marl.sim import sumo

            self._source = sumo.open_source(cfg, self.rng.mobility)
            self.state = self._source.state
        #: [N] which slots hold a vehicle (vehicles.population=open; None: every slot, always)
        self.present: NDArray[np.bool_] | None = None
        if self.open_population:
            assert isinstance(self.state, mobility.TrackedState) and self.state.present is not None
            self.present = self.state.present.copy()
        shadowing_cls = channel.SparseShadowing if self.sparse_state else channel.Shadowing
        self.shadowing: channel.Shadowing | channel.SparseShadowing = shadowing_cls(
            self.n, cfg.channel.shadowing_decorrelation_m, self.rng.shadowing, cfg.channel.shadowing_correlation
        )
        self.scheduler.reset(self.rng.sps, self.rng.traffic, self.present)
        #: the SCI decoding draws (sps.sci_decoding=sinr) come from a stream of their own
        self.chunks.reset(self.rng.link, sci_stream(seed) if self.pscch_curve is not None else None)
        self.n_entries = 0
        self.n_departures = 0
        #: [K] slots whose vehicle left at the last period end (population=open), for the metrics
        self._vacated = np.empty(0, dtype=np.int64)
        self.subframe = 0
        self._geometry: Geometry | None = None
        self.offsets_m = np.zeros((self.n, 2))
        self.last_geometry = None
        #: speed and lane commands applied at each period end (:meth:`set_drive`; None: none, the lane model as it is)
        self._drive: tuple[FloatArray, IntArray, float, float] | None = None
        #: (tx, rx, p_success, cause) [L] of the last simulated part of a period (the env's traffic mode reads
        #: the period it ran); per_ue: all chunks of that part, in order
        self.last_links: ChunkLinksOut | None = None
        self._ready = True
        warm = cfg.sim.warmup_subframes if warmup_subframes is None else warmup_subframes
        if warm:
            self.run(warm, record=False)
        if cfg.sim.warmup_mode == "until_reselected":
            self._warm_until_reselected()
        return self.snapshot()

    def _warm_until_reselected(self) -> None:
        """``sim.warmup_mode=until_reselected``: go on, a period at a time, until every vehicle has left
        the random resource of :meth:`reset` by a sensing-based selection (TS 36.213 14.1.1.6), so
        that no random initial allocation survives into the measurement (issue 13, defect 2).

        Each vehicle reselects after a counter of at most ``counter_max`` periods with probability
        ``1 - keep_probability`` at each expiry, so this ends (after about ``counter_max / (1 - p)``
        periods times a log of N); ``sim.warmup_subframes`` caps the total at 10^7 subframes.
        """
        cap = 10**7
        while np.any(self.scheduler.initial_resource) and self.subframe < cap:
            self.run(self.rri - self.subframe % self.rri, record=False)

    def sps_state(self) -> dict[str, object]:
        """The SPS state now, JSON-ready (the run summary reports it at the start of the measurement).

        Returns:
            ``subframe``; ``share_initial_resource``: vehicles still on the random resource drawn at
            :meth:`reset` (no sensing-based selection yet); ``share_never_expired``: vehicles whose
            reselection counter has not expired yet; ``counter_mean`` and ``counter_histogram``
            (reselection counter value -> number of vehicles; TS 36.321 5.14.1.1).
        """
        return self.scheduler.state(self.subframe, self.present)

    @property
    def period_rsrp_dbm(self) -> FloatArray:
        """[N * R] SCI RSRP heard so far this period per receiver and resource, dBm (``-inf``: none)."""
        return self.scheduler.sci_rsrp_dbm(self.scheduler.period_sci_mw)

    @property
    def resource(self) -> IntArray:
        """[N] each vehicle's reserved resource, ``slot * n_sub + subchannel`` (-1: none; the scheduler's)."""
        return self.scheduler.resource

    @property
    def n_reselections(self) -> int:
        """Sensing-based selections since :meth:`reset` (the scheduler's count)."""
        return self.scheduler.n_reselections

    @property
    def slot(self) -> IntArray:
        """[N] slot of each reserved resource."""
        return self.scheduler.slot

    @property
    def subchannel(self) -> IntArray:
        """[N] subchannel of each reserved resource."""
        return self.scheduler.subchannel

    def snapshot(self) -> Snapshot:
        """Positions, velocities, resources and channel state now (copies)."""
        self._check_ready()
        geo = self._period_geometry()
        h = geo.rx.shape[0] // 2
        positions_m = geo.positions_m.copy()
        fields: dict[str, object] = {
            "subframe": self.subframe,
            "positions_m": positions_m,
            "velocities_mps": mobility.velocities_mps(self.state),
            "slot": self.slot.copy(),
            "subchannel": self.subchannel.copy(),
            "generation_slot": self.scheduler.generation_slot.copy(),
            "counter": self.scheduler.counter.copy(),
            "rri_ms": self.rri,
            "n_subchannels": self.n_sub,
            "present": None if self.present is None else self.present.copy(),
        }
        build = PairMatrices(
            self.config,
            self.road,
            self.n,
            positions_m,
            geo.rx[:h],
            geo.tx[:h],
            geo.los_half,
            geo.mean_rx_dbm_half,
        )
        if self.sparse_state:  # the N x N matrices only when read (copies of the pair arrays until then)
            return LazySnapshot.create(fields, build.copy())
        los, sh = build()
        return Snapshot(los=los, shadowing_db=sh, **fields)  # type: ignore[arg-type]

    @property
    def vehicle_ids(self) -> list[str | None] | None:
        """SUMO (or trace) IDs of the vehicles, vehicle ``i`` first (``vehicles.population=open``: the
        vehicle in each slot, None where empty); None with ``vehicles.mobility=model``."""
        return None if self._source is None else list(self._source.ids)

    def close(self) -> None:
        """Stop the SUMO simulation of ``vehicles.mobility=sumo`` (nothing to do otherwise; idempotent).

        ``reset`` starts a new one; libsumo holds one simulation per process, so a second simulator
        with SUMO mobility in the same process takes it over from the first.
        """
        if self._source is not None:
            self._source.close()
            self._source = None

    def _check_ready(self) -> None:
        if not self._ready:
            raise RuntimeError("call Simulator.reset(seed) before run() or snapshot()")

    def set_offsets(self, offsets_m: FloatArray) -> None:
        """Displace vehicles from their road positions by ``offsets_m`` [N, 2] (the env's traffic mode).

        Takes effect from the next period that has not started (the current period's geometry is
        recomputed if nothing of it has been simulated yet).
        """
        offsets_m = np.asarray(offsets_m, dtype=np.float64)
        if offsets_m.shape != (self.n, 2) or not np.all(np.isfinite(offsets_m)):
            raise ValueError(f"offsets_m must be a finite [{self.n}, 2] array")
        self.offsets_m = offsets_m.copy()
        if self.subframe % self.rri == 0:
            self._geometry = None

    def set_drive(self, target_mps: FloatArray, lane_change: IntArray, accel_mps2: float, decel_mps2: float) -> None:
        """Speed and lane commands of the lane model (``vehicles.mobility=model``; the env's Traffic task),
        applied at the end of every period from now on (:func:`cv2x_marl.sim.mobility.drive`, limit
        ``vehicles.speed_max_mps``), before the vehicles move; vehicles without a target (NaN) keep the
        lane model's constant speed. :meth:`reset` clears them.

        Args:
            target_mps: [N] target speeds (m/s; NaN: no command).
            lane_change: [N] +1 one lane left, 0 keep, -1 one lane right.
            accel_mps2, decel_mps2: the bounds of the speed change (m/s^2).
        """
        if self.config.vehicles.mobility != "model":
            raise ValueError("set_drive needs vehicles.mobility=model (SUMO drives its vehicles itself)")
        target = np.asarray(target_mps, dtype=np.float64).copy()
        lanes = np.asarray(lane_change, dtype=np.int64).copy()
        if target.shape != (self.n,) or lanes.shape != (self.n,):
            raise ValueError(f"target_mps and lane_change must have shape ({self.n},)")
        self._drive = (target, lanes, float(accel_mps2), float(decel_mps2))

    # --------------------------------------------------------------- geometry
    def displacement_m(self, pos_from: FloatArray, pos_to: FloatArray) -> FloatArray:
        """[..., 2] displacement ``pos_to - pos_from`` (minimum image when distances wrap)."""
        return displacement_m(self.config, self.road, pos_from, pos_to)

    @property
    def pair_skin_m(self) -> float:
        """The Verlet list's skin, m (:attr:`PairList.skin_m`; 0: a sweep every period)."""
        return self.pair_list.skin_m

    @pair_skin_m.setter
    def pair_skin_m(self, skin_m: float) -> None:
        self.pair_list.skin_m = skin_m

    def _pairs(self, pos: FloatArray) -> tuple[IntArray, IntArray]:
        """Unordered pairs ``(i, j)``, ``i < j``, sorted, within ``link.max_range_m`` (all without a cut-off);
        with ``vehicles.population=open`` only pairs of present vehicles (:meth:`PairList.pairs`)."""
        return self.pair_list.pairs(pos, self.present)

    def _period_geometry(self) -> Geometry:
        """Pair geometry and received powers for the current period (computed once per period)."""
        if self._geometry is not None:
            return self._geometry
        cfg = self.config
        pos = mobility.positions_m(self.road, self.state) + self.offsets_m
        i, j = self._pairs(pos)
        vel = mobility.velocities_mps(self.state)
        box = self.road.periodic_box_m if cfg.road.wrap_distances else np.full(2, np.inf)
        dx, dy, dist, rel = kernels.pair_geometry(
            np.ascontiguousarray(pos, dtype=np.float64), np.ascontiguousarray(vel, dtype=np.float64), i, j, box
        )
        if cfg.channel.los == "always" or self.road.kind == "highway":
            los = np.ones(i.shape[0], dtype=bool)
        else:
            hc, vc = self.road.corridors(pos if self.present is None else np.nan_to_num(pos))  # empty slots: NaN
            los = Road.corridor_los((hc[i], vc[i]), (hc[j], vc[j]))
        ch = cfg.channel
        if ch.pathloss == "winner_b1":  # dx, dy as they are: no [P, 2] copy
            pl = channel.winner_b1_db(dx, dy, los, cfg.radio.carrier_hz, ch.effective_height_m, ch.min_distance_m)
        else:
            pl = channel.path_loss_db(ch, cfg.radio.carrier_hz, np.column_stack((dx, dy)), los)
        del dx, dy
        z = np.empty(0)
        if ch.shadowing_std_db > 0 or ch.shadowing_nlos_std_db > 0:
            z = self.shadowing.sample(i, j, self.state.odometer_m, dist)
        gains = np.empty(0)
        if ch.fading == "rayleigh":
            gains = channel.rayleigh_power_gain(self.rng.fading, 2 * i.shape[0])
        mean_dbm, rx_mw = kernels.received_powers(
            tx_eirp_dbm(self.config), pl, z, los, float(ch.shadowing_std_db), float(ch.shadowing_nlos_std_db), gains
        )
        geo = Geometry(
            pos, np.concatenate([i, j]), np.concatenate([j, i]), np.concatenate([dist, dist]), rx_mw, los, mean_dbm, rel
        )
        self._geometry = geo
        return geo

    # -------------------------------------------------------------------- run
    def run(
        self,
        n_subframes: int,
        record: bool = True,
        progress: Callable[[int], object] | None = None,
        links_sink: Callable[[dict[str, np.ndarray]], object] | None = None,
    ) -> RunResult:
        """Simulate ``n_subframes`` subframes from the current state.

        Args:
            n_subframes: subframes to simulate (need not be a whole number of periods).
            record: measure PRR and keep the links table (False: warm-up).
            progress: called with the number of subframes done after each period.
            links_sink: with ``metrics.record_links``, receives the links table piece by piece (the
                columns of each simulated part of a period, in order) instead of the run keeping it
                in memory: memory stays bounded however long the run (``cv2x-marl simulate`` streams
                them into ``links.parquet``).

        Returns:
            The run's metrics and, when ``metrics.record_links`` and no ``links_sink``, the links
            table as columns.
        """
        self._check_ready()
        if n_subframes < 0:
            raise ValueError(f"n_subframes must be >= 0, got {n_subframes}")
        cfg = self.config
        acc = PrrAccumulator(self.n, cfg.metrics.prr_bin_m, cfg.metrics.max_distance_m)
        acc.open_population = self.present is not None  # node metrics per vehicle, not per slot
        self._vacated = np.empty(0, dtype=np.int64)
        if record:
            acc.sps_state_at_start = self.sps_state()
        keep_links = record and cfg.metrics.record_links
        cols: dict[str, list[np.ndarray]] = {c: [] for c in LINK_COLUMNS}
        t0 = time.perf_counter()
        end = self.subframe + n_subframes
        period_links: list[ChunkLinksOut] = []  # per_ue: the chunks
        per_ue = self.scheduler.per_ue
        while self.subframe < end:
            lo = self.subframe % self.rri
            hi = min(self.rri, lo + end - self.subframe)
            if per_ue:  # stop after the next subframe where a counter expires (or reaches 0)
                hi = self.scheduler.next_arrival_event(lo, hi)
                if lo == 0:
                    period_links = []
            before = self.last_links
            self._chunk(lo, hi, acc if record else None, cols if keep_links else None)
            if per_ue:
                if self.last_links is not before:
                    period_links.append(self.last_links)  # type: ignore[arg-type]  # set by _chunk
                self.scheduler.arrivals(lo, hi, self.subframe)
            if keep_links and links_sink is not None and cols[LINK_COLUMNS[0]]:
                links_sink({c: np.concatenate(v) for c, v in cols.items()})
                for v in cols.values():
                    v.clear()
            self.subframe += hi - lo
            if hi == self.rri:
                if len(period_links) > 1:  # per_ue cut the period: last_links is the whole period's
                    self.last_links = joined(period_links)
                period_links = []
                self._end_period()
                if record and self._vacated.size:  # population=open: a slot's next vehicle is a new node
                    acc.retire(self._vacated)
                    self._vacated = np.empty(0, dtype=np.int64)
            if progress is not None:
                progress(hi - lo)
        if len(period_links) > 1:  # a run ending mid-period: last_links holds the parts of it run here
            self.last_links = joined(period_links)
        keep = keep_links and links_sink is None
        links = {c: np.concatenate(v) if v else np.empty(0) for c, v in cols.items()} if keep else None
        return RunResult(acc, links, n_subframes, time.perf_counter() - t0)

    def _chunk(
        self,
        lo: int,
        hi: int,
        acc: PrrAccumulator | None,
        cols: dict[str, list[np.ndarray]] | None,
    ) -> None:
        """All transmissions of the current period whose slot lies in ``[lo, hi)`` (:meth:`ChunkRunner.run`:
        the compiled chunk from :attr:`compiled_min_links` links unless :attr:`compiled_period` is False)."""
        geo = self._period_geometry()
        compiled = self.compiled_period and geo.rx.shape[0] >= self.compiled_min_links
        links = self.chunks.run(lo, hi, self.subframe, geo, self.scheduler, acc, cols, compiled)
        if links is not None:
            self.last_links = links

    def _admit(self) -> None:
        """``vehicles.population=open``: after a mobility step, free the slots of the vehicles that left
        (their links end: no transmission, no reception) and set up those that entered: no SPS history
        (:meth:`SpsScheduler.admit`: they listen for one period), fresh shadowing towards everyone, a new
        generation slot, no offset."""
        st = self.state
        assert isinstance(st, mobility.TrackedState) and st.present is not None and st.entered is not None
        assert self.present is not None
        # a vehicle left when its slot empties or is handed to a new vehicle in the same step
        left = self.present & (~st.present | st.entered)
        self.n_departures += int(left.sum())
        self._vacated = np.flatnonzero(left)
        e = np.flatnonzero(st.entered)
        self.scheduler.admit(~st.present, e, self.rng.traffic)
        if e.size:
            self.n_entries += int(e.size)
            self.shadowing.renew(e, st.odometer_m)
            self.offsets_m[e] = 0.0
        self.present = st.present.copy()

    def _end_period(self) -> None:
        """Commit sensing, run the SPS counters and reselections (:meth:`SpsScheduler.end_period`), then move
        the vehicles."""
        self.scheduler.end_period(self.subframe, self.present)
        if self._source is not None:
            self.state = self._source.advance()
            if self.present is not None:
                self._admit()
        else:
            assert isinstance(self.state, mobility.VehicleState)
            if self._drive is not None:
                target, lanes, accel, decel = self._drive
                dt_s, limit = self.rri / 1000.0, self.config.vehicles.speed_max_mps
                self.state = mobility.drive(self.road, self.state, target, lanes, accel, decel, dt_s, limit)
            self.state = mobility.advance(self.road, self.config.road, self.state, self.rri / 1000.0, self.rng.mobility)
        self.last_geometry = self._geometry if self.keep_period_geometry else None
        self._geometry = None
