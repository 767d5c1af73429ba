"""RSRP measurements of observation version 3 (cv2x_marl.env.measurement) against independent constructions."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env.measurement import Measurements, scaled_rsrp
from cv2x_marl.rng import env_stream

FAST = {"overrides": ["sim.warmup_subframes=200"]}


def _independent_reports(
    seed: int, periods: list[tuple[np.ndarray, np.ndarray]], window: int, error_db: float
) -> tuple[np.ndarray, np.ndarray]:
    """The reports after ``periods`` (rx_dbm, P per period), one ordered pair at a time, from the same
    draws (uniforms, Exp(1) fading, N(0, 1) errors per period, in that order) of the ``measurement`` stream."""
    rng = env_stream(seed, "measurement")
    n = periods[0][1].shape[0]
    history: list[tuple[np.ndarray, np.ndarray]] = []
    report = np.full((n, n), np.nan)
    age = np.zeros((n, n), dtype=int)
    for rx_dbm, p in periods:
        u = rng.random((n, n))
        fade = rng.standard_exponential((n, n))
        err = rng.standard_normal((n, n)) * error_db
        history.append((u < p, 10.0 ** (rx_dbm / 10.0) * fade))
        last = history[-window:]
        for j in range(n):
            for i in range(n):
                samples = [x[j, i] for dec, x in last if dec[j, i]]
                if samples:
                    report[j, i] = 10.0 * np.log10(np.mean(samples)) + err[j, i]
                age[j, i] = 0 if history[-1][0][j, i] else age[j, i] + 1
    return report, age


@pytest.mark.parametrize("fast", [True, False])
def test_rsrp_entries_match_an_independent_computation(fast: bool) -> None:
    """``fast``: SingleMover-v3's one-mover step keeps the mover's column (what it observes) current;
    the full step (every vehicle's links) every pair's."""
    seed = 11
    g = gymnasium.make("cv2x/SingleMover-v3", max_cycles=20, **FAST)
    g.unwrapped.fast = fast
    obs, _ = g.reset(seed=seed)
    par = g.unwrapped.par
    links = par.links
    periods = [(links.rx_dbm(par.positions_m), links.evaluate(par.positions_m)[0])] * par.measure.window
    rng = np.random.default_rng(0)
    for _ in range(7):
        obs, *_ = g.step(rng.uniform(-1, 1, 2).astype(np.float32))
        pos = par.positions_m.copy()
        periods.append((links.rx_dbm(pos), links.evaluate(pos)[0]))
    report, age = _independent_reports(seed, periods, par.measure.window, par.options.rsrp_error_db)
    cols = [0] if fast else slice(None)
    rsrp, report, age_env, age = par.measure.rsrp_dbm[:, cols], report[:, cols], par.measure.age[:, cols], age[:, cols]
    heard = np.isfinite(report)
    assert heard.sum() > (8 if fast else 100)  # most pairs are heard
    np.testing.assert_allclose(rsrp[heard], report[heard], rtol=0, atol=1e-9)
    assert np.isnan(rsrp[~heard]).all()
    np.testing.assert_array_equal(age_env, age)
    report, age = np.broadcast_to(report, (par.n, par.n)), np.broadcast_to(age, (par.n, par.n))  # column 0 below
    # the observation of vehicle 0: neighbour k is the k-th nearest (stable order), its link j -> 0
    d = np.hypot(*(par.positions_m - par.positions_m[0]).T)
    d[0] = np.inf
    order = np.argsort(d, kind="stable")[: par.layout.n_neighbours]
    meas = par.layout.measured(obs)
    expected = np.where(np.isfinite(report[order, 0]), (report[order, 0] + 100.0) / 20.0, 0.0)
    np.testing.assert_allclose(meas[:, 0], np.clip(expected, -10, 10), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(meas[:, 1], age[order, 0] / 10.0, rtol=1e-6)


def test_closed_form_mean_without_error() -> None:
    """error 0, one constant link: the report is 10 log10(rx_mw * mean of the decoded fades)."""
    rx = np.array([[-np.inf, -80.0], [-70.0, -np.inf]])
    p = np.array([[0.0, 1.0], [0.5, 0.0]])
    m = Measurements.start(rx, p, 4, 0.0, env_stream(3, "measurement"))
    rng = env_stream(3, "measurement")
    dec_10, fade_10 = [], []
    for _ in range(4):
        u = rng.random((2, 2))
        f = rng.standard_exponential((2, 2))
        rng.standard_normal((2, 2))
        dec_10.append(u[1, 0] < 0.5)
        fade_10.append(f[1, 0])
        assert u[0, 1] < 1.0
    fades = [f for d, f in zip(dec_10, fade_10, strict=True) if d]
    if fades:
        assert m.rsrp_dbm[1, 0] == pytest.approx(-70.0 + 10 * np.log10(np.mean(fades)), abs=1e-9)
    else:
        assert np.isnan(m.rsrp_dbm[1, 0])
    assert np.isnan(m.rsrp_dbm[0, 0])  # nothing heard from oneself (P = 0)


def test_stale_neighbour_keeps_its_value_and_ages() -> None:
    n, window = 3, 5
    rx = np.full((n, n), -75.0)
    p_on = np.ones((n, n)) - np.eye(n)
    m = Measurements.start(rx, p_on, window, 3.0, env_stream(5, "measurement"))
    assert np.isfinite(m.rsrp_dbm[~np.eye(n, dtype=bool)]).all() and (m.age[~np.eye(n, dtype=bool)] == 0).all()
    p_off = p_on.copy()
    p_off[1, 0] = 0.0  # vehicle 0 no longer decodes vehicle 1
    for _ in range(window):  # packets still in the window: reported afresh (new error), age grows
        m.update(rx, p_off)
    value = m.rsrp_dbm[1, 0]
    assert m.age[1, 0] == window
    for k in range(1, 4):  # the window holds none of 1's packets: the last report is kept (stale)
        m.update(rx, p_off)
        assert m.rsrp_dbm[1, 0] == value
        assert m.age[1, 0] == window + k
    assert m.age[2, 0] == 0 and m.rsrp_dbm[2, 0] != value


def test_scaled_rsrp() -> None:
    np.testing.assert_allclose(scaled_rsrp(np.array([-100.0, -80.0, np.nan])), [0.0, 1.0, 0.0])
