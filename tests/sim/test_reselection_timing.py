"""sps.reselection_timing (issue 13, defect 7): with ``per_ue`` a UE counts down and reselects at its
own packet arrival (its generation slot n), sensing the 1000 ms before n (SCIs heard earlier in the
same period included) and selecting in [n + T1, n + T2]; ``period_end`` (the default) is unchanged."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, ScenarioConfig, apply_overrides, preset
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.metrics import CAUSE_CODE

BASE = [
    "sim.warmup_subframes=0",
    "vehicles.n_vehicles=10",
    "traffic.synchronous=false",
    "sps.selection_window_subframes=20",
    "sps.selection=paper",
    "sps.paper_best_k=1",  # the lowest-RSSI survivor: a deterministic choice
    "sps.reselection_timing=per_ue",
]
ARRIVAL = 90  # slot of the arrival: candidates in slots 91-99 (this period) and 0-10 (the next)
STRONG_SCI_MW = 1e-3  # a strong SCI: 0 dBm of PSSCH power, RSRP far above any threshold
V, W = 0, 1  # the two UEs that reselect at ARRIVAL
R_PREV, R_Y = 95 * 2 + 0, 96 * 2 + 1  # candidates of V after the arrival slot
R_CUR, R_X = 5 * 2 + 0, 6 * 2 + 1  # candidates of W before it (slots 5, 6: heard this period or not at all)


def _expected_choice(vehicle: int, state: dict, cfg: ScenarioConfig) -> int:
    """The selection TS 36.213 14.1.1.6 prescribes, built independently from the captured sensing state:
    the SCI RSRP heard RRI before each candidate within the 1000 ms before the arrival, the literal
    3 dB loop, the S-RSSI average over the window's periods, the lowest-RSSI survivor."""
    n_sub, rri = cfg.sps.n_subchannels, cfg.traffic.rri_ms
    slots = [(ARRIVAL + k) % rri for k in range(1, cfg.sps.selection_window_subframes + 1)]
    cand = [s * n_sub + c for s in slots for c in range(n_sub)]
    own_slot = state["resource"][vehicle] // n_sub
    rsrp, rssi = [], []
    for r in cand:
        s = r // n_sub
        if s == ARRIVAL:  # n + RRI: its reserving SCI would be sent at n, outside [n - 1000, n - 1]
            heard = -math.inf
        else:
            heard = state["cur_rsrp"][vehicle, r] if s < ARRIVAL else state["prev_rsrp"][vehicle, r]
        rsrp.append(math.inf if s == own_slot else heard)
        # periods whose slot s lies in [n - 1000, n - 1]: this one and 9 before for s < n, else the 10 before
        values = []
        for q in range(state["ring"].shape[0]):
            x = float(state["ring"][q, vehicle, r])
            if q == state["oldest"] and s < ARRIVAL:
                x = math.nan if s == own_slot else float(np.float32(state["cur_rssi"][vehicle, r] + state["noise"]))
            if not math.isnan(x):
                values.append(x)
        rssi.append(sum(values) / len(values) if values else state["noise"])
    need = math.ceil(0.2 * len(cand))
    th = cfg.sps.rsrp_threshold_dbm
    while sum(x <= th for x in rsrp) < need:
        th += cfg.sps.threshold_step_db
    survivors = [i for i, x in enumerate(rsrp) if x <= th]
    return cand[min(survivors, key=lambda i: rssi[i])]


def _prepared(extra: list[str] | None = None) -> Simulator:
    sim = Simulator(apply_overrides(preset("paper"), [*BASE, *(extra or [])]))
    sim.reset(seed=2, warmup_subframes=0)
    sim.run(3 * sim.rri)  # 3 periods of sensing; now at a period start
    return sim


def _capture_at_arrival(sim: Simulator) -> dict:
    """The sensing state the UEs arriving at slot ``ARRIVAL`` select on, captured when their chunk of
    the period ends (filled in by the next run)."""
    n, r = sim.n, sim.n_res
    state: dict = {}
    arrivals = sim.scheduler.arrivals

    def spy(lo: int, hi: int, subframe: int) -> None:
        if hi - 1 == ARRIVAL:
            state.update(
                cur_rsrp=sim.period_rsrp_dbm.reshape(n, r).copy(),
                prev_rsrp=sim.scheduler.sci_rsrp_dbm(sim.scheduler.prev_sci_mw).reshape(n, r).copy(),
                cur_rssi=sim.scheduler.period_rssi_mw.reshape(n, r).copy(),
                ring=sim.scheduler.rssi_ring.copy(),
                oldest=(sim.subframe // sim.rri) % sim.scheduler.rssi_ring.shape[0],
                resource=sim.resource.copy(),
                noise=sim.noise_mw,
            )
        arrivals(lo, hi, subframe)

    sim.scheduler.arrivals = spy  # type: ignore[method-assign]
    return state


def test_a_ue_selects_at_its_own_arrival_on_the_1000_ms_before_it() -> None:
    sim = _prepared()
    cfg, n, r = sim.config, sim.n, sim.n_res
    assert sim.subframe % sim.rri == 0
    sim.scheduler.counter[:] = 50  # nobody else expires in this period
    sim.scheduler.counter[[V, W]] = 0
    sim.scheduler.generation_slot[[V, W]] = ARRIVAL
    sim.resource[V], sim.resource[W] = 40 * 2, 60 * 2  # old slots 40 and 60, before the arrival
    busy = np.isin(sim.resource, [R_PREV, R_Y, R_CUR, R_X])
    sim.resource[busy & (np.arange(n) > W)] = 50 * 2 + 1  # nobody else on the four candidates
    # SCIs: V heard one on R_PREV a period ago (slot 95 >= 90: that is the live reservation: excluded) and
    # one on R_Y "this period" (slot 96 is after the arrival: not yet heard, so ignored); W heard one on
    # R_CUR this period (slot 5 < 90: excluded) and one on R_X only a period ago (slot 6 was silent since: free)
    sim.scheduler.prev_sci_mw.reshape(n, r)[V, R_PREV] = STRONG_SCI_MW
    sim.scheduler.period_sci_mw.reshape(n, r)[V, R_Y] = STRONG_SCI_MW
    sim.scheduler.period_sci_mw.reshape(n, r)[W, R_CUR] = STRONG_SCI_MW
    sim.scheduler.prev_sci_mw.reshape(n, r)[W, R_X] = STRONG_SCI_MW
    # S-RSSI: the four are the quietest candidates, in this order for each UE
    sim.scheduler.rssi_ring[:, V, R_PREV], sim.scheduler.rssi_ring[:, V, R_Y] = 1e-15, 2e-15
    sim.scheduler.rssi_ring[:, W, R_CUR], sim.scheduler.rssi_ring[:, W, R_X] = 1e-15, 2e-15

    state = _capture_at_arrival(sim)
    start, reselections = sim.subframe, sim.n_reselections
    links = sim.run(2 * sim.rri).links
    assert links is not None and state and state["oldest"] == (start // sim.rri) % sim.scheduler.rssi_ring.shape[0]
    expected = [_expected_choice(V, state, cfg), _expected_choice(W, state, cfg)]
    assert sim.resource[[V, W]].tolist() == expected == [R_Y, R_X]
    assert sim.n_reselections - reselections == 2
    counter = sim.scheduler.counter
    assert np.all((counter[[V, W]] >= 5 - 2) & (counter[[V, W]] <= 15 - 2))  # new, then 2 arrivals
    # one transmission per packet: V sends on slot 40 and, after the arrival, on 96 in the same period;
    # W sends on 60, and its new slot 6 comes before the arrival: from the next period on
    sent = {u: sorted((links["subframe"][links["tx"] == u] - start).tolist()) for u in (V, W)}
    assert sorted(set(sent[V])) == [40, 96, 196] and sorted(set(sent[W])) == [60, 106]
    # neither of them monitored its transmissions: the S-RSSI ring of that period is NaN there
    first = (start // sim.rri) % sim.scheduler.rssi_ring.shape[0]
    ring_v = sim.scheduler.rssi_ring[first, V].reshape(sim.rri, 2)
    ring_w = sim.scheduler.rssi_ring[first, W].reshape(sim.rri, 2)
    assert np.isnan(ring_v[[40, 96]]).all() and not np.isnan(ring_v[[60, 6]]).any()
    assert np.isnan(ring_w[60]).all() and not np.isnan(ring_w[[40, 6, 96]]).any()


def test_the_arrival_slot_one_period_on_is_never_excluded() -> None:
    """With T2 = RRI (W = 100) the candidates include slot n + RRI itself; the SCI heard at n - RRI on
    that resource reserved n, not n + RRI, and the one that would reserve n + RRI comes at n, outside
    the sensing window: TS 36.213 14.1.1.6 excludes nothing there (review of issue 13)."""
    sim = _prepared(["sps.selection_window_subframes=100"])
    cfg, n, r = sim.config, sim.n, sim.n_res
    r_g, r_next = ARRIVAL * 2 + 0, (ARRIVAL + 1) * 2 + 0  # slot n + RRI, and slot n + 1
    sim.scheduler.counter[:] = 50
    sim.scheduler.counter[V] = 0
    sim.scheduler.generation_slot[V] = ARRIVAL
    sim.resource[V] = 40 * 2
    sim.resource[np.isin(sim.resource, [r_g, r_next]) & (np.arange(n) != V)] = 50 * 2 + 1
    sim.scheduler.prev_sci_mw.reshape(n, r)[V, r_g] = STRONG_SCI_MW  # heard at n - RRI: reserved n, which is now
    sim.scheduler.rssi_ring[:, V, r_g], sim.scheduler.rssi_ring[:, V, r_next] = 1e-15, 2e-15  # r_g the quietest
    state = _capture_at_arrival(sim)
    sim.run(sim.rri)
    assert state and sim.resource[V] == _expected_choice(V, state, cfg) == r_g


def test_the_same_ues_at_the_period_end_select_on_the_last_period_only() -> None:
    """period_end: the SCI heard on R_X a period ago excludes it, the one heard this period on R_CUR
    too (the whole period is the last period's map); the selection window still follows slot 90."""
    sim = _prepared(["sps.reselection_timing=period_end"])
    n, r = sim.n, sim.n_res
    sim.scheduler.counter[:] = 50
    sim.scheduler.counter[W] = 1  # expires at this period's end
    sim.scheduler.generation_slot[W] = ARRIVAL
    sim.resource[W] = 60 * 2
    sim.resource[np.isin(sim.resource, [R_CUR, R_X]) & (np.arange(n) != W)] = 50 * 2 + 1
    sim.scheduler.period_sci_mw.reshape(n, r)[W, R_CUR] = STRONG_SCI_MW
    sim.scheduler.period_sci_mw.reshape(n, r)[W, R_X] = STRONG_SCI_MW
    sim.scheduler.rssi_ring[:, W, R_CUR], sim.scheduler.rssi_ring[:, W, R_X] = 1e-15, 2e-15
    sim.run(sim.rri)
    assert sim.resource[W] not in (R_CUR, R_X) and (sim.resource[W] // 2 - ARRIVAL - 1) % 100 < 20


def test_standard_signalling_releases_at_the_arrival_where_the_counter_reaches_zero() -> None:
    sim = _prepared(["sps.reservation_signalling=standard"])
    n, r = sim.n, sim.n_res
    u, v = 2, 3
    sim.scheduler.counter[:] = 50
    sim.scheduler.counter[[u, v]] = 1  # their last packet arrives at slot 50 of this period
    sim.scheduler.generation_slot[[u, v]] = 50
    sim.resource[u], sim.resource[v] = 30 * 2, 70 * 2  # u sends before its arrival, v after it
    sim.resource[np.isin(sim.resource, [60, 140]) & ~np.isin(np.arange(n), [u, v])] = 10 * 2 + 1
    sim.scheduler.releasing[:] = False
    sim.run(sim.rri - 1)  # up to slot 98, before the period end
    rsrp = sim.period_rsrp_dbm.reshape(n, r)
    assert sim.scheduler.releasing[[u, v]].all() and np.all(sim.scheduler.counter[[u, v]] == 0)  # keep_probability 0
    assert np.isfinite(rsrp[:, 60]).any()  # u's packet before the arrival still reserves
    assert np.isneginf(rsrp[:, 140]).all()  # v's last packet (after it) reserves nothing
    sim.run(1 + 31)  # period end, then the next period up to slot 30: u's last packet
    assert np.isneginf(sim.period_rsrp_dbm.reshape(n, r)[:, 60]).all()
    before = sim.n_reselections
    sim.run(20)  # slots 31-50, the arrival at 50: both reselect, with fresh counters
    assert sim.n_reselections - before == 2 and not sim.scheduler.releasing[[u, v]].any()
    assert np.all(sim.scheduler.counter[[u, v]] >= 4)


def test_half_duplex_and_decoding_stay_consistent_after_mid_period_changes() -> None:
    sim = Simulator(
        apply_overrides(
            preset("paper"),
            ["vehicles.n_vehicles=60", "traffic.synchronous=false", "sps.reselection_timing=per_ue"],
        )
    )
    sim.reset(seed=3)
    links = sim.run(3000).links
    assert links is not None and sim.n_reselections > 50
    tx_sf = set(zip(links["tx"].tolist(), links["subframe"].tolist(), strict=True))
    busy = np.array([(b, s) in tx_sf for b, s in zip(links["rx"].tolist(), links["subframe"].tolist(), strict=True)])
    assert busy.sum() > 0 and np.all(links["cause"][busy] == CAUSE_CODE["half_duplex"])
    assert not np.any(links["cause"][~busy] == CAUSE_CODE["half_duplex"])
    # one transmission per packet: a packet arrives at subframe g + k RRI and goes out within the next
    # RRI, so the packet index (t - 1 - g) // RRI of each UE's transmissions steps by exactly one
    g0 = sim.scheduler.generation_slot
    for i in range(60):
        t = np.array(sorted({s for tx, s in tx_sf if tx == i}))
        k = (t - 1 - int(g0[i])) // sim.rri
        assert t.size >= 25 and np.all(np.diff(k) == 1), (i, t, k)


def test_last_links_hold_the_whole_period_when_it_is_cut() -> None:
    """The env's traffic mode reads ``last_links`` after one period: with per_ue, every chunk of it."""
    sim = Simulator(
        apply_overrides(
            preset("paper"),
            ["vehicles.n_vehicles=60", "traffic.synchronous=false", "sps.reselection_timing=per_ue"],
        )
    )
    sim.reset(seed=4)
    cut = 0
    for _ in range(5):
        events = sim.scheduler.next_arrival_event(0, sim.rri) < sim.rri
        links = sim.run(sim.rri).links
        assert links is not None and sim.last_links is not None
        tx, rx, p, cause = sim.last_links
        np.testing.assert_array_equal(tx, links["tx"])
        np.testing.assert_array_equal(rx, links["rx"])
        np.testing.assert_array_equal(p, links["p_success"])
        np.testing.assert_array_equal(cause, links["cause"])
        cut += events
    assert cut >= 3  # most of these periods were cut at an expiry


@pytest.mark.parametrize("signalling", ["always", "standard"])
def test_the_default_is_bit_identical_to_the_code_before_the_switch(signalling: str) -> None:
    """Reference values: the same run on commit 38b49f8 (before sps.reselection_timing)."""
    for timing in ([], ["sps.reselection_timing=period_end"]):
        cfg = apply_overrides(
            preset("paper"),
            [
                "sim.warmup_subframes=500",
                "vehicles.n_vehicles=60",
                "traffic.synchronous=false",
                "sps.keep_probability=0.4",
                f"sps.reservation_signalling={signalling}",
                *timing,
            ],
        )
        assert cfg.sps.reselection_timing == "period_end"
        sim = Simulator(cfg)
        sim.reset(seed=5)
        result = sim.run(3000)
        assert result.links is not None
        assert result.metrics.summary()["prr_mean"] == 0.6961440814037098
        assert (sim.n_reselections, sim.scheduler.n_keeps) == (106, 79)
        assert int(np.sum(sim.resource * np.arange(sim.n))) == 159069
        assert int(result.links["outcome"].sum()) == 73495


def test_unknown_timing_is_refused_by_name() -> None:
    with pytest.raises(
        ConfigError, match=r"sps\.reselection_timing: 'perue' is not allowed; allowed values: period_end"
    ):
        apply_overrides(preset("paper"), ["sps.reselection_timing=perue"])


def test_per_ue_with_an_open_population(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Entering vehicles listen a period and select at its end, then count down at their arrivals."""
    pytest.importorskip("libsumo")
    from cv2x_marl.sim import sumo

    monkeypatch.setenv(sumo.CACHE_ENV, str(tmp_path))
    over = ["road.length_m=600", "sim.warmup_subframes=0", "sps.reselection_timing=per_ue"]
    sim = Simulator(apply_overrides(preset("sumo-highway"), over))
    try:
        sim.reset(seed=3)
        links = sim.run(3000).links
        assert links is not None and sim.n_entries > 0 and sim.n_departures > 0 and sim.n_reselections > 0
        assert sim.present is not None
        assert np.all(sim.resource[~sim.present] == -1) and np.all(sim.scheduler.counter[sim.resource >= 0] >= 0)
        tx_sf = set(zip(links["tx"].tolist(), links["subframe"].tolist(), strict=True))
        rx_sf = zip(links["rx"].tolist(), links["subframe"].tolist(), strict=True)
        busy = np.array([(b, s) in tx_sf for b, s in rx_sf])
        assert np.all(links["cause"][busy] == CAUSE_CODE["half_duplex"])
        assert not np.any(links["cause"][~busy] == CAUSE_CODE["half_duplex"])
    finally:
        sim.close()


def test_the_compiled_sparse_period_equals_the_numpy_period_with_per_ue(compiled_and_numpy: Callable[..., Any]) -> None:
    """per_ue cuts periods into chunks; the compiled period runs them as the numpy one does."""
    over = [
        "link.pair_state=sparse",
        "metrics.record_links=false",
        "sps.reselection_timing=per_ue",
        "sps.reservation_signalling=standard",
    ]
    a, _, _, _ = compiled_and_numpy(apply_overrides(preset("highway"), over), 5, 300, 650)
    assert a.sparse_state and a.n_reselections > 0


def test_a_run_crossing_into_a_period_keeps_the_whole_last_period_in_last_links() -> None:
    """per_ue cuts a period into chunks; when one run crosses into a period whose part has no transmitter
    yet, last_links is the whole previous period (its chunks joined), as after a run ending on it."""
    cfg = apply_overrides(preset("highway"), [*BASE, "sps.reselection_timing=per_ue", "road.length_m=300"])
    for seed in range(20):
        a = Simulator(cfg)
        a.reset(seed, warmup_subframes=1000)
        expiring = bool(np.any(a.scheduler.counter <= 1))  # a UE's counter runs out in this period: the period is cut
        cuts: list[tuple[int, int]] = []
        orig = a._chunk
        a._chunk = lambda lo, hi, *rest, _o=orig, _c=cuts: (_c.append((lo, hi)), _o(lo, hi, *rest))[1]  # type: ignore[method-assign]
        a.run(a.rri)
        if expiring and len(cuts) > 1 and not np.any(a.slot == 0):  # nobody transmits in the next slot 0
            break
    else:
        pytest.skip("no seed with a cut period followed by an empty slot 0")
    assert a.last_links is not None
    b = Simulator(cfg)
    b.reset(seed, warmup_subframes=1000)
    b.run(b.rri + 1)  # one run: the whole period, then slot 0 of the next (no transmitter)
    assert b.last_links is not None
    for x, y in zip(a.last_links, b.last_links, strict=True):
        np.testing.assert_array_equal(x, y)
