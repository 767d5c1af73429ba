"""What a Mode 4 vehicle has measured on the road: observation version 4 (``cv2x/Traffic-v1``).

In traffic mode (:class:`~cv2x_marl.env.mobility_env.MobilityEnv` with ``mode="traffic"``) every env step is one
100-ms period of the simulator (:class:`cv2x_marl.sim.Simulator`): every vehicle sends one packet on its SPS
resource and each receiver decodes it or not (the period's sampled outcome, ``Simulator.last_links``: cause
``ok``). This module turns those periods into what a vehicle knows after its sensing window:

* **RSRP** of each neighbour's link, by :class:`cv2x_marl.env.measurement.Measurements` (the measurement of
  observation version 3, reused): each period, the packets i *actually decoded* (the simulator's outcome,
  passed as a success probability of 1 or 0, so the measurement's own decoding draw always agrees with it)
  give one sample each, the period's mean received power (``Simulator.last_geometry``: path loss and the
  simulator's shadowing at that period's positions, :func:`period_rx_dbm`) times Rayleigh fading, averaged
  over the window in mW, plus the TS 36.133 report error; stale (with its age) while j's packets are lost.
  The start window is v3's (``window`` periods at the start with the last warm-up period's powers and
  success probabilities).
* **SCI content** of each neighbour (:class:`SciReports`): the resource (subframe, subchannel) of the last
  SCI of j that i decoded, and whether that SCI announced a reselection (no reservation: TS 36.213 14.1.1.6
  with ``sps.reservation_signalling=standard``; never with ``always``). The reselection counter is not in SCI
  format 1 (TS 36.212 5.4.3.1.2), so no neighbour's counter is observed. A packet's SCI carries the resource
  its sender held at the start of that period (exact with ``sps.reselection_timing=period_end``, the paper
  presets'; with ``per_ue`` a sender that reselects mid-period is reported on the resource it held before).
  At reset the neighbours heard in the start window are reported on the resources they hold then.
* **Own SPS state**: the own resource of the next period, the reselection counter (TS 36.321 5.14.1.1: a UE
  knows its own) and whether its next SCI announces a reselection.

:func:`fill_observations` writes the per-neighbour and own entries of observation version 4
(:mod:`cv2x_marl.env.observation`, module docstring) for the v0 block's neighbours, nearest first.
Randomness: the episode's ``measurement`` stream (:func:`cv2x_marl.rng.env_stream`), drawn as
:class:`~cv2x_marl.env.measurement.Measurements` draws it; the SCI reports draw nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.env.measurement import Measurements, scaled_rsrp
from cv2x_marl.env.observation import FEATURES_V4, OWN_V4, ObservationLayout
from cv2x_marl.rng import env_stream
from cv2x_marl.sim.chunk import ChunkLinksOut
from cv2x_marl.sim.geometry import Geometry
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.sim.sps import counter_range

if TYPE_CHECKING:
    from cv2x_marl.config import ScenarioConfig
    from cv2x_marl.env.options import EnvOptions
    from cv2x_marl.sim import Simulator
    from cv2x_marl.sim.ground_truth import PairGeometry

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class TrafficEnvState(Protocol):
    """What this module reads of a traffic-mode env (:class:`~cv2x_marl.env.MobilityEnv` with observation 4).

    Attributes:
        layout: the observation layout (version 4).
        n: vehicles.
        config, options: the scenario and the env's options.
        sim: the simulator (``keep_period_geometry`` set).
        link_p: [N(tx), N(rx)] the period's success probabilities.
        resource: [N] every vehicle's next resource.
        traffic_measure: the measurements (:class:`TrafficMeasurements`).
        geometry: the pair geometry of the positions now (the v0 block's).
        own: the own state (:class:`~cv2x_marl.env.observation_models.OwnState`: ``u_now``, ``u_prev``, [N]
            utility per target receiver now and the step before).
    """

    layout: ObservationLayout
    n: int
    config: ScenarioConfig
    options: EnvOptions
    sim: Simulator
    link_p: FloatArray
    resource: IntArray
    traffic_measure: TrafficMeasurements
    geometry: PairGeometry | None
    own: Any


def period_rx_dbm(geometry: Geometry, n: int) -> FloatArray:
    """[N(tx), N(rx)] mean received power of a period (dBm): the simulator's ``mean_rx_dbm_half`` of each pair
    in range for both directions (EIRP - path loss - shadowing, no fading); ``-inf`` for the pairs out of
    ``link.max_range_m`` and on the diagonal.

    Args:
        geometry: the period's :class:`~cv2x_marl.sim.geometry.Geometry` (``Simulator.last_geometry``).
        n: vehicles.
    """
    h = geometry.rx.shape[0] // 2  # the first half holds the pairs (i, j), i < j, as (rx, tx)
    a, b = geometry.rx[:h], geometry.tx[:h]
    out = np.full((n, n), -np.inf)
    out[a, b] = geometry.mean_rx_dbm_half
    out[b, a] = geometry.mean_rx_dbm_half
    return out


def decoded_links(links: ChunkLinksOut, n: int) -> NDArray[np.bool_]:
    """[N(tx), N(rx)] whether rx decoded tx's packet in the period ``links`` describes (``Simulator.last_links``:
    cause ``ok``; half duplex, sensitivity, propagation and collision losses are not decoded)."""
    tx, rx, _, cause = links
    ok = cause == CAUSE_CODE["ok"]
    out = np.zeros((n, n), dtype=bool)
    out[tx[ok], rx[ok]] = True
    return out


@dataclass
class SciReports:
    """What each vehicle read in the last SCI it decoded from each other vehicle (module docstring).

    Attributes:
        resource: [N(tx), N(rx)] ``slot * n_subchannels + subchannel`` of tx's last SCI decoded at rx (-1: none).
        release: [N(tx), N(rx)] whether that SCI announced a reselection (carried no reservation).
        sent_resource: [N] the resource each vehicle's SCIs of the coming period carry (its resource now).
        sent_release: [N] whether they announce a reselection (``SpsScheduler.releasing`` now).
    """

    resource: IntArray
    release: NDArray[np.bool_]
    sent_resource: IntArray
    sent_release: NDArray[np.bool_]

    @classmethod
    def start(cls, heard: NDArray[np.bool_], resource: IntArray, releasing: NDArray[np.bool_]) -> SciReports:
        """The reports after the start window: the pairs ``heard`` [N, N] read the senders' ``resource`` [N] and
        ``releasing`` [N] now."""
        res = np.asarray(resource, dtype=np.int64)
        rel = np.asarray(releasing, dtype=bool)
        return cls(np.where(heard, res[:, None], -1), heard & rel[:, None], res.copy(), rel.copy())

    def update(self, decoded: NDArray[np.bool_], resource: IntArray, releasing: NDArray[np.bool_]) -> None:
        """One period: the pairs ``decoded`` [N, N] read the SCIs sent in it; then ``resource`` [N] and
        ``releasing`` [N] (the SPS state after the period's end) are what the next period's SCIs carry."""
        self.resource = np.where(decoded, self.sent_resource[:, None], self.resource)
        self.release = np.where(decoded, self.sent_release[:, None], self.release)
        self.sent_resource = np.asarray(resource, dtype=np.int64).copy()
        self.sent_release = np.asarray(releasing, dtype=bool).copy()


@dataclass
class TrafficMeasurements:
    """A traffic-mode env's measurements: RSRP reports (:class:`Measurements`) and SCI reports (:class:`SciReports`)."""

    rsrp: Measurements
    sci: SciReports

    @classmethod
    def start(
        cls, sim: Simulator, p: FloatArray, window: int, error_db: float, rng: np.random.Generator
    ) -> TrafficMeasurements:
        """After the simulator's reset: the start window (:meth:`Measurements.start`) with the last warm-up
        period's powers and success probabilities ``p`` [N(tx), N(rx)] (the env's ``link_p``).

        Args:
            sim: the simulator, reset with ``keep_period_geometry`` set.
            p: [N(tx), N(rx)] success probabilities of the last warm-up period.
            window: the sensing window (periods).
            error_db: the report error's standard deviation (dB).
            rng: the episode's ``measurement`` stream.
        """
        if sim.last_geometry is None:
            raise RuntimeError("the simulator kept no period geometry: set keep_period_geometry before its reset")
        rx = period_rx_dbm(sim.last_geometry, sim.n)
        rsrp = Measurements.start(rx, p, window, error_db, rng)
        return cls(rsrp, SciReports.start(np.isfinite(rsrp.rsrp_dbm), sim.resource, sim.scheduler.releasing))

    def update(self, sim: Simulator) -> None:
        """The period the simulator has just run: its decoded packets' samples and SCIs."""
        assert sim.last_geometry is not None and sim.last_links is not None
        decoded = decoded_links(sim.last_links, sim.n)
        self.rsrp.update(period_rx_dbm(sim.last_geometry, sim.n), decoded.astype(np.float64))
        self.sci.update(decoded, sim.resource, sim.scheduler.releasing)


def start_measurements(env: TrafficEnvState, episode_seed: int) -> TrafficMeasurements:
    """:meth:`TrafficMeasurements.start` for ``env`` just reset on ``episode_seed`` (its options' sensing window and
    report error, its ``link_p``, the episode's ``measurement`` stream)."""
    o = env.options
    return TrafficMeasurements.start(
        env.sim, env.link_p, o.sensing_window, o.rsrp_error_db, env_stream(episode_seed, "measurement")
    )


@njit(cache=True)
def _fill_kernel(
    out: NDArray[np.float32],
    dist2_m2: FloatArray,
    rsrp_scaled: FloatArray,
    age: IntArray,
    heard: NDArray[np.bool_],
    sci_resource: IntArray,
    sci_release: NDArray[np.bool_],
    resource: IntArray,
    counter_share: FloatArray,
    releasing: NDArray[np.bool_],
    u_now: FloatArray,
    u_prev: FloatArray,
    rows: IntArray,
    k: int,
    offset: int,
    own_offset: int,
    window: int,
    n_sub: int,
    rri: int,
    obs_clip: float,
) -> None:
    """:func:`fill_observations`' entries, computed in float64, clipped, stored as float32; the neighbours in the
    v0 block's order (a stable sort of the distances, the agent itself last: ``observation_kernel``'s)."""
    n = dist2_m2.shape[0]
    dist_i = np.empty(n)
    vals = np.empty(FEATURES_V4)
    for r in range(rows.shape[0]):
        i = rows[r]
        for j in range(n):
            dist_i[j] = math.sqrt(dist2_m2[i, j])
        dist_i[i] = np.inf
        order = np.argsort(dist_i, kind="mergesort")
        own = resource[i]
        for kk in range(k):
            j = order[kk]
            res = sci_resource[j, i]
            known = res >= 0
            vals[0] = rsrp_scaled[j, i]
            vals[1] = age[j, i] / window
            vals[2] = 1.0 if heard[j, i] else 0.0
            vals[3] = (res // n_sub) / rri if known else 0.0
            vals[4] = (res % n_sub) / n_sub if known else 0.0
            vals[5] = 1.0 if known and sci_release[j, i] else 0.0
            vals[6] = 1.0 if known and res // n_sub == own // n_sub else 0.0
            vals[7] = 1.0 if known and res == own else 0.0
            base = offset + kk * FEATURES_V4
            for f in range(FEATURES_V4):
                out[r, base + f] = min(max(vals[f], -obs_clip), obs_clip)
        mine = (
            (own // n_sub) / rri,
            (own % n_sub) / n_sub,
            counter_share[i],
            1.0 if releasing[i] else 0.0,
            u_now[i],
            10.0 * (u_now[i] - u_prev[i]),
        )
        for f in range(OWN_V4):
            out[r, own_offset + f] = min(max(mine[f], -obs_clip), obs_clip)


def fill_observations(env: TrafficEnvState, obs: NDArray[np.float32], rows: IntArray | None = None) -> None:
    """Write observation version 4's measured and own entries of agents ``rows`` (all: None) into ``obs``
    [A, size] in place, one compiled pass (the v0 block and the driving entries are written by the env;
    ``tests/env/test_traffic_measured.py`` checks every entry against an independent numpy replay).

    Args:
        env: a traffic-mode env with observation version 4, after its links and measurements of this step.
        obs: [A, env.layout.size] the agents' observations.
        rows: [A] the agents of ``obs``'s rows (None: every vehicle, in index order).
    """
    layout: ObservationLayout = env.layout
    if layout.version not in (4, 5):
        raise ValueError("fill_observations writes observation version 4 (and version 5's blocks of version 4)")
    assert env.geometry is not None and env.own is not None
    rows = np.arange(env.n, dtype=np.int64) if rows is None else np.ascontiguousarray(rows, dtype=np.int64)
    cfg, m, sci = env.config, env.traffic_measure.rsrp, env.traffic_measure.sci
    sched = env.sim.scheduler
    _fill_kernel(
        obs, env.geometry.dist2_m2, scaled_rsrp(m.rsrp_dbm), m.age, np.isfinite(m.rsrp_dbm), sci.resource,
        sci.release, np.ascontiguousarray(env.resource, dtype=np.int64),
        sched.counter / counter_range(cfg.sps, cfg.traffic.rri_ms)[1], np.ascontiguousarray(sched.releasing),
        np.ascontiguousarray(env.own.u_now, dtype=np.float64), np.ascontiguousarray(env.own.u_prev, dtype=np.float64),
        rows, layout.n_neighbours, layout.v0_size, layout.own_v1_offset, m.window, cfg.sps.n_subchannels,
        cfg.traffic.rri_ms, layout.obs_clip,
    )  # fmt: skip
