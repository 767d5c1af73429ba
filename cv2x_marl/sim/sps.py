"""Sensing-based semi-persistent scheduling, vectorised over the vehicles that reselect.

Resources are indexed within one reservation period: ``r = slot * n_subchannels + subchannel``
with ``slot`` in ``[0, RRI)``. A vehicle whose packets are generated at slot ``g`` selects from
the window ``[g + T1, g + T2]`` (mod RRI), ``M = (T2 - T1 + 1) * n_subchannels`` candidates
(TS 36.213 14.1.1.6 with one subchannel per packet):

1. exclude a candidate whose subframe the UE did not monitor (its own transmission, step 5);
2. exclude a candidate reserved by a received SCI whose PSSCH-RSRP exceeds the threshold
   (step 6); while fewer than ``ceil(0.2 M)`` remain, raise the threshold by 3 dB (step 7);
3. paper rule: the ``k = 3`` lowest-RSSI survivors, one of them uniformly (Sec. 3);
   3GPP rule: the lowest-RSSI survivors making ``ceil(0.2 M)``, one uniformly (step 8);
   uniform (the analytical model's assumption, ``validate --assumptions model``): any survivor, uniformly.

``sps.threshold_increase=model_cbr`` replaces step 7 by the analytical model's weighting of its Step 2
and Step 3 (Gonzalez-Martin et al. 2019 eqs. 21-23): with probability ``alpha(CBR)`` the UE keeps the
initial threshold however few candidates survive (:func:`model_step2_alone`).

The 3 dB loop has a closed form: with ``v_q`` the q-th smallest RSRP of the candidates
(``q = ceil(0.2 M)``), the final threshold is ``Th + 3 max(0, ceil((v_q - Th) / 3))``.

The reselection counter (TS 36.321 5.14.1.1) is drawn uniformly in ``[5, 15]`` for RRI >= 100 ms
and ``[5 * 100 / RRI, 15 * 100 / RRI]`` for shorter RRIs; it falls by one per transmission and,
when it expires, the UE keeps its resource with probability ``keep_probability``.

:class:`SpsScheduler` holds every vehicle's SPS state (resources, counters, releases, the sensing
window) and runs the procedures on it (selection with sensing, counters and reselections at the
period end or at each packet arrival, releases, an open population's entries); the simulator drives
it once per chunk and period (:class:`cv2x_marl.sim.simulator.Simulator`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ScenarioConfig, SpsConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def counter_range(cfg: SpsConfig, rri_ms: int) -> tuple[int, int]:
    """Inclusive range of the reselection counter for this RRI (TS 36.321 5.14.1.1)."""
    scale = max(1.0, 100.0 / rri_ms)
    return round(cfg.counter_min * scale), round(cfg.counter_max * scale)


def draw_counters(cfg: SpsConfig, rri_ms: int, n: int, rng: np.random.Generator) -> IntArray:
    """``n`` reselection counters, uniform on :func:`counter_range`."""
    lo, hi = counter_range(cfg, rri_ms)
    return rng.integers(lo, hi + 1, size=n)


def candidate_resources(generation_slot: IntArray, cfg: SpsConfig, rri_ms: int) -> IntArray:
    """[V, M] candidate resource indices of the selection window of each of V vehicles."""
    offsets = cfg.t1_subframes + np.arange(cfg.selection_window_subframes)
    slots = (generation_slot[:, None] + offsets[None, :]) % rri_ms  # [V, W]
    sub = np.arange(cfg.n_subchannels)
    return (slots[:, :, None] * cfg.n_subchannels + sub[None, None, :]).reshape(len(generation_slot), -1)


@dataclass(frozen=True)
class Selection:
    """Outcome of one batch of resource selections (arrays over the V selecting vehicles)."""

    choice: IntArray  # [V] index into the candidate list
    threshold_dbm: FloatArray  # [V] final RSRP threshold after the 3 dB loop
    n_kept: IntArray  # [V] candidates surviving exclusion
    #: [V, M] candidate indices in the rule's ranking: the survivors by ascending S-RSSI (``uniform``: in index
    #: order), then the excluded ones
    order: IntArray | None = None
    #: [V] how many of the first entries of ``order`` the rule draws from (step 8's list: ``choice`` is one of them)
    n_pick: IntArray | None = None


def select(
    rsrp_dbm: FloatArray,
    rssi_mw: NDArray[np.floating],
    cfg: SpsConfig,
    rng: np.random.Generator,
) -> Selection:
    """Choose one candidate per row.

    Args:
        rsrp_dbm: [V, M] RSRP of the SCI reserving each candidate (``-inf``: none received,
            ``+inf``: subframe not monitored, always excluded).
        rssi_mw: [V, M] sensing-window average S-RSSI of each candidate, mW.
        cfg: SPS configuration (threshold, step, minimum fraction, rule).
        rng: the SPS stream.

    Returns:
        The chosen candidate of every row, the final threshold and the number of survivors.
    """
    v, m = rsrp_dbm.shape
    q = min(m, math.ceil(cfg.min_candidate_fraction * m - 1e-9))
    th0 = cfg.rsrp_threshold_dbm
    vq = np.partition(rsrp_dbm, q - 1, axis=1)[:, q - 1]
    if np.any(np.isposinf(vq)):
        raise ValueError("more than 80 % of the candidates are unmonitored: the 3 dB loop cannot end")
    with np.errstate(invalid="ignore"):
        steps = np.where(vq > th0, np.ceil((vq - th0) / cfg.threshold_step_db - 1e-12), 0.0)
    threshold = th0 + cfg.threshold_step_db * steps
    if cfg.threshold_increase == "model_cbr":  # Gonzalez-Martin et al. eqs. 21-23: Step 2 alone w.p. alpha
        step2 = model_step2_alone(rsrp_dbm, th0, np.asarray(rng.random(v), dtype=np.float64))
        threshold = np.where(step2, th0, threshold)
    kept = rsrp_dbm <= threshold[:, None]
    n_kept = kept.sum(axis=1)
    if cfg.selection == "uniform":  # the analytical model: uniform among every survivor, no S-RSSI ranking
        k = m
        score = np.where(kept, 0.0, np.inf)
    else:
        k = cfg.paper_best_k if cfg.selection == "paper" else q
        score = np.where(kept, rssi_mw, np.inf)
    order = np.argsort(score, axis=1, kind="stable")
    n_pick = np.minimum(k, n_kept)
    pick = np.floor(rng.random(v) * n_pick).astype(np.int64)
    choice = order[np.arange(v), pick]
    return Selection(choice, threshold, n_kept, order, n_pick)


def model_alpha(cbr: NDArray[np.floating]) -> FloatArray:
    """The analytical model's weight of Step 2 (Gonzalez-Martin et al. 2019 eq. 22), elementwise: 0 below a
    CBR of 0.2, ``2 CBR - 0.4`` up to 0.7, then 1."""
    c = np.asarray(cbr, dtype=np.float64)
    return np.asarray(np.where(c < 0.2, 0.0, np.where(c <= 0.7, 2.0 * c - 0.4, 1.0)))


def model_step2_alone(rsrp_dbm: FloatArray, threshold_dbm: float, u: FloatArray) -> NDArray[np.bool_]:
    """``sps.threshold_increase=model_cbr``: which of V selecting UEs use the analytical model's Step 2 alone
    (Gonzalez-Martin et al. 2019 eqs. 21-23): those with ``u < alpha(CBR)`` (eq. 22) that have a candidate
    left at the initial threshold, CBR being the UE's share of excluded candidates there (``N_e / N``,
    eq. 34; unmonitored ones count as excluded).

    Args:
        rsrp_dbm: [V, M] RSRP of the SCI reserving each candidate (``-inf``: none, ``+inf``: unmonitored).
        threshold_dbm: the initial RSRP threshold (per resource element).
        u: [V] uniforms on [0, 1).

    Returns:
        [V] True where the UE keeps the initial threshold.
    """
    n_free = np.sum(rsrp_dbm <= threshold_dbm, axis=1)
    cbr = 1.0 - n_free / rsrp_dbm.shape[1]
    return np.asarray((u < model_alpha(cbr)) & (n_free > 0))


@dataclass(frozen=True)
class SelectionRecord:
    """One batch of sensing-based selections as the scheduler ran them (:attr:`SpsScheduler.record_selections`):
    what each selecting vehicle sensed and the standard's list it drew from (TS 36.213 14.1.1.6 steps 5-8).

    Attributes:
        vehicles: [V] the selecting vehicles.
        candidates: [V, M] their candidate resources (``slot * n_sub + subchannel``, :func:`candidate_resources`).
        rsrp_dbm: [V, M] RSRP of the SCI reserving each candidate (``-inf``: none decoded, ``+inf``: not monitored).
        rssi_mw: [V, M] the sensing window's average S-RSSI of each candidate (mW; noise where never measured).
        order: [V, M] candidate indices ranked by the rule (:attr:`Selection.order`): the survivors first.
        n_kept: [V] the survivors of the exclusion (steps 5-7): the first ``n_kept`` entries of ``order``.
        n_list: [V] the standard's list: the first ``n_list`` entries of ``order`` (step 8).
        chosen: [V] the resource the standard's draw chose (the scheduler's ``sps`` stream).
    """

    vehicles: IntArray
    candidates: IntArray
    rsrp_dbm: FloatArray
    rssi_mw: FloatArray
    order: IntArray
    n_kept: IntArray
    n_list: IntArray
    chosen: IntArray


def nan_mean_first_axis(x: NDArray[np.float32]) -> NDArray[np.float32]:
    """``np.nanmean(x, axis=0)`` (same float32 result; NaN where all are NaN, without a warning)."""
    valid = ~np.isnan(x)
    total = np.where(valid, x, np.float32(0.0)).sum(axis=0)
    with np.errstate(invalid="ignore"):
        return np.asarray(total / valid.sum(axis=0), dtype=np.float32)


class SpsScheduler:
    """The SPS state of every vehicle slot and its procedures (TS 36.213 14.1.1.6, TS 36.321 5.14.1.1).

    The simulator drives it (:class:`cv2x_marl.sim.simulator.Simulator`):

    - :meth:`reset` once per episode: generation slots, random initial resources, counters;
    - per chunk of a period: the chunk's transmissions read :attr:`resource` / :attr:`slot` and
      :attr:`releasing` and add to the period's sensing sums :attr:`period_rssi_mw` and
      :attr:`period_sci_mw`; with ``sps.reselection_timing=per_ue`` :meth:`next_arrival_event` ends the
      chunk and :meth:`arrivals` runs after its transmissions;
    - :meth:`end_period` at each period end (sensing committed to the window, counters and reselections,
      joining vehicles' first selection), before the vehicles move;
    - :meth:`admit` after a mobility step of ``vehicles.population=open``.

    Every draw comes from the ``sps`` stream given to :meth:`reset` (the generation slots from the
    ``traffic`` stream), in the order the procedures run.

    Attributes:
        resource: [N] reserved resource per slot (``slot * n_sub + subchannel``; -1: none).
        counter: [N] reselection counters.
        generation_slot: [N] slot of each vehicle's packet generation, ``[0, RRI)``.
        initial_resource: [N] still on the random resource of :meth:`reset`.
        releasing: [N] ``reservation_signalling=standard``: will reselect, its SCIs reserve nothing.
        joining: [N] ``population=open``: entered and listening for a period before selecting.
        rssi_ring: [P, N, R] S-RSSI of the sensing window's periods (float32 mW, NaN: not monitored).
        period_rssi_mw: [N * R] the current period's S-RSSI sums, mW (noise not included).
        period_sci_mw: [N * R] the current period's strongest decoded SCI (PSSCH power, mW; 0: none).
        prev_sci_mw: [N * R] ``per_ue``: ``period_sci_mw`` of the previous period.
        moved_from: [N] ``per_ue``: the slot a vehicle left by a reselection this period (-1: none).
        n_reselections, n_expiries, n_keeps: counts since :meth:`reset`; ``n_expiries_per_vehicle`` [N].
    """

    def __init__(self, config: ScenarioConfig, n: int, noise_mw: float) -> None:
        self.cfg = config.sps
        self.n = n
        self.rri = config.traffic.rri_ms
        self.n_sub = config.sps.n_subchannels
        self.n_res = self.rri * self.n_sub
        self.noise_mw = noise_mw
        self.synchronous = config.traffic.synchronous
        self.rsrp_offset_db = 10.0 * np.log10(12 * config.sps.subchannel_rbs)
        #: periods of the sensing window (1000 ms)
        self.sensing_periods = max(1, config.sps.sensing_window_ms // self.rri)
        #: sps.reselection_timing=per_ue: counters and reselections at each UE's packet arrival
        self.per_ue = config.sps.reselection_timing == "per_ue"
        self.standard = config.sps.reservation_signalling == "standard"
        #: keep each selection's sensing and list in :attr:`selections` (the env's ``cv2x/Resource-v0`` reads them)
        self.record_selections = False
        #: with :attr:`record_selections`: the selections since the last period end began (:class:`SelectionRecord`)
        self.selections: list[SelectionRecord] = []

    def reset(
        self, rng: np.random.Generator, traffic_rng: np.random.Generator, present: NDArray[np.bool_] | None
    ) -> None:
        """Generation slots (``traffic_rng``), a random resource of the selection window and a counter per
        vehicle (``rng``, the ``sps`` stream, kept for every later draw), empty sensing.

        Args:
            rng: the ``sps`` stream.
            traffic_rng: the ``traffic`` stream (generation slots, unless ``traffic.synchronous``).
            present: [N] occupied slots (``population=open``; None: all): empty ones hold no resource.
        """
        cfg, n = self.cfg, self.n
        self.rng = rng
        if self.synchronous:
            self.generation_slot = np.zeros(n, dtype=np.int64)
        else:
            self.generation_slot = traffic_rng.integers(0, self.rri, size=n)
        cand = candidate_resources(self.generation_slot, cfg, self.rri)
        pick = rng.integers(0, cand.shape[1], size=n)
        self.resource = cand[np.arange(n), pick]
        self.counter = draw_counters(cfg, self.rri, n, rng)
        self.initial_resource = np.ones(n, dtype=bool)  # still on the random resource of reset
        self.n_expiries_per_vehicle = np.zeros(n, dtype=np.int64)
        self.releasing = np.zeros(n, dtype=bool)
        self.joining = np.zeros(n, dtype=bool)
        if present is not None:  # empty slots: no resource (slot -1: never active), no counter
            self.resource[~present] = -1
            self.counter[~present] = 0
            self.initial_resource[~present] = False
        if self.standard and not self.per_ue:  # per_ue: at the arrivals
            self._decide_releases()
        self.rssi_ring = np.full((self.sensing_periods, n, self.n_res), np.nan, dtype=np.float32)
        self._new_period_buffers()
        if self.per_ue:
            self.prev_sci_mw = np.zeros(n * self.n_res)
            self.moved_from = np.full(n, -1, dtype=np.int64)
        self.n_reselections = 0
        self.n_expiries = 0
        self.n_keeps = 0
        self.selections = []

    def _new_period_buffers(self) -> None:
        self.period_rssi_mw = np.zeros(self.n * self.n_res)
        #: kept linear so that only the rows the sensing reads are taken to dBm (:meth:`sci_rsrp_dbm`)
        self.period_sci_mw = np.zeros(self.n * self.n_res)

    @property
    def slot(self) -> IntArray:
        """[N] slot of each reserved resource."""
        return self.resource // self.n_sub

    @property
    def subchannel(self) -> IntArray:
        """[N] subchannel of each reserved resource."""
        return self.resource % self.n_sub

    def sci_rsrp_dbm(self, sci_mw: FloatArray) -> FloatArray:
        """The SCI RSRP (dBm per resource element, ``-inf``: no SCI) of strongest-SCI powers (mW, any shape):
        ``10 log10(P) - 10 log10(12 x RBs)``, the maximum over the SCIs' own RSRP (the logarithm is monotone)."""
        with np.errstate(divide="ignore"):
            return np.asarray(10.0 * np.log10(sci_mw) - self.rsrp_offset_db)

    def state(self, subframe: int, present: NDArray[np.bool_] | None) -> dict[str, object]:
        """The SPS state now, JSON-ready (:meth:`cv2x_marl.sim.simulator.Simulator.sps_state`)."""
        on = slice(None) if present is None else self.resource >= 0  # vehicles holding a resource
        values, counts = np.unique(self.counter[on], return_counts=True)
        out: dict[str, object] = {
            "subframe": int(subframe),
            "share_initial_resource": float(np.mean(self.initial_resource[on])),
            "share_never_expired": float(np.mean(self.n_expiries_per_vehicle[on] == 0)),
            "counter_mean": float(np.mean(self.counter[on])),
            "counter_histogram": {str(int(v)): int(c) for v, c in zip(values, counts, strict=True)},
        }
        if present is not None:  # population=open: the shares are over the vehicles holding a resource
            out["n_present"] = int(present.sum())
            out["n_listening"] = int((self.joining & present).sum())
        return out

    # ------------------------------------------------------------- procedures
    def _decide_releases(self) -> None:
        """``sps.reservation_signalling=standard``: the keep/reselect draw of the UEs whose counter
        reaches 1 in the coming period (TS 36.321 5.14.1.1: with probability ``keep_probability``
        the UE keeps its resource); those that will reselect send SCIs without a reservation in that
        period (TS 36.213 14.1.1.6), so no one excludes their resource on that account."""
        last = self.counter == 1
        keep = self.rng.random(self.n) < self.cfg.keep_probability
        self.releasing = last & ~keep

    def _sensing_selection(
        self,
        vehicles: IntArray,
        last_sci_mw: FloatArray | None,
        exclude_own: bool,
        at_slot: int | None = None,
        subframe: int = 0,
    ) -> IntArray:
        """Resources chosen by sensing (TS 36.213 14.1.1.6) for ``vehicles`` [V]: the SCIs of the
        period just ended (``last_sci_mw`` [N, R], the strongest decoded SCI's power, mW) and the S-RSSI
        of the sensing window; with ``at_slot`` (``sps.reselection_timing=per_ue``: the vehicles' packet
        arrival, a slot of the period starting at subframe ``subframe - subframe % RRI``) the sensing
        window is the 1000 ms before it instead (:meth:`_sensing_at`)."""
        cand = candidate_resources(self.generation_slot[vehicles], self.cfg, self.rri)
        rssi: NDArray[np.float32]
        if at_slot is None:
            assert last_sci_mw is not None
            rsrp = self.sci_rsrp_dbm(last_sci_mw[vehicles[:, None], cand])
            rssi = nan_mean_first_axis(self.rssi_ring[:, vehicles[:, None], cand])
        else:
            rsrp, rssi = self._sensing_at(vehicles, cand, at_slot, subframe)
        if exclude_own:
            rsrp = np.where(cand // self.n_sub == self.slot[vehicles][:, None], np.inf, rsrp)
        rssi = np.where(np.isnan(rssi), self.noise_mw, rssi)  # never measured
        sel = select(rsrp, rssi, self.cfg, self.rng)
        chosen = np.asarray(cand[np.arange(vehicles.size), sel.choice])
        if self.record_selections:
            assert sel.order is not None and sel.n_pick is not None
            record = SelectionRecord(
                vehicles.copy(), cand, rsrp, np.asarray(rssi, np.float64), sel.order, sel.n_kept, sel.n_pick, chosen
            )
            self.selections.append(record)
        return chosen

    def _sensing_at(
        self, vehicles: IntArray, cand: IntArray, at_slot: int, subframe: int
    ) -> tuple[FloatArray, NDArray[np.float32]]:
        """``sps.reselection_timing=per_ue``: what ``vehicles`` [V] sensed in the 1000 ms before their
        packet arrival at slot ``at_slot`` of the current period (``subframe`` lies in it), for their
        candidates ``cand`` [V, M].

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
        cur = self.sci_rsrp_dbm(self.period_sci_mw.reshape(n, r)[rows, cand])
        prev = self.sci_rsrp_dbm(self.prev_sci_mw.reshape(n, r)[rows, cand])
        # the arrival slot itself (subframe n + RRI, when T2 = RRI): the SCI reserving it would be sent at
        # n, outside the window [n - 1000, n - 1]; the one heard at n - RRI reserves n only
        rsrp = np.where(slot == at_slot, -np.inf, np.where(earlier, cur, prev))
        ring = self.rssi_ring[:, rows, cand]  # [P, V, M] (a copy: fancy indexing)
        now = (self.period_rssi_mw.reshape(n, r)[rows, cand] + self.noise_mw).astype(np.float32)
        now[slot == self.slot[vehicles][:, None]] = np.nan  # its own transmission this period
        oldest = (subframe // self.rri) % self.sensing_periods  # holds the period RRI x P ago
        ring[oldest] = np.where(earlier, now, ring[oldest])
        return rsrp, nan_mean_first_axis(ring)

    def next_arrival_event(self, lo: int, hi: int) -> int:
        """``sps.reselection_timing=per_ue``: the end of the next chunk of slots ``[lo, hi)``: one past the
        first slot where a vehicle's packet arrives with its counter expired (or, with
        ``sps.reservation_signalling=standard``, about to reach 0), so that its reselection (release)
        takes effect from the next slot on; ``hi`` when there is none."""
        last = 1 if self.standard else 0
        g = self.generation_slot
        event = (self.resource >= 0) & (self.counter <= last) & (g >= lo) & (g < hi)
        return int(g[event].min()) + 1 if np.any(event) else hi

    def arrivals(self, lo: int, hi: int, subframe: int) -> None:
        """``sps.reselection_timing=per_ue``: the packet arrivals in slots ``[lo, hi)`` of the current
        period (the chunk that started at ``subframe``), after the transmissions of those slots
        (TS 36.321 5.14.1.1).

        A UE whose counter has expired (0) keeps its resource with ``sps.keep_probability`` (with
        ``reservation_signalling=standard``: as decided when the counter reached 0) or reselects by
        sensing the 1000 ms before its arrival (:meth:`_sensing_at`), and draws a new counter; then
        every arriving UE counts its coming transmission (counter - 1). :meth:`next_arrival_event`
        ends the chunk at the slot of such arrivals, so a new resource after the arrival slot is used
        from this period on (the UE may send twice or not at all in the period of a reselection: one
        transmission per packet). With ``standard``, a UE whose counter reaches 0 draws keep/reselect
        now, and the SCI of its coming transmission reserves nothing if it will reselect.
        """
        cfg = self.cfg
        g = self.generation_slot
        arrived = np.flatnonzero((self.resource >= 0) & (g >= lo) & (g < hi))
        if not arrived.size:
            return
        expired = arrived[self.counter[arrived] <= 0]
        if expired.size:
            at = hi - 1
            assert np.all(g[expired] == at)  # the chunk ends at the slot of the arrivals with an expired counter
            if self.standard:
                keep = ~self.releasing[expired]
                self.releasing[expired] = False
            else:
                keep = self.rng.random(expired.size) < cfg.keep_probability
            reselect = expired[~keep]
            self.n_expiries += int(expired.size)
            self.n_expiries_per_vehicle[expired] += 1
            self.n_keeps += int(keep.sum())
            self.counter[expired] = draw_counters(cfg, self.rri, expired.size, self.rng)
            if reselect.size:
                old_slot = self.slot[reselect]
                self.resource[reselect] = self._sensing_selection(
                    reselect, None, cfg.exclude_unmonitored, at_slot=at, subframe=subframe
                )
                self.moved_from[reselect] = old_slot
                self.initial_resource[reselect] = False
                self.n_reselections += int(reselect.size)
        self.counter[arrived] -= 1
        if self.standard:
            last = arrived[self.counter[arrived] == 0]
            if last.size:
                keep_last = self.rng.random(last.size) < cfg.keep_probability
                self.releasing[last] = ~keep_last

    def _sent_this_period(self, veh: IntArray) -> tuple[IntArray, IntArray]:
        """``(vehicle, slot)`` of every transmission of ``veh`` in the period just ended. Period-end
        reselection: each vehicle's slot. ``per_ue``: a vehicle that reselected at its arrival ``g``
        sent on its old slot if that was ``<= g`` and on its new one if that is ``> g``."""
        slot = self.slot[veh]
        if not self.per_ue:
            return veh, slot
        old = self.moved_from[veh]
        g = self.generation_slot[veh]
        moved = old >= 0
        new_sent = ~moved | (slot > g)
        old_sent = moved & (old <= g)
        return np.concatenate([veh[new_sent], veh[old_sent]]), np.concatenate([slot[new_sent], old[old_sent]])

    def _select_joining(self, last_sci_mw: FloatArray, present: NDArray[np.bool_]) -> None:
        """``vehicles.population=open``: the vehicles that entered at the end of the previous period and
        listened through this one select a resource by sensing (their sensing window is this period:
        the SCIs that exclude resources are this period's, as for every other vehicle) and draw a
        reselection counter; they transmit from the next period on."""
        join = np.flatnonzero(self.joining & present)
        if not join.size:
            return
        self.resource[join] = self._sensing_selection(join, last_sci_mw, exclude_own=False)  # it sent nothing
        self.counter[join] = draw_counters(self.cfg, self.rri, join.size, self.rng)
        self.joining[join] = False
        self.n_reselections += int(join.size)

    def end_period(self, subframe: int, present: NDArray[np.bool_] | None) -> None:
        """At the end of the period that ends at ``subframe``: commit its S-RSSI to the sensing window
        (each vehicle's own transmissions unmonitored: half duplex), run the counters and reselections
        (``sps.reselection_timing=period_end``; ``per_ue``: they ran at the arrivals), let the joining
        vehicles of an open population (``present`` [N]; None: closed) select, and start the next
        period's sensing sums."""
        self.selections = []
        k = (subframe // self.rri - 1) % self.sensing_periods
        ring = self.period_rssi_mw.reshape(self.n, self.n_res).astype(np.float32)
        ring += np.float32(self.noise_mw)
        veh = np.arange(self.n) if present is None else np.flatnonzero(self.resource >= 0)  # transmitters
        veh, sent_slot = self._sent_this_period(veh)
        own = veh * self.n_res
        own_res = (sent_slot * self.n_sub)[:, None] + np.arange(self.n_sub)[None, :]
        ring.reshape(-1)[(own[:, None] + own_res).reshape(-1)] = np.nan  # not monitored (half duplex)
        self.rssi_ring[k] = ring
        last_sci_mw = self.period_sci_mw.reshape(self.n, self.n_res)

        if self.per_ue:  # counters and reselections ran at the arrivals
            self.prev_sci_mw = self.period_sci_mw
            self.moved_from.fill(-1)
            if present is not None:
                self._select_joining(last_sci_mw, present)
        else:
            self._counters_and_reselections(last_sci_mw, present)
        self._new_period_buffers()

    def _counters_and_reselections(self, last_sci_mw: FloatArray, present: NDArray[np.bool_] | None) -> None:
        """``sps.reselection_timing=period_end``: every vehicle's counter and reselection at the end of
        the period, on the SCIs of the period just ended (``last_sci_mw`` [N, R], strongest SCI, mW)."""
        cfg = self.cfg
        if present is None:
            self.counter -= 1
            expired = self.counter <= 0
        else:  # only vehicles holding a resource count down
            holding = self.resource >= 0
            self.counter -= holding
            expired = (self.counter <= 0) & holding
        if self.standard:
            keep = ~self.releasing  # decided when the counter reached 1 (_decide_releases)
        else:
            keep = self.rng.random(self.n) < cfg.keep_probability
        reselect = np.flatnonzero(expired & ~keep)
        self.n_expiries += int(expired.sum())
        self.n_expiries_per_vehicle += expired
        self.n_keeps += int((expired & keep).sum())
        if np.any(expired):
            self.counter[expired] = draw_counters(cfg, self.rri, int(expired.sum()), self.rng)
        if reselect.size:
            self.resource[reselect] = self._sensing_selection(reselect, last_sci_mw, cfg.exclude_unmonitored)
            self.initial_resource[reselect] = False
            self.n_reselections += int(reselect.size)
        if present is not None:
            self._select_joining(last_sci_mw, present)
        if self.standard:
            self._decide_releases()

    def admit(self, gone: NDArray[np.bool_], entered: IntArray, traffic_rng: np.random.Generator) -> None:
        """``vehicles.population=open``: the SPS side of a mobility step. The slots ``gone`` [N] (emptied)
        hold no resource and no counter; the vehicles ``entered`` [E] have no SPS history (an empty
        sensing window, no resource: they listen for one period, then select at :meth:`end_period`)
        and, unless ``traffic.synchronous``, a new generation slot from ``traffic_rng``."""
        self.resource[gone] = -1
        self.counter[gone] = 0
        self.joining[gone] = False
        self.releasing[gone] = False
        self.initial_resource[gone] = False
        e = entered
        if e.size:
            self.resource[e] = -1
            self.counter[e] = 0
            self.joining[e] = True
            self.releasing[e] = False
            self.initial_resource[e] = False
            self.n_expiries_per_vehicle[e] = 0
            self.rssi_ring[:, e, :] = np.nan
            if not self.synchronous:
                self.generation_slot[e] = traffic_rng.integers(0, self.rri, size=e.size)
