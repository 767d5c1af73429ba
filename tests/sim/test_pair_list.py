"""The Verlet list of the pairs in range (``Simulator.pair_skin_m``): every period's pairs equal a fresh
sweep's, in the same order, through rebuilds, wrap-around, agent offsets and open populations; the
runs are identical to runs that sweep every period."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from cv2x_marl.config import apply_overrides, preset
from cv2x_marl.sim import Simulator, kernels
from cv2x_marl.sim.geometry import PairList


@pytest.mark.parametrize("wrap", [True, False])
def test_filtered_candidates_equal_the_sweep_at_the_cut_off(wrap: bool) -> None:
    rng = np.random.default_rng(7)
    box = np.array([3000.0, np.inf]) if wrap else np.full(2, np.inf)
    for n, r in ((50, 400.0), (400, 250.0), (1000, 900.0)):
        pos0 = np.column_stack((rng.uniform(0, 3000, n), rng.uniform(0, 20, n)))
        ci, cj = kernels.pairs_within_range(pos0, box, r + 60.0)
        for _ in range(5):  # moves of at most 29.9 m each: no pair from outside r + 60 comes within r
            step = rng.uniform(-1, 1, (n, 2))
            pos = pos0 + 29.9 * step / np.linalg.norm(step, axis=1, keepdims=True) * rng.uniform(0, 1, (n, 1))
            i, j = kernels.filter_pairs_within_range(pos, box, r, ci, cj)
            ri, rj = kernels.pairs_within_range(pos, box, r)
            np.testing.assert_array_equal(i, ri)
            np.testing.assert_array_equal(j, rj)
            assert ri.size < ci.size  # the skin holds pairs that the filter drops


def _run_pairs(
    cfg: object, skin: float, periods: int, offsets: bool = False
) -> tuple[list[tuple[np.ndarray, np.ndarray]], Simulator, int]:
    """Each period's links (tx, rx), the simulator, and how many times the pair list was built."""
    sim = Simulator(cfg)  # type: ignore[arg-type]
    sim.pair_skin_m = skin
    sim.reset(3)
    out = []
    rng = np.random.default_rng(0)
    builds, last = 0, None
    for _ in range(periods):
        if offsets:  # the env's agents move vehicles off their road positions
            sim.set_offsets(rng.uniform(-2, 2, (sim.n, 2)))
        geo = sim._period_geometry()
        out.append((geo.tx.copy(), geo.rx.copy()))
        if sim.pair_list.built is not last:
            builds, last = builds + 1, sim.pair_list.built
        sim.run(sim.rri)
    return out, sim, builds


@pytest.mark.parametrize("offsets", [False, True])
def test_simulator_pairs_equal_a_sweep_every_period(offsets: bool) -> None:
    """Highway ring with a 300 m cut-off and its default 15 m skin: the list is rebuilt every few periods
    (vehicles move up to 3.9 m per period), and every period's links, and the whole run, equal a sweep's."""
    cfg = apply_overrides(
        preset("highway-legacy"),
        ["road.length_m=1500", "link.max_range_m=300", "metrics.max_distance_m=300", "sim.warmup_subframes=0"],
    )
    skin_pairs, a, builds = _run_pairs(cfg, 15.0, 25, offsets)
    sweep_pairs, b, none = _run_pairs(cfg, 0.0, 25, offsets)
    assert none == 0 and b.pair_list.built is None
    assert 2 <= builds <= 20  # rebuilt on the way, but not every period
    for (tx_a, rx_a), (tx_b, rx_b) in zip(skin_pairs, sweep_pairs, strict=True):
        np.testing.assert_array_equal(tx_a, tx_b)
        np.testing.assert_array_equal(rx_a, rx_b)
    assert a.last_links is not None and b.last_links is not None
    for x, y in zip(a.last_links, b.last_links, strict=True):
        np.testing.assert_array_equal(x, y)
    # a skin of 5 % of the cut-off by default
    assert Simulator(cfg).pair_skin_m == pytest.approx(15.0)


def _list_built(skin_m: float) -> tuple[Simulator, np.ndarray, object]:
    """A 1 km highway ring with a 200 m cut-off and the given skin, reset: the simulator, its positions and the
    pair list the reset built."""
    cfg = apply_overrides(preset("highway-legacy"), ["road.length_m=1000", "link.max_range_m=200"])
    sim = Simulator(cfg)
    sim.pair_skin_m = skin_m
    sim.reset(1, warmup_subframes=0)
    pos = np.ascontiguousarray(sim._period_geometry().positions_m)
    assert sim.pair_list.built is not None
    return sim, pos, sim.pair_list.built


def test_rebuild_when_a_vehicle_moved_half_the_skin() -> None:
    sim, pos, built = _list_built(10.0)
    offsets = np.zeros((sim.n, 2))
    offsets[4, 0] = 4.9  # 2 x 4.9 < 10: the list stands
    sim._pairs(pos + offsets)
    assert sim.pair_list.built is built
    offsets[4, 0] = 5.1  # 2 x 5.1 > 10: rebuilt
    i, j = sim._pairs(pos + offsets)
    assert sim.pair_list.built is not built
    ri, rj = kernels.pairs_within_range(pos + offsets, sim.road.periodic_box_m, 200.0)
    np.testing.assert_array_equal(i, ri)
    np.testing.assert_array_equal(j, rj)


def test_a_changed_skin_rebuilds_the_list() -> None:
    sim, pos, built = _list_built(1.0)
    sim.pair_skin_m = 10.0  # the 1 m list holds no pair between 201 and 210 m: it must not be reused
    sim._pairs(pos)
    assert sim.pair_list.built is not built and sim.pair_list.built is not None and sim.pair_list.built[2] == 10.0


def _vehicles_at(t: float) -> list[tuple[str, float]]:
    """Vehicles driving apart and together (pairs leave and enter a 60 m range); b leaves at 1 s and d takes
    its slot; f enters a new slot at 1.5 s; e leaves at 2.2 s and nobody takes its slot."""
    ids = ["a", "c", "b" if t < 1.0 - 1e-9 else "d", "e"]
    out = [(v, 50 + 30 * i + (15, -10, 5, -15)[i] * t) for i, v in enumerate(ids)]
    if t >= 2.2 - 1e-9:
        out = out[:3]
    if t >= 1.5 - 1e-9:
        out.append(("f", 60 + 10 * t))
    return out


def test_open_population_pairs_equal_a_sweep(
    tmp_path: Path, write_fcd: Callable[..., Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = apply_overrides(
        preset("paper"),
        [
            "vehicles.mobility=trace",
            f"vehicles.trace_file={write_fcd(tmp_path / 'fcd.xml', 4.0, _vehicles_at)}",
            "vehicles.population=open",
            "vehicles.sumo_begin_s=0",
            "vehicles.capacity=5",
            "sim.warmup_subframes=0",
            "link.max_range_m=60",
            "metrics.interferer_range_m=60",
        ],
    )
    slot_sets: set[tuple[int, ...]] = set()
    real_pairs_of = PairList._pairs_of

    def spy(pairs: PairList, pos: np.ndarray, idx: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        slot_sets.add(tuple(range(pairs.n)) if idx is None else tuple(idx.tolist()))
        return real_pairs_of(pairs, pos, idx)

    monkeypatch.setattr(PairList, "_pairs_of", spy)
    skin_pairs, a, builds = _run_pairs(cfg, 4.0, 30)
    sweep_pairs, _, _ = _run_pairs(cfg, 0.0, 30)
    # the present slots changed twice (f entered slot 4, e left slot 3), each change rebuilding the list
    assert slot_sets == {(0, 1, 2, 3), (0, 1, 2, 3, 4), (0, 1, 2, 4)}
    assert builds >= 3
    sizes = []
    for (tx_a, rx_a), (tx_b, rx_b) in zip(skin_pairs, sweep_pairs, strict=True):
        np.testing.assert_array_equal(tx_a, tx_b)
        np.testing.assert_array_equal(rx_a, rx_b)
        sizes.append(tx_a.size)
    steps = np.diff(sizes)
    assert np.any(steps > 0) and np.any(steps < 0)  # pairs came into range (a, e) and went out of it (c, d)
    assert a.n_departures == 2 and a.n_entries == 2  # b and e left; d and f entered
