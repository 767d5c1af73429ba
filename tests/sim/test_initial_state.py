"""sim.warmup_mode and the SPS state at the start of the measurement (issue 13, defect 2).

``fixed`` (the default) warms up for ``sim.warmup_subframes``; ``until_reselected`` goes on until
every vehicle has left its random initial resource by a sensing-based selection. The run summary
reports the state either way (``sps_state_at_start``)."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.sim import Simulator

BASE = ["sim.warmup_subframes=0", "vehicles.n_vehicles=30", "traffic.synchronous=false"]


def _sim(*extra: str) -> Simulator:
    return Simulator(apply_overrides(preset("paper"), [*BASE, *extra]))


def test_counter_state_after_five_periods_by_hand() -> None:
    sim = _sim()
    sim.reset(7, warmup_subframes=0)
    c0 = sim.scheduler.counter.copy()  # drawn uniformly in [5, 15] at RRI 100
    state0 = sim.sps_state()
    assert state0["share_initial_resource"] == 1.0 and state0["share_never_expired"] == 1.0
    assert state0["counter_histogram"] == {str(v): int(np.sum(c0 == v)) for v in np.unique(c0)}
    assert state0["counter_mean"] == pytest.approx(c0.mean())
    sim.run(5 * sim.rri, record=False)
    # keep_probability 0: exactly the vehicles drawn with 5 expired once and reselected
    fives = c0 == 5
    assert fives.any() and not fives.all()
    state = sim.sps_state()
    assert state["subframe"] == 5 * sim.rri
    assert state["share_initial_resource"] == pytest.approx(1.0 - fives.mean())
    assert state["share_never_expired"] == pytest.approx(1.0 - fives.mean())
    np.testing.assert_array_equal(sim.scheduler.counter[~fives], c0[~fives] - 5)
    np.testing.assert_array_equal(sim.scheduler.initial_resource, ~fives)


def test_summary_reports_the_state_at_measurement_start() -> None:
    sim = _sim()
    sim.reset(7, warmup_subframes=0)
    sim.run(3 * sim.rri, record=False)
    want = sim.sps_state()
    summary = sim.run(sim.rri).metrics.summary()
    assert summary["sps_state_at_start"] == want


def test_until_reselected_ends_after_the_longest_first_counter() -> None:
    sim = _sim()
    sim.reset(7, warmup_subframes=0)
    longest = int(sim.scheduler.counter.max())
    warm = _sim("sim.warmup_mode=until_reselected")
    warm.reset(7, warmup_subframes=0)  # same seed: same initial counters; keep_probability 0
    assert warm.subframe == longest * warm.rri
    state = warm.sps_state()
    assert state["share_initial_resource"] == 0.0 and state["share_never_expired"] == 0.0
    assert not warm.scheduler.initial_resource.any()


def test_until_reselected_with_keeps_and_a_longer_fixed_warmup() -> None:
    sim = _sim("sim.warmup_mode=until_reselected", "sps.keep_probability=0.5", "sim.warmup_subframes=2050")
    sim.reset(2)
    assert sim.subframe >= 2050 and sim.subframe % sim.rri == 0
    assert not sim.scheduler.initial_resource.any()
    assert sim.scheduler.n_keeps > 0  # some expiries kept the resource, so the warm-up had to go on past them


def test_fixed_is_the_default_and_unchanged() -> None:
    cfg = preset("paper")
    assert cfg.sim.warmup_mode == "fixed"
    sim = Simulator(cfg)
    sim.reset(1)
    assert sim.subframe == cfg.sim.warmup_subframes


def test_unknown_mode_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"sim\.warmup_mode: 'forever' is not allowed; allowed values: fixed"):
        apply_overrides(preset("paper"), ["sim.warmup_mode=forever"])
