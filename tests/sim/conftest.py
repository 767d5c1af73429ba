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
    the numpy chunk (``Simulator.compiled_period``); asserts that they agree and returns
    ``(compiled_sim, its_metrics, numpy_sim, its_metrics)``. End the run mid-period so that the period's
    SCI map and S-RSSI sums are compared while they hold something.

    Exact: transmitters, receivers, causes, decoded counts, SCI map, S-RSSI, resources (sums of the same
    powers in the same order, maxima). ``P`` and its sums to 1e-12: the kernel's ``log10`` / ``pow`` are
    libm's, numpy may dispatch SIMD versions that differ in the last bit on some CPUs (equal on the
    development machine; docs/model.md, "The compiled period")."""
    import numpy as np

    from cv2x_marl.sim import Simulator

    def run(cfg: Any, seed: int, warmup_subframes: int, n_subframes: int) -> tuple[Any, Any, Any, Any]:
        out = []
        for compiled in (True, False):
            sim = Simulator(cfg)
            sim.compiled_period = compiled
            sim.compiled_min_links = 0  # the compiled chunk at any size
            sim.reset(seed, warmup_subframes=warmup_subframes)  # part periods: chunks of part of a period
            out.append((sim, sim.run(n_subframes).metrics))
        (a, ma), (b, mb) = out
        assert a.subframe % a.rri != 0, "end the run mid-period: the period's maps are compared"
        assert a.last_links is not None and b.last_links is not None
        (tx_a, rx_a, p_a, cause_a), (tx_b, rx_b, p_b, cause_b) = a.last_links, b.last_links
        for x, y in ((tx_a, tx_b), (rx_a, rx_b), (cause_a, cause_b)):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_allclose(p_a, p_b, rtol=1e-12, atol=1e-15)
        for key in ("bin_n", "bin_decoded", "bin_causes", "node_n", "node_decoded"):
            np.testing.assert_array_equal(getattr(ma, key), getattr(mb, key), err_msg=key)
        for key in ("bin_expected", "node_expected"):
            np.testing.assert_allclose(getattr(ma, key), getattr(mb, key), rtol=1e-12, atol=1e-12, err_msg=key)
        assert np.any(a._period_sci_mw > 0) and np.any(a._period_rssi > 0)
        np.testing.assert_array_equal(a._period_sci_mw, b._period_sci_mw)
        np.testing.assert_array_equal(a._period_rssi, b._period_rssi)
        np.testing.assert_array_equal(a._rssi_ring, b._rssi_ring)
        np.testing.assert_array_equal(a.resource, b.resource)
        assert not np.any(a._chunk_total) and not np.any(a._chunk_total_slot)  # the scratches left zero
        assert a.n_reselections == b.n_reselections
        assert ma.n_transmissions == mb.n_transmissions > 0
        return a, ma, b, mb

    return run


@pytest.fixture()
def write_fcd() -> Callable[..., Any]:
    """``write(path, seconds, vehicles_at)``: a SUMO FCD trace (``<fcd-export>``) of 0.1 s steps from 0 to
    ``seconds``, ``vehicles_at(t)`` giving the ``(id, x)`` of the vehicles present at time ``t`` (on the
    paper grid's road ``y = 56.25`` m); returns ``path``."""
    from pathlib import Path

    def write(path: Path, seconds: float, vehicles_at: Callable[[float], list[tuple[str, float]]]) -> Path:
        lines = ["<fcd-export>"]
        for k in range(round(seconds / 0.1) + 1):
            t = k * 0.1
            lines.append(f'<timestep time="{t:.2f}">')
            for v, x in vehicles_at(t):
                lines.append(f'<vehicle id="{v}" x="{x:.3f}" y="56.25" angle="90" speed="1"/>')
            lines.append("</timestep>")
        lines.append("</fcd-export>")
        path.write_text("\n".join(lines))
        return path

    return write
