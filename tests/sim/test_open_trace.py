"""Open populations from a hand-written FCD trace (no SUMO needed): a vehicle leaving while another
takes its slot in the same step is a departure, and the per-node PRR of the run is per vehicle (the
two vehicles that shared the slot are two nodes), checked against the links table."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from cv2x_marl.config import apply_overrides, preset
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.metrics import CAUSE_CODE

SWAP_S = 0.5  # b leaves, d appears, at this trace time


def _vehicles_at(t: float) -> list[tuple[str, float]]:
    """a, b, c 40 m apart, moving at 1 m/s; b leaves at SWAP_S and d takes its place."""
    return [(v, 50 + 40 * i + t) for i, v in enumerate(["a", "c", "b" if t < SWAP_S - 1e-9 else "d"])]


def test_slot_handover_is_a_departure_and_node_prr_is_per_vehicle(
    tmp_path: Path, write_fcd: Callable[..., Path]
) -> None:
    cfg = apply_overrides(
        preset("paper"),
        [
            "vehicles.mobility=trace",
            f"vehicles.trace_file={write_fcd(tmp_path / 'fcd.xml', 3.0, _vehicles_at)}",
            "vehicles.population=open",
            "vehicles.sumo_begin_s=0",
            "vehicles.capacity=4",
            "sim.warmup_subframes=0",
            "metrics.record_links=true",
            "sps.n_subchannels=1",
        ],
    )
    sim = Simulator(cfg)
    sim.reset(0)
    assert sim.vehicle_ids == ["a", "b", "c", None]  # first seen, then ID
    res = sim.run(25 * sim.rri)
    assert sim.vehicle_ids == ["a", "d", "c", None]  # d took b's slot in the step b left
    assert sim.n_departures == 1 and sim.n_entries == 1
    links = res.links
    assert links is not None
    swap_sf = round(SWAP_S * 1000)
    target = links["cause"] != CAUSE_CODE["half_duplex"]

    def prr(tx: int, lo: int, hi: int) -> float:
        sel = target & (links["tx"] == tx) & (links["subframe"] >= lo) & (links["subframe"] < hi)
        assert sel.sum() >= 4
        return float(np.mean(links["outcome"][sel]))

    end = 25 * sim.rri
    # nodes: those that left (b), then those present by slot (a, d, c)
    expected = [prr(1, 0, swap_sf), prr(0, 0, end), prr(1, swap_sf, end), prr(2, 0, end)]
    summary = res.metrics.summary()
    np.testing.assert_allclose(summary["node_prr"], expected, rtol=0, atol=1e-12)
    assert summary["prr_mean"] == float(np.mean(expected))
    # d listened for one period after it appeared: no transmission from slot 1 in [swap, swap + RRI)
    assert not np.any((links["tx"] == 1) & (links["subframe"] >= swap_sf) & (links["subframe"] < swap_sf + sim.rri))


def test_capacity_without_an_open_population_is_refused() -> None:
    import pytest

    from cv2x_marl.config import ConfigError

    with pytest.raises(ConfigError, match=r"vehicles\.capacity=40 sizes an open population's slots"):
        apply_overrides(preset("paper"), ["vehicles.capacity=40"])
