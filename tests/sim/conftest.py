"""Shared fixtures of the simulator tests."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest


@pytest.fixture(autouse=True, scope="module")
def _sumo_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """One generated-SUMO-scenario cache per test module, never the user's (``CV2X_MARL_SUMO_CACHE``)."""
    from cv2x_marl.sim.sumo import CACHE_ENV

    mp = pytest.MonkeyPatch()
    mp.setenv(CACHE_ENV, str(tmp_path_factory.mktemp("sumo-cache")))
    yield
    mp.undo()


@pytest.fixture()
def compiled_and_numpy() -> Callable[..., tuple[Any, Any, Any, Any]]:
    """``run(cfg, seed, warmup_subframes, n_subframes)``: the same scenario with the compiled chunk and with
    the numpy chunk (``Simulator.compiled_period``); asserts that they agree bit for bit (last links, PRR
    sums, SCI map, S-RSSI ring, resources) and returns ``(compiled_sim, its_metrics, numpy_sim, its_metrics)``."""
    import numpy as np

    from cv2x_marl.sim import Simulator

    def run(cfg: Any, seed: int, warmup_subframes: int, n_subframes: int) -> tuple[Any, Any, Any, Any]:
        out = []
        for compiled in (True, False):
            sim = Simulator(cfg)
            sim.compiled_period = compiled
            sim.reset(seed, warmup_subframes=warmup_subframes)  # part periods: chunks of part of a period
            out.append((sim, sim.run(n_subframes).metrics))
        (a, ma), (b, mb) = out
        assert a.last_links is not None and b.last_links is not None
        for x, y in zip(a.last_links, b.last_links, strict=True):
            np.testing.assert_array_equal(x, y)
        for key in ("bin_n", "bin_decoded", "bin_causes", "bin_expected", "node_n", "node_decoded", "node_expected"):
            np.testing.assert_array_equal(getattr(ma, key), getattr(mb, key), err_msg=key)
        np.testing.assert_array_equal(a._period_sci_mw, b._period_sci_mw)
        np.testing.assert_array_equal(a._period_rssi, b._period_rssi)
        np.testing.assert_array_equal(a._rssi_ring, b._rssi_ring)
        np.testing.assert_array_equal(a.resource, b.resource)
        assert a.n_reselections == b.n_reselections
        assert ma.n_transmissions == mb.n_transmissions > 0
        return a, ma, b, mb

    return run
