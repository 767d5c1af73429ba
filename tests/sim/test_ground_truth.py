"""SnapshotLinks (the env's all-links evaluator): the compiled kernel against the numpy reference,
both against MoverLinks (the general :func:`cv2x_marl.sim.channel.path_loss_db`, one transmitter at
a time) and against the simulator's own link outcomes."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cv2x_marl.config import from_dict, preset
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.ground_truth import MoverLinks, SnapshotLinks, pair_geometry, row_index_table
from cv2x_marl.sim.road import Road

CASES: dict[str, tuple[str, dict[str, Any], str]] = {
    "paper-nlos": ("paper", {}, "snapshot"),
    "paper-inband": ("paper", {"link": {"inband_emission_db": -25.0}}, "snapshot"),
    "paper-threshold": ("paper", {"link": {"model": "threshold"}}, "snapshot"),
    "paper-sensitivity": ("paper", {"radio": {"sensitivity_dbm": -95.0}}, "snapshot"),
    "paper-geometry-los": ("paper", {}, "geometry"),
    "paper-always-los": ("paper", {"channel": {"los": "always"}}, "always"),  # interferers LOS too
    "paper-power-law": ("paper", {"channel": {"pathloss": "power_law"}}, "snapshot"),
    "highway-wrap-range": ("highway", {"sim": {"warmup_subframes": 300}}, "snapshot"),
}


@pytest.mark.kernel_equality
@pytest.mark.parametrize("case", list(CASES))
def test_snapshot_links_match_mover_links_when_one_vehicle_moves(case: str) -> None:
    name, over, truth_los = CASES[case]
    cfg = from_dict({"sim": {"warmup_subframes": 500}, **over}, preset(name))
    snap = Simulator(cfg).reset(seed=5)
    sl = SnapshotLinks(cfg, snap, truth_los)
    ref = SnapshotLinks(cfg, snap, truth_los, compiled=False)
    assert sl.compiled == (case not in ("paper-geometry-los", "paper-power-law")) and not ref.compiled
    rng = np.random.default_rng(0)
    n = snap.positions_m.shape[0]
    everyone = snap.positions_m + rng.uniform(-30.0, 30.0, size=(n, 2))  # all vehicles moved
    p_fast, geo = sl.evaluate(everyone)
    p_ref, geo_ref = ref.evaluate(everyone)
    np.testing.assert_allclose(p_fast, p_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(geo.disp_m, geo_ref.disp_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(geo.dist2_m2, geo_ref.dist2_m2, rtol=1e-12, atol=1e-9)
    assert (p_fast > 0).sum() > n
    for mover in (0, 3, n - 1):
        ml = MoverLinks.from_snapshots(cfg, [snap], [mover], truth_los)
        moved = ml.start_m + rng.uniform(-20.0, 20.0, size=(1, 2))
        pos = snap.positions_m.copy()
        pos[mover] = moved[0]
        # MoverLinks fixes the target set at the start (range included); compare on it
        p_sl = np.where(ml.target[0], sl.success(pos)[mover], 0.0)
        np.testing.assert_allclose(p_sl, ml.success(moved)[0], rtol=1e-9, atol=1e-12)
        # ... and the target set itself is the same at the start positions
        assert np.array_equal(sl.success(snap.positions_m)[mover] > 0, ml.success(ml.start_m)[0] > 0)


def test_highway_links_wrap_round_the_road() -> None:
    cfg = preset("highway")  # 2 km torus, 1 km cut-off: links are kept by their short-way-round distance
    snap = Simulator(from_dict({"sim": {"warmup_subframes": 300}}, cfg)).reset(seed=1)
    sl = SnapshotLinks(cfg, snap)
    pos = snap.positions_m
    geo = sl.geometry(pos)
    assert np.abs(geo.disp_m[0]).max() <= 1000.0 + 1e-9
    off = ~np.eye(pos.shape[0], dtype=bool)
    in_range = np.sqrt(geo.dist2_m2) <= 1000.0
    dbm = sl.rx_dbm(pos)
    assert sl.compiled and (sl.success(pos)[~in_range] == 0.0).all()
    assert np.isfinite(dbm[off & in_range]).all() and np.isneginf(dbm[~in_range]).all()
    plain = np.hypot(*(pos[None, :, :] - pos[:, None, :]).transpose(2, 0, 1))
    assert (in_range & (plain > 1500.0)).sum() > 100  # the far ends of the road hear each other


def test_pair_geometry_is_the_displacement_table() -> None:
    pos = np.array([[0.0, 0.0], [3.0, 4.0], [-1990.0, 2.0]])
    geo = pair_geometry(pos)
    assert geo.disp_m[:, 0, 1].tolist() == [3.0, 4.0] and geo.disp_m[:, 1, 0].tolist() == [-3.0, -4.0]
    assert geo.dist2_m2[0, 1] == 25.0 and geo.dist2_m2[1, 1] == 0.0
    road = Road.from_config(preset("highway").road)  # 2,000 m long: x wraps, y does not
    wrapped = pair_geometry(pos, road)
    assert wrapped.disp_m[:, 0, 2].tolist() == [10.0, 2.0] and wrapped.disp_m[:, 2, 0].tolist() == [-10.0, -2.0]


@pytest.mark.kernel_equality
@pytest.mark.parametrize("name", ["paper", "highway-legacy"])
def test_snapshot_links_match_the_simulators_own_links(name: str) -> None:
    """Every link the simulator decodes in the period after the snapshot, wrap-around included."""
    cfg = from_dict({"sim": {"warmup_subframes": 300}}, preset(name))
    sim = Simulator(cfg)
    snap = sim.reset(seed=4)
    links = sim.run(cfg.traffic.rri_ms).links
    assert links is not None
    ok = links["cause"] != 1  # half-duplex losses are not targets
    for compiled in (True, False):
        p = SnapshotLinks(cfg, snap, compiled=compiled).success(snap.positions_m)
        np.testing.assert_allclose(p[links["tx"][ok], links["rx"][ok]], links["p_success"][ok], rtol=1e-9, atol=1e-12)
    n = snap.positions_m.shape[0]
    assert ok.sum() > 0.8 * n * (n - 1)  # nearly every ordered pair is a decoded link


def test_wrong_vehicle_count_is_rejected() -> None:
    cfg = from_dict({"sim": {"warmup_subframes": 100}}, preset("paper"))
    snap = Simulator(cfg).reset(seed=0)
    for compiled in (True, False):
        sl = SnapshotLinks(cfg, snap, compiled=compiled)
        for bad in (snap.positions_m[:18], np.zeros((51, 2)), snap.positions_m.ravel()):
            with pytest.raises(ValueError, match=r"positions_m must have shape \(21, 2\)"):
                sl.success(bad)


def test_row_index_table() -> None:
    mask = np.array([[False, True, False, True], [False, False, False, False], [True, True, True, False]])
    assert row_index_table(mask).tolist() == [[1, 3, -1], [-1, -1, -1], [0, 1, 2]]
    assert row_index_table(np.zeros((2, 2), bool)).tolist() == [[-1], [-1]]
