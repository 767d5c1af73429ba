"""sps.reservation_signalling (issue 13, defect 1): with ``standard`` the keep/reselect draw is
taken when the counter reaches 1 and the last SCI of a UE that will reselect reserves nothing, so
nobody excludes its resource on that account; ``always`` (the default) is unchanged."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.sim import Simulator

BASE = ["sim.warmup_subframes=0", "vehicles.n_vehicles=60", "traffic.synchronous=false"]


def _mid_period(mode: str, seed: int = 4) -> Simulator:
    sim = Simulator(apply_overrides(preset("paper"), [*BASE, f"sps.reservation_signalling={mode}"]))
    sim.reset(seed, warmup_subframes=0)
    sim.run(4 * sim.rri)  # counters start in [5, 15]: after 4 periods the 5s are at 1
    sim.run(sim.rri - 1)  # every transmission of the fifth period but its last subframe, no period end yet
    return sim


def test_the_last_sci_before_reselection_reserves_nothing() -> None:
    std = _mid_period("standard")
    releasing = np.flatnonzero(std.scheduler.releasing)
    assert releasing.size > 0 and np.all(std.scheduler.counter[releasing] == 1)  # keep_probability 0: all of them
    rsrp = std.period_rsrp_dbm.reshape(std.n, std.n_res)
    sent = [i for i in releasing if std.slot[i] < std.rri - 1]
    others = [i for i in range(std.n) if i not in set(releasing) and std.slot[i] < std.rri - 1]
    assert sent and others
    # no receiver recorded a reservation on the resource of a releasing UE that only it uses
    alone = [i for i in sent if np.sum(std.resource == std.resource[i]) == 1]
    assert alone and np.all(np.isneginf(rsrp[:, std.resource[alone]]))
    assert np.any(np.isfinite(rsrp[:, std.resource[others]]))
    legacy = _mid_period("always")
    assert not legacy.scheduler.releasing.any()
    np.testing.assert_array_equal(legacy.resource, std.resource)  # same start: only the SCIs differ
    assert np.any(np.isfinite(legacy.period_rsrp_dbm.reshape(std.n, std.n_res)[:, std.resource[alone]]))


def test_releasing_ues_reselect_at_the_period_end_and_the_rest_keep_their_counters() -> None:
    sim = _mid_period("standard")
    releasing = sim.scheduler.releasing.copy()
    counters = sim.scheduler.counter.copy()
    sim.run(1)  # the period ends: decrement, reselections, the next period's draw
    assert sim.scheduler.n_expiries == int(releasing.sum()) == sim.n_reselections
    np.testing.assert_array_equal(sim.scheduler.counter[~releasing], counters[~releasing] - 1)
    assert np.all(sim.scheduler.counter[releasing] >= 5)  # fresh counters, 5-15 at RRI 100
    # keep_probability 0: all of them
    np.testing.assert_array_equal(sim.scheduler.releasing, sim.scheduler.counter == 1)


def test_unknown_mode_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"sps\.reservation_signalling: 'never' is not allowed"):
        apply_overrides(preset("paper"), ["sps.reservation_signalling=never"])
