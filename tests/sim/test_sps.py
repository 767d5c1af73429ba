"""SPS: counters, keep probability, the 3 dB exclusion loop and the selection rules."""

import math

import numpy as np
import pytest

from cv2x_marl.config import SpsConfig, from_dict, preset
from cv2x_marl.sim import Simulator, sps


@pytest.mark.parametrize(("rri_ms", "lo", "hi"), [(100, 5, 15), (200, 5, 15), (50, 10, 30), (20, 25, 75)])
def test_counter_range(rri_ms: int, lo: int, hi: int) -> None:
    cfg = SpsConfig()
    assert sps.counter_range(cfg, rri_ms) == (lo, hi)
    draws = sps.draw_counters(cfg, rri_ms, 20_000, np.random.default_rng(0))
    assert draws.min() == lo and draws.max() == hi
    assert np.bincount(draws - lo).min() > 0  # every value in the range occurs


def _loop_reference(rsrp_row: np.ndarray, th0: float, step: float, frac: float) -> tuple[float, int]:
    """The standard's loop, literally: raise the threshold until >= 20 % remain."""
    m = rsrp_row.size
    th = th0
    while np.sum(rsrp_row <= th) < frac * m - 1e-9:
        th += step
    return th, int(np.sum(rsrp_row <= th))


def test_threshold_closed_form_matches_the_loop_and_keeps_20_percent() -> None:
    rng = np.random.default_rng(5)
    cfg = SpsConfig(rsrp_threshold_dbm=-110.0)
    v, m = 500, 40
    rsrp = rng.uniform(-130, -60, size=(v, m))
    rsrp[rng.random((v, m)) < 0.3] = -np.inf  # no SCI received
    rsrp[:, 0] = np.inf  # unmonitored
    rssi = rng.uniform(1e-12, 1e-9, size=(v, m))
    sel = sps.select(rsrp, rssi, cfg, rng)
    for row in range(v):
        th, kept = _loop_reference(rsrp[row], -110.0, 3.0, 0.2)
        assert sel.threshold_dbm[row] == pytest.approx(th)
        assert sel.n_kept[row] == kept
    assert np.all(sel.n_kept >= math.ceil(0.2 * m))
    chosen = rsrp[np.arange(v), sel.choice]
    assert np.all(chosen <= sel.threshold_dbm)  # never an excluded candidate
    assert np.all(sel.choice != 0)  # never the unmonitored one


def test_paper_rule_picks_among_best_three_by_rssi() -> None:
    rng = np.random.default_rng(1)
    cfg = SpsConfig(selection="paper")
    rsrp = np.full((3000, 10), -np.inf)
    rssi = np.tile(np.arange(10, 0, -1, dtype=float), (3000, 1))  # best (lowest) RSSI at index 9, 8, 7
    sel = sps.select(rsrp, rssi, cfg, rng)
    counts = np.bincount(sel.choice, minlength=10)
    assert set(np.flatnonzero(counts)) == {7, 8, 9}
    assert counts[7:].min() > 900  # uniform among the three


def test_3gpp_rule_picks_uniformly_in_lowest_20_percent() -> None:
    rng = np.random.default_rng(2)
    cfg = SpsConfig(selection="3gpp")
    rsrp = np.full((5000, 20), -np.inf)
    rssi = np.tile(np.arange(20, dtype=float), (5000, 1))
    sel = sps.select(rsrp, rssi, cfg, rng)
    counts = np.bincount(sel.choice, minlength=20)
    assert set(np.flatnonzero(counts)) == {0, 1, 2, 3}  # ceil(0.2 * 20) = 4
    assert counts[:4].min() > 1100


def test_candidate_window_wraps_modulo_rri() -> None:
    cfg = SpsConfig(n_subchannels=2, t1_subframes=1, selection_window_subframes=4)
    cand = sps.candidate_resources(np.array([0, 98]), cfg, 100)
    assert cand[0].tolist() == [2, 3, 4, 5, 6, 7, 8, 9]
    assert cand[1].tolist() == [198, 199, 0, 1, 2, 3, 4, 5]


def test_observed_keep_frequency_and_counter_cycle() -> None:
    cfg = from_dict({"sps": {"keep_probability": 0.6}, "metrics": {"record_links": False}}, preset("paper"))
    sim = Simulator(cfg)
    sim.reset(seed=4, warmup_subframes=0)
    sim.run(60_000, record=False)
    n = sim.scheduler.n_expiries
    # 21 vehicles x 600 periods / mean counter 10 = about 1260 expiries
    assert 1000 < n < 1500
    freq = sim.scheduler.n_keeps / n
    assert abs(freq - 0.6) < 4 * np.sqrt(0.6 * 0.4 / n)
    assert n - sim.scheduler.n_keeps == sim.n_reselections
    lo, hi = sps.counter_range(cfg.sps, cfg.traffic.rri_ms)
    assert np.all((sim.scheduler.counter >= 1) & (sim.scheduler.counter <= hi))
    assert lo == 5
