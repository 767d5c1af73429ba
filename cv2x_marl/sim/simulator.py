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
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.rng import STREAM_NAMES, RngStreams
from cv2x_marl.sim import channel, inband, kernels, link, mobility, sps
from cv2x_marl.sim.memory import check_memory, uses_sparse_state
from cv2x_marl.sim.metrics import CAUSE_CODE, PrrAccumulator
from cv2x_marl.sim.road import Road
from cv2x_marl.units import db_to_linear, noise_power_dbm

if TYPE_CHECKING:
    from cv2x_marl.sim.sumo import MobilitySource

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

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


@dataclass(frozen=True)
class Snapshot:
    """The network at one instant: what the env (and GBMU) start from.

    Attributes:
        subframe: absolute subframe index of the snapshot.
        positions_m: [N, 2] positions.
        velocities_mps: [N, 2] velocity vectors.
        slot: [N] subframe of each vehicle's reserved resource within the period, ``[0, RRI)``.
        subchannel: [N] subchannel of each reserved resource.
        generation_slot: [N] slot at which each vehicle generates its packets.
        counter: [N] SPS reselection counters.
        los: [N, N] line-of-sight flags (symmetric).
        shadowing_db: [N, N] shadowing (symmetric, dB, added as a loss).
        rri_ms: reservation interval.
        n_subchannels: subchannels per subframe.
        present: [N] which vehicle slots hold a vehicle (``vehicles.population=open``; None: all).
            An empty slot has NaN position and velocity and slot -1; a vehicle that entered and is
            still listening (no resource selected yet) has slot -1 too.
    """

    subframe: int
    positions_m: FloatArray
    velocities_mps: FloatArray
    slot: IntArray
    subchannel: IntArray
    generation_slot: IntArray
    counter: IntArray
    los: NDArray[np.bool_]
    shadowing_db: FloatArray
    rri_ms: int
    n_subchannels: int
    present: NDArray[np.bool_] | None = None


class _PairMatrices:
    """Builds a snapshot's ``[N, N]`` LOS and shadowing matrices from the unordered pairs in range.

    Pairs out of range (no entry) read LOS and 0 dB, as before. The shadowing of a pair is its
    large-scale loss minus the path loss: ``(EIRP - PL(d, LOS)) - mean received power``.
    """

    def __init__(
        self,
        config: ScenarioConfig,
        road: Road,
        n: int,
        positions_m: FloatArray,
        i: IntArray,
        j: IntArray,
        los: NDArray[np.bool_],
        mean_rx_dbm: FloatArray,
    ) -> None:
        self.config, self.road, self.n = config, road, n
        self.positions_m, self.i, self.j, self.los, self.mean_rx_dbm = positions_m, i, j, los, mean_rx_dbm

    def copy(self) -> _PairMatrices:
        """The same builder over copies of the pair arrays (the caller's may be views of larger ones)."""
        return _PairMatrices(
            self.config, self.road, self.n, self.positions_m, self.i.copy(), self.j.copy(), self.los.copy(),
            self.mean_rx_dbm.copy(),
        )  # fmt: skip

    def __call__(self) -> tuple[NDArray[np.bool_], FloatArray]:
        """``(los, shadowing_db)``, both ``[N, N]`` and symmetric."""
        n, a, b = self.n, self.i, self.j
        los = np.ones((n, n), dtype=bool)
        sh = np.zeros((n, n))
        los[a, b] = los[b, a] = self.los
        d = self.positions_m[b] - self.positions_m[a]
        disp = self.road.minimum_image(d) if self.config.road.wrap_distances else d
        pl_free = channel.path_loss_db(self.config.channel, self.config.radio.carrier_hz, disp, self.los)
        sh[a, b] = sh[b, a] = (_tx_eirp_dbm(self.config) - pl_free) - self.mean_rx_dbm
        return los, sh


class _LazyPairMatrix:
    """``Snapshot.los`` / ``.shadowing_db`` of a :class:`_LazySnapshot`: built on first read, then kept."""

    def __set_name__(self, owner: type, name: str) -> None:
        self._name = name

    def __get__(self, obj: _LazySnapshot | None, objtype: type | None = None) -> np.ndarray:
        if obj is None:
            return self  # type: ignore[return-value]  # the descriptor itself, read on the class
        los, sh = obj.__dict__.pop("_build")()
        object.__setattr__(obj, "los", los)  # instance attributes from now on (this is not a data descriptor)
        object.__setattr__(obj, "shadowing_db", sh)
        return obj.__dict__[self._name]


class _LazySnapshot(Snapshot):
    """A :class:`Snapshot` whose ``[N, N]`` ``los`` and ``shadowing_db`` are built when first read.

    With the sparse pair state (:func:`~cv2x_marl.sim.memory.uses_sparse_state`) :meth:`Simulator.reset`
    returns one: until read it holds the pair arrays only (25 bytes per pair in range); the values,
    once read, are those an eager snapshot has.
    """

    los = _LazyPairMatrix()
    shadowing_db = _LazyPairMatrix()

    @classmethod
    def create(cls, fields: dict[str, object], build: _PairMatrices) -> _LazySnapshot:
        """The snapshot with the given non-matrix ``fields`` and the matrices' builder."""
        obj = object.__new__(cls)
        for name, value in fields.items():
            object.__setattr__(obj, name, value)
        object.__setattr__(obj, "_build", build)
        return obj


def _tx_eirp_dbm(config: ScenarioConfig) -> float:
    """Transmit power plus both antenna gains, dBm."""
    r = config.radio
    return r.tx_power_dbm + r.tx_antenna_gain_dbi + r.rx_antenna_gain_dbi


@dataclass
class RunResult:
    """What one :meth:`Simulator.run` measured."""

    metrics: PrrAccumulator
    links: dict[str, np.ndarray] | None
    n_subframes: int
    runtime_s: float
    extra: dict[str, float] = field(default_factory=dict)


def _nan_mean_first_axis(x: NDArray[np.float32]) -> NDArray[np.float32]:
    """``np.nanmean(x, axis=0)`` (same float32 result; NaN where all are NaN, without a warning)."""
    valid = ~np.isnan(x)
    total = np.where(valid, x, np.float32(0.0)).sum(axis=0)
    with np.errstate(invalid="ignore"):
        return np.asarray(total / valid.sum(axis=0), dtype=np.float32)


def sci_stream(seed: int) -> np.random.Generator:
    """The random stream of the SCI decoding draws (``sps.sci_decoding=sinr``) for a root ``seed``.

    It is the child ``SeedSequence`` that follows the named streams of :class:`cv2x_marl.rng.RngStreams`
    (spawn key ``len(STREAM_NAMES)``): independent of them, so the SCI draws move no other draw (the
    PSSCH outcomes, the SPS choices, the mobility), and equal to the stream an eighth name appended to
    ``STREAM_NAMES`` would give.
    """
    child = np.random.SeedSequence(int(seed)).spawn(len(STREAM_NAMES) + 1)[-1]
    return np.random.default_rng(child)


#: the period's ordered pairs from which a chunk runs compiled (Simulator.compiled_min_links)
COMPILED_CHUNK_MIN_LINKS = 1000


def _joined(
    parts: list[tuple[IntArray, IntArray, FloatArray, NDArray[np.int8]]],
) -> tuple[IntArray, IntArray, FloatArray, NDArray[np.int8]]:
    """``Simulator.last_links`` of the chunks ``parts`` of one period, in order (``tx, rx, p, cause``)."""
    tx, rx, p, cause = (np.concatenate(cols) for cols in zip(*parts, strict=True))
    return tx, rx, p, cause


@dataclass
class _Geometry:
    """Per-period pair quantities. Ordered pairs are (rx, tx); the first half is (i, j), i < j.

    LOS, mean received power and relative speed are symmetric: kept for the P unordered pairs
    (``*_half``) and doubled to the 2P ordered ones only when read (the links table, the Rayleigh
    model), so a run without them never builds those arrays (corridor scale: 100 MB at 10,000 vehicles).
    """

    positions_m: FloatArray
    rx: IntArray
    tx: IntArray
    distance_m: FloatArray
    rx_mw: FloatArray
    los_half: NDArray[np.bool_]
    mean_rx_dbm_half: FloatArray
    rel_speed_mps_half: FloatArray
    #: the links grouped by transmitter (kernels.links_by_transmitter), built when a chunk needs them
    tx_start: IntArray | None = None
    tx_index: IntArray | None = None

    @functools.cached_property
    def los(self) -> NDArray[np.bool_]:
        """[2P] LOS of each ordered pair."""
        return np.concatenate([self.los_half, self.los_half])

    @functools.cached_property
    def mean_rx_dbm(self) -> FloatArray:
        """[2P] mean (unfaded) received power of each ordered pair, dBm."""
        return np.concatenate([self.mean_rx_dbm_half, self.mean_rx_dbm_half])

    @functools.cached_property
    def rel_speed_mps(self) -> FloatArray:
        """[2P] relative speed of each ordered pair, m/s."""
        return np.concatenate([self.rel_speed_mps_half, self.rel_speed_mps_half])


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
        self._rsrp_offset_db = 10.0 * np.log10(12 * config.sps.subchannel_rbs)
        #: [n_sub, n_sub] in-band leakage M[victim, interferer] between different subchannels (zero
        #: diagonal) with link.inband_emission_model=3gpp; None otherwise (flat keeps its own arithmetic)
        self._leakage: FloatArray | None = None
        if config.link.inband_emission_model == "3gpp":
            self._leakage = inband.pool_leakage_weights(config)
        self._sensing_periods = max(1, config.sps.sensing_window_ms // self.rri)
        #: sps.reselection_timing=per_ue: counters and reselections at each UE's packet arrival
        self._per_ue = config.sps.reselection_timing == "per_ue"
        #: sps.sci_decoding=sinr: the PSCCH BLER curve that decides which SCIs a receiver decodes (None: all)
        self.pscch_curve: link.PscchCurve | None = None
        if config.sps.sci_decoding == "sinr":
            self.pscch_curve = link.load_pscch_curve()
        #: the PSCCH curve's SINR points in linear units (where its BLER is interpolated), for the kernel
        self._pscch_lin = np.power(10.0, self.pscch_curve.sinr_db / 10.0) if self.pscch_curve is not None else None
        check_memory(config)  # refuse (ConfigError) before the N x N arrays: pair index here, shadowing in reset
        self.sparse_state = uses_sparse_state(config)
        #: the compiled chunk (_chunk_compiled) where it applies: no links table, link.model not rayleigh,
        #: at least compiled_min_links links in the period; False forces the numpy chunk (the reference the
        #: tests compare it with). Below the size the numpy chunk is as fast or faster (its calls cost less
        #: than the kernel's dispatch): measured 148 vs 168 us per period at 420 links, 283 vs 267 us at 1,560
        self.compiled_period = True
        self.compiled_min_links = COMPILED_CHUNK_MIN_LINKS
        self._all_pairs: tuple[IntArray, IntArray] | None = None
        #: Verlet list of the pairs in range (link.max_range_m set): the sweep runs at the cut-off plus this
        #: skin, and until a vehicle has moved half of it the period's pairs are that list filtered at the
        #: cut-off, the same pairs in the same order (kernels.filter_pairs_within_range; tested). 0: a sweep
        #: every period. 5 % of the cut-off: highway speeds rebuild it every 6-20 periods
        self.pair_skin_m = 0.05 * config.link.max_range_m if config.link.max_range_m is not None else 0.0
        #: (build positions, slots of an open population, skin, i, j) of the list in use
        self._pair_list: (
            tuple[FloatArray, NDArray[np.int64] | None, float, NDArray[np.int32], NDArray[np.int32]] | None
        ) = None
        if config.link.max_range_m is None:  # the compiled sweep gives the pairs in range otherwise
            iu, ju = np.triu_indices(self.n, 1)
            self._all_pairs = (iu.astype(np.int64), ju.astype(np.int64))
        self._source: MobilitySource | None = None
        if config.vehicles.mobility != "model":  # SUMO installed, files there: refuse now, not at reset
            from cv2x_marl.sim import sumo

            sumo.check_source(config)
        self._ready = False

    # ------------------------------------------------------------------ state
    def reset(self, seed: int, warmup_subframes: int | None = None) -> Snapshot:
        """Place the vehicles, draw initial resources, run the warm-up; return the snapshot."""
        cfg = self.config
        self.rng = RngStreams.from_seed(seed)
        #: the SCI decoding draws (sps.sci_decoding=sinr), a stream of its own
        self._sci_rng = sci_stream(seed) if self.pscch_curve is not None else None
        self._ready = False  # until this reset completes (starting SUMO can fail)
        self.close()
        self._pair_list = None  # the Verlet list belongs to the previous episode's positions
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
        if cfg.traffic.synchronous:
            self.generation_slot = np.zeros(self.n, dtype=np.int64)
        else:
            self.generation_slot = self.rng.traffic.integers(0, self.rri, size=self.n)
        cand = sps.candidate_resources(self.generation_slot, cfg.sps, self.rri)
        pick = self.rng.sps.integers(0, cand.shape[1], size=self.n)
        self.resource = cand[np.arange(self.n), pick]
        self.counter = sps.draw_counters(cfg.sps, self.rri, self.n, self.rng.sps)
        self.initial_resource = np.ones(self.n, dtype=bool)  # still on the random resource of reset
        self.n_expiries_per_vehicle = np.zeros(self.n, dtype=np.int64)
        self._releasing = np.zeros(self.n, dtype=bool)
        #: [N] vehicles that entered and listen for a period before selecting (population=open)
        self._joining = np.zeros(self.n, dtype=bool)
        if self.present is not None:  # empty slots: no resource (slot -1: never active), no counter
            self.resource[~self.present] = -1
            self.counter[~self.present] = 0
            self.initial_resource[~self.present] = False
        self.n_entries = 0
        self.n_departures = 0
        #: [K] slots whose vehicle left at the last period end (population=open), for the metrics
        self._vacated = np.empty(0, dtype=np.int64)
        if cfg.sps.reservation_signalling == "standard" and not self._per_ue:  # per_ue: at the arrivals
            self._decide_releases()
        self.subframe = 0
        self._rssi_ring = np.full((self._sensing_periods, self.n, self.n_res), np.nan, dtype=np.float32)
        #: the compiled chunk's scratch for the power sums per receiver and resource (zero between chunks)
        self._chunk_total = np.zeros(self.n * self.n_res)
        #: ... and for the flat in-band model's power per receiver and subframe
        self._chunk_total_slot = np.zeros(self.n * self.rri if self.config.link.inband_emission_db is not None else 0)
        self._new_period_buffers()
        if self._per_ue:
            #: [N * R] strongest decoded SCI of the period before the current one (per_ue sensing), mW
            self._prev_sci_mw = np.zeros(self.n * self.n_res)
            #: [N] the slot a vehicle left by a reselection in the current period (-1: none)
            self._moved_from = np.full(self.n, -1, dtype=np.int64)
        self._geometry: _Geometry | None = None
        self.n_reselections = 0
        self.n_expiries = 0
        self.n_keeps = 0
        self.offsets_m = np.zeros((self.n, 2))
        #: (tx, rx, p_success, cause) [L] of the last simulated part of a period (the env's traffic mode reads
        #: the period it ran); per_ue: all chunks of that part, in order
        self.last_links: tuple[IntArray, IntArray, FloatArray, NDArray[np.int8]] | None = None
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
        while np.any(self.initial_resource) and self.subframe < cap:
            self.run(self.rri - self.subframe % self.rri, record=False)

    def sps_state(self) -> dict[str, object]:
        """The SPS state now, JSON-ready (the run summary reports it at the start of the measurement).

        Returns:
            ``subframe``; ``share_initial_resource``: vehicles still on the random resource drawn at
            :meth:`reset` (no sensing-based selection yet); ``share_never_expired``: vehicles whose
            reselection counter has not expired yet; ``counter_mean`` and ``counter_histogram``
            (reselection counter value -> number of vehicles; TS 36.321 5.14.1.1).
        """
        on = slice(None) if self.present is None else self.resource >= 0  # vehicles holding a resource
        values, counts = np.unique(self.counter[on], return_counts=True)
        out: dict[str, object] = {
            "subframe": int(self.subframe),
            "share_initial_resource": float(np.mean(self.initial_resource[on])),
            "share_never_expired": float(np.mean(self.n_expiries_per_vehicle[on] == 0)),
            "counter_mean": float(np.mean(self.counter[on])),
            "counter_histogram": {str(int(v)): int(c) for v, c in zip(values, counts, strict=True)},
        }
        if self.present is not None:  # population=open: the shares are over the vehicles holding a resource
            out["n_present"] = int(self.present.sum())
            out["n_listening"] = int((self._joining & self.present).sum())
        return out

    def _new_period_buffers(self) -> None:
        self._period_rssi = np.zeros(self.n * self.n_res)
        #: [N * R] strongest decoded SCI per receiver and resource this period (PSSCH power, mW; 0: none),
        #: kept linear so that only the rows the sensing reads are taken to dBm (:meth:`_sci_rsrp_dbm`)
        self._period_sci_mw = np.zeros(self.n * self.n_res)

    @property
    def period_rsrp_dbm(self) -> FloatArray:
        """[N * R] SCI RSRP heard so far this period per receiver and resource, dBm (``-inf``: none)."""
        return self._sci_rsrp_dbm(self._period_sci_mw)

    def _sci_rsrp_dbm(self, sci_mw: FloatArray) -> FloatArray:
        """The SCI RSRP (dBm per resource element, ``-inf``: no SCI) of strongest-SCI powers (mW, any shape):
        ``10 log10(P) - 10 log10(12 x RBs)``, the maximum over the SCIs' own RSRP (the logarithm is monotone)."""
        with np.errstate(divide="ignore"):
            return np.asarray(10.0 * np.log10(sci_mw) - self._rsrp_offset_db)

    @property
    def slot(self) -> IntArray:
        """[N] slot of each reserved resource."""
        return self.resource // self.n_sub

    @property
    def subchannel(self) -> IntArray:
        """[N] subchannel of each reserved resource."""
        return self.resource % self.n_sub

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
            "generation_slot": self.generation_slot.copy(),
            "counter": self.counter.copy(),
            "rri_ms": self.rri,
            "n_subchannels": self.n_sub,
            "present": None if self.present is None else self.present.copy(),
        }
        build = _PairMatrices(
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
            return _LazySnapshot.create(fields, build.copy())
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

    # --------------------------------------------------------------- geometry
    def displacement_m(self, pos_from: FloatArray, pos_to: FloatArray) -> FloatArray:
        """[..., 2] displacement ``pos_to - pos_from`` (minimum image when distances wrap)."""
        d = pos_to - pos_from
        return self.road.minimum_image(d) if self.config.road.wrap_distances else d

    def _pairs(self, pos: FloatArray) -> tuple[IntArray, IntArray]:
        """Unordered pairs ``(i, j)``, ``i < j``, sorted, within ``link.max_range_m`` (all without a cut-off);
        with ``vehicles.population=open`` only pairs of present vehicles."""
        if self.present is not None:
            idx = np.flatnonzero(self.present)
            i, j = self._pairs_of(pos[idx], idx)
            return idx[i], idx[j]  # idx is increasing: the order is kept
        return self._pairs_of(pos, None)

    def _pairs_of(self, pos: FloatArray, idx: NDArray[np.int64] | None) -> tuple[IntArray, IntArray]:
        """The pairs of ``pos`` [M, 2] (the slots ``idx`` of an open population; None: every slot)."""
        rng_m = self.config.link.max_range_m
        if rng_m is None:
            if idx is not None and idx.shape[0] != self.n:
                iu, ju = np.triu_indices(pos.shape[0], 1)
                return iu.astype(np.int64), ju.astype(np.int64)
            assert self._all_pairs is not None
            return self._all_pairs
        # a compiled sweep along x (kernels.pairs_within_range): the KD-tree's pairs (scipy's query_pairs,
        # tested), sorted; ~4x faster at scale and ~3x at 200 vehicles, and no scipy import. Through a
        # Verlet list (pair_skin_m): the sweep at the cut-off plus the skin, filtered every period
        pos = np.ascontiguousarray(pos, dtype=np.float64)
        box = self.road.periodic_box_m if self.config.road.wrap_distances else np.full(2, np.inf)
        skin = self.pair_skin_m
        if skin <= 0.0:
            return kernels.pairs_within_range(pos, box, float(rng_m))
        cached = self._pair_list
        if cached is not None:
            pos0, idx0, skin0, ci, cj = cached
            same_slots = (idx is None and idx0 is None) or (
                idx is not None and idx0 is not None and np.array_equal(idx, idx0)
            )
            if same_slots and skin0 == skin:  # a changed pair_skin_m rebuilds it
                moved = self.displacement_m(pos0, pos)
                # a pair outside r + skin at the build is still outside r while 2 max |moved| < skin (the
                # minimum-image distance is a metric); the margin covers the rounding of these sums
                if 2.0 * float(np.sqrt(np.max(np.einsum("ij,ij->i", moved, moved), initial=0.0))) < skin * (1 - 1e-6):
                    return kernels.filter_pairs_within_range(pos, box, float(rng_m), ci, cj)
        wide_i, wide_j = kernels.pairs_within_range(pos, box, float(rng_m) + skin)
        ci, cj = wide_i.astype(np.int32), wide_j.astype(np.int32)  # slots < 2^31: half the memory kept
        del wide_i, wide_j
        self._pair_list = (pos.copy(), None if idx is None else idx.copy(), skin, ci, cj)
        return kernels.filter_pairs_within_range(pos, box, float(rng_m), ci, cj)

    def _tx_eirp_dbm(self) -> float:
        return _tx_eirp_dbm(self.config)

    def _period_geometry(self) -> _Geometry:
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
            self._tx_eirp_dbm(), pl, z, los, float(ch.shadowing_std_db), float(ch.shadowing_nlos_std_db), gains
        )
        geo = _Geometry(
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
        period_links: list[tuple[IntArray, IntArray, FloatArray, NDArray[np.int8]]] = []  # per_ue: the chunks
        while self.subframe < end:
            lo = self.subframe % self.rri
            hi = min(self.rri, lo + end - self.subframe)
            if self._per_ue:  # stop after the next subframe where a counter expires (or reaches 0)
                hi = self._next_arrival_event(lo, hi)
                if lo == 0:
                    period_links = []
            before = self.last_links
            self._chunk(lo, hi, acc if record else None, cols if keep_links else None)
            if self._per_ue:
                if self.last_links is not before:
                    period_links.append(self.last_links)  # type: ignore[arg-type]  # set by _chunk
                self._arrivals(lo, hi)
            if keep_links and links_sink is not None and cols[LINK_COLUMNS[0]]:
                links_sink({c: np.concatenate(v) for c, v in cols.items()})
                for v in cols.values():
                    v.clear()
            self.subframe += hi - lo
            if hi == self.rri:
                if len(period_links) > 1:  # per_ue cut the period: last_links is the whole period's
                    self.last_links = _joined(period_links)
                period_links = []
                self._end_period()
                if record and self._vacated.size:  # population=open: a slot's next vehicle is a new node
                    acc.retire(self._vacated)
                    self._vacated = np.empty(0, dtype=np.int64)
            if progress is not None:
                progress(hi - lo)
        if len(period_links) > 1:  # a run ending mid-period: last_links holds the parts of it run here
            self.last_links = _joined(period_links)
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
        """All transmissions of the current period whose slot lies in ``[lo, hi)``."""
        cfg = self.config
        geo = self._period_geometry()
        slot = self.slot
        active = (slot >= lo) & (slot < hi)
        if not np.any(active):
            return
        compiled = self.compiled_period and geo.rx.shape[0] >= self.compiled_min_links
        if compiled and cols is None and cfg.link.model != "rayleigh":
            self._chunk_compiled(geo, active, acc)
            return
        sel = active[geo.tx]
        rx, tx = geo.rx[sel], geo.tx[sel]
        s_mw = geo.rx_mw[sel]
        res_tx = self.resource[tx]
        key = rx * self.n_res + res_tx
        total = np.bincount(key, weights=s_mw, minlength=self.n * self.n_res)
        i_mw = np.maximum(total[key] - s_mw, 0.0)
        if cfg.link.inband_emission_db is not None:
            slot_key = rx * self.rri + slot[tx]
            total_slot = np.bincount(slot_key, weights=s_mw, minlength=self.n * self.rri)
            i_mw = i_mw + db_to_linear(cfg.link.inband_emission_db) * np.maximum(total_slot[slot_key] - total[key], 0.0)
        leak_mw: FloatArray | None = None
        if self._leakage is not None:  # 3gpp: leak[rx, slot, v] = sum_i M[v, i] total[rx, slot, i]
            leak_mw = self._inband_leakage(total)
            i_mw = i_mw + leak_mw[key]
        hd = slot[rx] == slot[tx]
        sinr_db = 10.0 * np.log10(s_mw / (i_mw + self.noise_mw))
        snr_db = 10.0 * np.log10(s_mw / self.noise_mw)
        rx_dbm = 10.0 * np.log10(s_mw)
        n_links = rx.shape[0]

        need_triples = cols is not None or cfg.link.model == "rayleigh"
        if need_triples:
            rep, partner = self._co_channel_terms(tx, rx, active)
        model = cfg.link.model
        if model == "per_table":
            p = self.curve.success(sinr_db)
            p0 = self.curve.success(snr_db)
        elif model == "threshold":
            p = link.threshold_success(sinr_db, cfg.link.sinr_threshold_db)
            p0 = link.threshold_success(snr_db, cfg.link.sinr_threshold_db)
        else:
            mean_s = db_to_linear(geo.mean_rx_dbm[sel])
            mean_i = self._mean_power_lookup(rx[rep], partner)
            p = link.rayleigh_success(mean_s, self.noise_mw, mean_i, rep, cfg.link.sinr_threshold_db)
            p0 = link.rayleigh_success(mean_s, self.noise_mw, np.empty(0), rep[:0], cfg.link.sinr_threshold_db)
        u = self.rng.link.random(n_links)
        if model == "rayleigh":
            theta = cfg.link.sinr_threshold_db
            outcome, would0 = sinr_db >= theta, snr_db >= theta
        else:
            outcome, would0 = u < p, u < p0
        sci_ok: NDArray[np.bool_] | None = None
        if self.pscch_curve is not None:  # sps.sci_decoding=sinr: one SCI draw per link
            u_sci, q = self._sci_draws(sinr_db)
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

        self.last_links = (tx, rx, p, cause)
        # sensing: S-RSSI of every resource heard in this chunk, SCI RSRP of every decodable SCI
        self._period_rssi += total
        if leak_mw is not None:  # 3gpp: S-RSSI is the energy in the subchannel, leakage included (as WiLabV2Xsim)
            self._period_rssi += leak_mw
        sci = ~fail & ~self._releasing[tx]  # a UE's last SCI before reselecting reserves nothing (standard)
        if sci_ok is not None:  # sps.sci_decoding=sinr: only a decoded PSCCH reserves
            sci &= sci_ok
        np.maximum.at(self._period_sci_mw, key[sci], s_mw[sci])

        if acc is not None:
            acc.add(tx, geo.distance_m[sel], p, outcome, cause, int(active.sum()))
        if cols is not None:
            rng_i = cfg.metrics.interferer_range_m
            if cfg.metrics.nsv_scope == "concurrent":  # every transmitter of the subframe, any subchannel
                rep, partner = self._group_terms(tx, rx, active, slot)
            dpart = self.displacement_m(geo.positions_m[rx[rep]], geo.positions_m[partner])
            dist_i = np.hypot(dpart[:, 0], dpart[:, 1])
            near = dist_i <= rng_i
            nsv = np.bincount(rep[near], minlength=n_links)
            l_m = np.full(n_links, rng_i)
            np.minimum.at(l_m, rep[near], dist_i[near])
            period_start = self.subframe - lo
            cols["tx"].append(tx.astype(np.int32))
            cols["rx"].append(rx.astype(np.int32))
            cols["subframe"].append(period_start + slot[tx])
            cols["subchannel"].append(self.subchannel[tx].astype(np.int16))
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

    def _chunk_compiled(self, geo: _Geometry, active: NDArray[np.bool_], acc: PrrAccumulator | None) -> None:
        """:meth:`_chunk` in compiled passes over the chunk's links (:func:`kernels.period_chunk`; no links
        table, ``link.model`` per_table or threshold, either in-band emission model): the same draws
        from the same streams, the same sums in the same order, the dB values and the PER and PSCCH
        interpolation with numpy's formulas, taken only where a comparison needs them; tested equal to the
        numpy path (``tests/sim/test_scale.py``, ``tests/sim/test_sci_decoding.py``)."""
        cfg = self.config
        nb = acc.n_bins if acc is not None else 1
        sens = cfg.radio.sensitivity_dbm
        code = kernels.MODEL_THRESHOLD if cfg.link.model == "threshold" else self.curve.kernel_model
        pscch = self.pscch_curve
        sci_lin, sci_bler = np.empty(0), np.empty(0)  # sps.sci_decoding=always: every SCI
        if pscch is not None and self._pscch_lin is not None:
            sci_lin, sci_bler = self._pscch_lin, pscch.bler
        tx, rx, p, cause, bin_n, bin_dec, bin_exp, bin_causes, node_n, node_dec, node_exp = kernels.period_chunk(
            geo.rx,
            geo.tx,
            geo.distance_m,
            geo.rx_mw,
            active,
            self.resource,
            self.slot,
            self.n_res,
            self.noise_mw,
            self.rng.link,
            code,
            self.curve.sinr_db,
            self.curve.per,
            float(cfg.link.sinr_threshold_db),
            -np.inf if sens is None else float(sens),
            self._releasing,
            self._period_rssi,
            self._period_sci_mw,
            acc.bin_m if acc is not None else 1.0,
            nb,
            len(CAUSE_CODE),
            *self._chunk_links(geo, active),
            self._chunk_total,
            self._sci_rng if self._sci_rng is not None else self.rng.link,
            sci_lin,
            sci_bler,
            float(cfg.sps.sci_sinr_offset_db),
            bool(cfg.sps.sci_gates_pssch),
            self.n_sub,
            float(db_to_linear(cfg.link.inband_emission_db)) if cfg.link.inband_emission_db is not None else 0.0,
            self._chunk_total_slot,
            self._leakage if self._leakage is not None else np.empty((0, 0)),
            kernels.chunk_tile_subframes(self.n, self.n_sub, self.rri),
        )
        self.last_links = (tx, rx, p, cause)
        if acc is not None:
            acc.add_counts(int(active.sum()), bin_n, bin_dec, bin_exp, bin_causes, node_n, node_dec, node_exp)

    def _inband_leakage(self, total: NDArray[Any]) -> FloatArray:
        """``link.inband_emission_model=3gpp``: the leakage into each resource of each receiver,
        ``leak[rx, slot, v] = sum_i M[v, i] total[rx, slot, i]`` (mW, [N * R]), summed in ``i`` order
        element by element (so the compiled chunk's ``kernels.period._leak_mw`` gives the same bits; a BLAS
        product may sum in another order).

        Args:
            total: [N * R] power per receiver and resource of the chunk, mW.
        """
        assert self._leakage is not None
        t2 = total.reshape(self.n * self.rri, self.n_sub)
        m = self._leakage
        leak = t2[:, :1] * m[:, 0]
        for i in range(1, self.n_sub):
            leak = leak + t2[:, i : i + 1] * m[:, i]
        return leak.reshape(-1)

    def _chunk_links(self, geo: _Geometry, active: NDArray[np.bool_]) -> tuple[bool, IntArray]:
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

    def _sci_draws(self, sinr_db: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``sps.sci_decoding=sinr``: whether each link's receiver decodes the transmitter's SCI.

        The PSCCH (2 RBs of the subchannel next to the PSSCH in the same subframe, TS 36.211 9.4, pools
        with ``adjacencyPSCCH-PSSCH-r14`` of TS 36.331) is taken to see the link's SINR plus
        ``sps.sci_sinr_offset_db``: the same co-channel transmitters (their PSCCHs lie in the same
        RBs), in-band emission and noise per unit bandwidth as the PSSCH (docs/model.md, SCI
        decoding). Decoded iff ``u < 1 - BLER(SINR + offset)`` (:class:`cv2x_marl.sim.link.PscchCurve`),
        one uniform per link from :func:`sci_stream`, independent of the PSSCH outcome's uniform.

        Args:
            sinr_db: [L] the PSSCH SINR of the chunk's links, in link order (dB).

        Returns:
            ``u`` [L] the uniforms and ``q`` [L] the decoding probabilities: decoded iff ``u < q``.
        """
        assert self.pscch_curve is not None and self._sci_rng is not None
        u = np.asarray(self._sci_rng.random(sinr_db.shape[0]), dtype=np.float64)
        return u, self.pscch_curve.decoding_probability(sinr_db + self.config.sps.sci_sinr_offset_db)

    def _co_channel_terms(self, tx: IntArray, rx: IntArray, active: NDArray[np.bool_]) -> tuple[IntArray, IntArray]:
        """For every link, the other transmitters on its resource (one row per (link, interferer)).

        Returns:
            ``rep`` [K]: index of the link; ``partner`` [K]: the co-channel transmitter
            (never the link's own transmitter nor its receiver).
        """
        return self._group_terms(tx, rx, active, self.resource)

    def _group_terms(
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

    def _mean_power_lookup(self, rx: IntArray, tx: IntArray) -> FloatArray:
        """Mean (unfaded) received power of arbitrary (rx, tx) pairs; 0 beyond the cut-off."""
        geo = self._period_geometry()
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

    def _decide_releases(self) -> None:
        """``sps.reservation_signalling=standard``: the keep/reselect draw of the UEs whose counter
        reaches 1 in the coming period (TS 36.321 5.14.1.1: with probability ``keep_probability``
        the UE keeps its resource); those that will reselect send SCIs without a reservation in that
        period (TS 36.213 14.1.1.6), so no one excludes their resource on that account."""
        last = self.counter == 1
        keep = self.rng.sps.random(self.n) < self.config.sps.keep_probability
        self._releasing = last & ~keep

    def _sensing_selection(
        self, vehicles: IntArray, last_sci_mw: FloatArray | None, exclude_own: bool, at_slot: int | None = None
    ) -> IntArray:
        """Resources chosen by sensing (TS 36.213 14.1.1.6) for ``vehicles`` [V]: the SCIs of the
        period just ended (``last_sci_mw`` [N, R], the strongest decoded SCI's power, mW) and the S-RSSI
        of the sensing window; with ``at_slot`` (``sps.reselection_timing=per_ue``: the vehicles' packet
        arrival, a slot of the current period) the sensing window is the 1000 ms before it instead
        (:meth:`_sensing_at`)."""
        cfg = self.config
        cand = sps.candidate_resources(self.generation_slot[vehicles], cfg.sps, self.rri)
        rssi: NDArray[np.float32]
        if at_slot is None:
            assert last_sci_mw is not None
            rsrp = self._sci_rsrp_dbm(last_sci_mw[vehicles[:, None], cand])
            rssi = _nan_mean_first_axis(self._rssi_ring[:, vehicles[:, None], cand])
        else:
            rsrp, rssi = self._sensing_at(vehicles, cand, at_slot)
        if exclude_own:
            rsrp = np.where(cand // self.n_sub == self.slot[vehicles][:, None], np.inf, rsrp)
        rssi = np.where(np.isnan(rssi), self.noise_mw, rssi)  # never measured
        choice = sps.select(rsrp, rssi, cfg.sps, self.rng.sps).choice
        return np.asarray(cand[np.arange(vehicles.size), choice])

    def _sensing_at(self, vehicles: IntArray, cand: IntArray, at_slot: int) -> tuple[FloatArray, NDArray[np.float32]]:
        """``sps.reselection_timing=per_ue``: what ``vehicles`` [V] sensed in the 1000 ms before their
        packet arrival at slot ``at_slot`` of the current period, for their candidates ``cand`` [V, M].

        A candidate in slot ``s`` is reserved by an SCI heard ``RRI`` subframes before it (TS 36.213
        14.1.1.6 step 6 with one RRI): for ``s < at_slot`` that SCI was heard earlier in this period,
        for ``s > at_slot`` in the previous one; for ``s == at_slot`` (subframe n + RRI, in the window
        when T2 = RRI) it would be sent at n itself, outside the sensing window: nothing excludes it.
        The S-RSSI of slot ``s`` averages the periods whose slot ``s`` lies in the window: this period
        and the 9 before it for ``s < at_slot``, the 10 before it otherwise (at RRI 100). A vehicle
        does not monitor its own transmission (NaN).

        Returns:
            ``rsrp`` [V, M] (dBm, ``-inf``: none heard) and the window-average S-RSSI [V, M] (mW, NaN:
            never measured).
        """
        n, r = self.n, self.n_res
        rows = vehicles[:, None]
        slot = cand // self.n_sub
        earlier = slot < at_slot  # heard in this period, before the arrival
        cur = self._sci_rsrp_dbm(self._period_sci_mw.reshape(n, r)[rows, cand])
        prev = self._sci_rsrp_dbm(self._prev_sci_mw.reshape(n, r)[rows, cand])
        # the arrival slot itself (subframe n + RRI, when T2 = RRI): the SCI reserving it would be sent at
        # n, outside the window [n - 1000, n - 1]; the one heard at n - RRI reserves n only
        rsrp = np.where(slot == at_slot, -np.inf, np.where(earlier, cur, prev))
        ring = self._rssi_ring[:, rows, cand]  # [P, V, M] (a copy: fancy indexing)
        now = (self._period_rssi.reshape(n, r)[rows, cand] + self.noise_mw).astype(np.float32)
        now[slot == self.slot[vehicles][:, None]] = np.nan  # its own transmission this period
        oldest = (self.subframe // self.rri) % self._sensing_periods  # holds the period RRI x P ago
        ring[oldest] = np.where(earlier, now, ring[oldest])
        return rsrp, _nan_mean_first_axis(ring)

    def _next_arrival_event(self, lo: int, hi: int) -> int:
        """``sps.reselection_timing=per_ue``: the end of the next chunk of slots ``[lo, hi)``: one past the
        first slot where a vehicle's packet arrives with its counter expired (or, with
        ``sps.reservation_signalling=standard``, about to reach 0), so that its reselection (release)
        takes effect from the next slot on; ``hi`` when there is none."""
        last = 1 if self.config.sps.reservation_signalling == "standard" else 0
        g = self.generation_slot
        event = (self.resource >= 0) & (self.counter <= last) & (g >= lo) & (g < hi)
        return int(g[event].min()) + 1 if np.any(event) else hi

    def _arrivals(self, lo: int, hi: int) -> None:
        """``sps.reselection_timing=per_ue``: the packet arrivals in slots ``[lo, hi)`` of the current
        period, after the transmissions of those slots (TS 36.321 5.14.1.1).

        A UE whose counter has expired (0) keeps its resource with ``sps.keep_probability`` (with
        ``reservation_signalling=standard``: as decided when the counter reached 0) or reselects by
        sensing the 1000 ms before its arrival (:meth:`_sensing_at`), and draws a new counter; then
        every arriving UE counts its coming transmission (counter - 1). :meth:`_next_arrival_event`
        ends the chunk at the slot of such arrivals, so a new resource after the arrival slot is used
        from this period on (the UE may send twice or not at all in the period of a reselection: one
        transmission per packet). With ``standard``, a UE whose counter reaches 0 draws keep/reselect
        now, and the SCI of its coming transmission reserves nothing if it will reselect.
        """
        cfg = self.config
        g = self.generation_slot
        arrived = np.flatnonzero((self.resource >= 0) & (g >= lo) & (g < hi))
        if not arrived.size:
            return
        expired = arrived[self.counter[arrived] <= 0]
        if expired.size:
            at = hi - 1
            assert np.all(g[expired] == at)  # the chunk ends at the slot of the arrivals with an expired counter
            if cfg.sps.reservation_signalling == "standard":
                keep = ~self._releasing[expired]
                self._releasing[expired] = False
            else:
                keep = self.rng.sps.random(expired.size) < cfg.sps.keep_probability
            reselect = expired[~keep]
            self.n_expiries += int(expired.size)
            self.n_expiries_per_vehicle[expired] += 1
            self.n_keeps += int(keep.sum())
            self.counter[expired] = sps.draw_counters(cfg.sps, self.rri, expired.size, self.rng.sps)
            if reselect.size:
                old_slot = self.slot[reselect]
                self.resource[reselect] = self._sensing_selection(
                    reselect, None, cfg.sps.exclude_unmonitored, at_slot=at
                )
                self._moved_from[reselect] = old_slot
                self.initial_resource[reselect] = False
                self.n_reselections += int(reselect.size)
        self.counter[arrived] -= 1
        if cfg.sps.reservation_signalling == "standard":
            last = arrived[self.counter[arrived] == 0]
            if last.size:
                keep_last = self.rng.sps.random(last.size) < cfg.sps.keep_probability
                self._releasing[last] = ~keep_last

    def _sent_this_period(self, veh: IntArray) -> tuple[IntArray, IntArray]:
        """``(vehicle, slot)`` of every transmission of ``veh`` in the period just ended. Period-end
        reselection: each vehicle's slot. ``per_ue``: a vehicle that reselected at its arrival ``g``
        sent on its old slot if that was ``<= g`` and on its new one if that is ``> g``."""
        slot = self.slot[veh]
        if not self._per_ue:
            return veh, slot
        old = self._moved_from[veh]
        g = self.generation_slot[veh]
        moved = old >= 0
        new_sent = ~moved | (slot > g)
        old_sent = moved & (old <= g)
        return np.concatenate([veh[new_sent], veh[old_sent]]), np.concatenate([slot[new_sent], old[old_sent]])

    def _select_joining(self, last_sci_mw: FloatArray) -> None:
        """``vehicles.population=open``: the vehicles that entered at the end of the previous period and
        listened through this one select a resource by sensing (their sensing window is this period:
        the SCIs that exclude resources are this period's, as for every other vehicle) and draw a
        reselection counter; they transmit from the next period on."""
        assert self.present is not None
        join = np.flatnonzero(self._joining & self.present)
        if not join.size:
            return
        cfg = self.config
        self.resource[join] = self._sensing_selection(join, last_sci_mw, exclude_own=False)  # it sent nothing
        self.counter[join] = sps.draw_counters(cfg.sps, self.rri, join.size, self.rng.sps)
        self._joining[join] = False
        self.n_reselections += int(join.size)

    def _admit(self) -> None:
        """``vehicles.population=open``: after a mobility step, free the slots of the vehicles that left
        (their links end: no transmission, no reception) and set up those that entered: no SPS history
        (an empty sensing window, no resource: they listen for one period, :meth:`_select_joining`),
        fresh shadowing towards everyone, a new generation slot, no offset."""
        st = self.state
        assert isinstance(st, mobility.TrackedState) and st.present is not None and st.entered is not None
        assert self.present is not None
        # a vehicle left when its slot empties or is handed to a new vehicle in the same step
        left = self.present & (~st.present | st.entered)
        gone = ~st.present
        self.n_departures += int(left.sum())
        self._vacated = np.flatnonzero(left)
        self.resource[gone] = -1
        self.counter[gone] = 0
        self._joining[gone] = False
        self._releasing[gone] = False
        self.initial_resource[gone] = False
        e = np.flatnonzero(st.entered)
        if e.size:
            self.n_entries += int(e.size)
            self.resource[e] = -1
            self.counter[e] = 0
            self._joining[e] = True
            self._releasing[e] = False
            self.initial_resource[e] = False
            self.n_expiries_per_vehicle[e] = 0
            self._rssi_ring[:, e, :] = np.nan
            self.shadowing.renew(e, st.odometer_m)
            if not self.config.traffic.synchronous:
                self.generation_slot[e] = self.rng.traffic.integers(0, self.rri, size=e.size)
            self.offsets_m[e] = 0.0
        self.present = st.present.copy()

    def _end_period(self) -> None:
        """Commit sensing, run the SPS counters and reselections (``sps.reselection_timing=period_end``;
        ``per_ue``: they ran at the arrivals), then move the vehicles."""
        cfg = self.config
        k = (self.subframe // self.rri - 1) % self._sensing_periods
        ring = self._period_rssi.reshape(self.n, self.n_res).astype(np.float32)
        ring += np.float32(self.noise_mw)
        veh = np.arange(self.n) if self.present is None else np.flatnonzero(self.resource >= 0)  # transmitters
        veh, sent_slot = self._sent_this_period(veh)
        own = veh * self.n_res
        own_res = (sent_slot * self.n_sub)[:, None] + np.arange(self.n_sub)[None, :]
        ring.reshape(-1)[(own[:, None] + own_res).reshape(-1)] = np.nan  # not monitored (half duplex)
        self._rssi_ring[k] = ring
        last_sci_mw = self._period_sci_mw.reshape(self.n, self.n_res)

        if self._per_ue:  # counters and reselections ran at the arrivals (_arrivals)
            self._prev_sci_mw = self._period_sci_mw
            self._moved_from.fill(-1)
            if self.present is not None:
                self._select_joining(last_sci_mw)
        else:
            self._counters_and_reselections(last_sci_mw)
        self._new_period_buffers()
        if self._source is not None:
            self.state = self._source.advance()
            if self.present is not None:
                self._admit()
        else:
            assert isinstance(self.state, mobility.VehicleState)
            self.state = mobility.advance(self.road, cfg.road, self.state, self.rri / 1000.0, self.rng.mobility)
        self._geometry = None

    def _counters_and_reselections(self, last_sci_mw: FloatArray) -> None:
        """``sps.reselection_timing=period_end``: every vehicle's counter and reselection at the end of
        the period, on the SCIs of the period just ended (``last_sci_mw`` [N, R], strongest SCI, mW)."""
        cfg = self.config
        if self.present is None:
            self.counter -= 1
            expired = self.counter <= 0
        else:  # only vehicles holding a resource count down
            holding = self.resource >= 0
            self.counter -= holding
            expired = (self.counter <= 0) & holding
        if cfg.sps.reservation_signalling == "standard":
            keep = ~self._releasing  # decided when the counter reached 1 (_decide_releases)
        else:
            keep = self.rng.sps.random(self.n) < cfg.sps.keep_probability
        reselect = np.flatnonzero(expired & ~keep)
        self.n_expiries += int(expired.sum())
        self.n_expiries_per_vehicle += expired
        self.n_keeps += int((expired & keep).sum())
        if np.any(expired):
            self.counter[expired] = sps.draw_counters(cfg.sps, self.rri, int(expired.sum()), self.rng.sps)
        if reselect.size:
            self.resource[reselect] = self._sensing_selection(reselect, last_sci_mw, cfg.sps.exclude_unmonitored)
            self.initial_resource[reselect] = False
            self.n_reselections += int(reselect.size)
        if self.present is not None:
            self._select_joining(last_sci_mw)
        if cfg.sps.reservation_signalling == "standard":
            self._decide_releases()
