"""Corridor scale (issue 13): sparse pair state with a cut-off, no N x N arrays, memory estimate."""

from __future__ import annotations

import copy
import tracemalloc
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from cv2x_marl.config import apply_overrides, preset
from cv2x_marl.sim import channel, memory
from cv2x_marl.sim.memory import ENV_LIMIT, estimate_memory_bytes, uses_sparse_state
from cv2x_marl.sim.simulator import Simulator
from cv2x_marl.sim.snapshot import LazySnapshot


@pytest.fixture(autouse=True)
def _no_env_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_LIMIT, raising=False)


def _small_sparse(monkeypatch: pytest.MonkeyPatch) -> None:
    """Sparse pair state from 2 vehicles on (the threshold is read at each Simulator.__init__)."""
    monkeypatch.setattr(memory, "SPARSE_STATE_MIN_VEHICLES", 2)


@pytest.mark.parametrize("correlation", ["travelled", "pair_distance"])
def test_sparse_shadowing_equals_dense_given_the_same_initial_draws(correlation: str) -> None:
    """All pairs read every period (none leaves or enters): the only difference is where the initial
    Z comes from (drawn at the first read, in pair order, before the update's normals)."""
    n = 7
    a, b = np.triu_indices(n, 1)
    a, b = a.astype(np.int64), b.astype(np.int64)
    rng_sparse = np.random.default_rng(5)
    sparse = channel.SparseShadowing(n, 25.0, rng_sparse, correlation)
    rng_dense = copy.deepcopy(rng_sparse)
    z0 = rng_dense.standard_normal(a.shape[0])  # what the sparse state draws at the first read
    dense = channel.Shadowing(n, 25.0, np.random.default_rng(99), correlation)
    dense._z[a, b] = dense._z[b, a] = z0
    dense._rng = rng_dense  # from here both draw the update normals from the same stream position
    step = np.random.default_rng(1)
    odo = np.zeros(n)
    dist = 100.0 + 50.0 * step.random(a.shape[0])
    for _ in range(6):
        zs = sparse.sample(a, b, odo, dist)
        zd = dense.sample(a, b, odo, dist)
        np.testing.assert_array_equal(zs, zd)
        odo = odo + 10.0 * step.random(n)
        dist = dist + 5.0 * step.standard_normal(a.shape[0])
    assert sparse.n_pairs == a.shape[0]


def test_sparse_shadowing_forgets_a_pair_that_leaves_range() -> None:
    n = 4
    sparse = channel.SparseShadowing(n, 25.0, np.random.default_rng(3))
    odo = np.zeros(n)
    a, b = np.array([0, 1, 2]), np.array([1, 3, 3])
    first = sparse.sample(a, b, odo)
    kept = sparse.sample(a[:2], b[:2], odo)  # (2, 3) out of range: dropped
    np.testing.assert_array_equal(kept, first[:2])  # nothing travelled: rho = 1, Z kept exactly
    assert sparse.n_pairs == 2
    rng = copy.deepcopy(sparse._rng)
    back = sparse.sample(a, b, odo)
    fresh = rng.standard_normal(1)  # one new pair: its initial Z, then the update normals (rho = 1)
    np.testing.assert_array_equal(back, [first[0], first[1], fresh[0]])
    assert back[2] != first[2]


def _cfg(extra: list[str]) -> object:
    # 1.5 km ring, 1 km cut-off: every pair is within range (half the ring plus the lanes' width)
    return apply_overrides(
        preset("highway"),
        ["road.length_m=1500", "sim.warmup_subframes=200", "link.max_range_m=1000", *extra],
    )


@pytest.mark.parametrize("extra", [[], ["channel.shadowing_correlation=pair_distance"]])
def test_sparse_state_gives_the_dense_links_without_shadowing(
    monkeypatch: pytest.MonkeyPatch, extra: list[str]
) -> None:
    """With the shadowing off the sparse and the dense state run the same simulation, link by link."""
    cfg = _cfg(["channel.shadowing_std_db=0", "channel.shadowing_nlos_std_db=0", *extra])
    dense = Simulator(cfg)  # type: ignore[arg-type]
    dense.reset(4)
    ref = dense.run(300).links
    _small_sparse(monkeypatch)
    sparse = Simulator(cfg)  # type: ignore[arg-type]
    assert sparse.sparse_state and not dense.sparse_state
    sparse.reset(4)
    got = sparse.run(300).links
    assert ref is not None and got is not None and ref["tx"].shape[0] > 0
    for key in ref:
        np.testing.assert_array_equal(got[key], ref[key], err_msg=key)


def test_sparse_state_keeps_the_shadowing_law(monkeypatch: pytest.MonkeyPatch) -> None:
    """With shadowing: the pairs' large-scale loss minus the path loss is sigma x Z of the sparse state."""
    _small_sparse(monkeypatch)
    sim = Simulator(_cfg([]))  # type: ignore[arg-type]
    snap = sim.reset(2)
    assert isinstance(snap, LazySnapshot) and "los" not in vars(snap)
    geo = sim._period_geometry()
    h = geo.rx.shape[0] // 2
    assert sim.shadowing.n_pairs == h == sim.n * (sim.n - 1) // 2  # every pair in range
    sh = snap.shadowing_db[geo.rx[:h], geo.tx[:h]]
    np.testing.assert_allclose(sh, 3.0 * sim.shadowing._z, atol=1e-9)  # highway: LOS, sigma 3 dB
    assert abs(np.mean(sim.shadowing._z)) < 0.1 and 0.9 < np.std(sim.shadowing._z) < 1.1


def test_lazy_snapshot_equals_the_eager_one(monkeypatch: pytest.MonkeyPatch) -> None:
    _small_sparse(monkeypatch)
    sim = Simulator(apply_overrides(preset("highway"), ["road.length_m=3000", "sim.warmup_subframes=300"]))
    sim.reset(1)
    lazy = sim.snapshot()
    sim.sparse_state = False
    eager = sim.snapshot()
    assert isinstance(lazy, LazySnapshot) and not isinstance(eager, LazySnapshot)
    np.testing.assert_array_equal(lazy.shadowing_db, eager.shadowing_db)
    np.testing.assert_array_equal(lazy.los, eager.los)
    np.testing.assert_array_equal(lazy.positions_m, eager.positions_m)
    assert lazy.los is lazy.los  # built once
    assert lazy.shadowing_db.shape == (sim.n, sim.n) and np.any(lazy.shadowing_db != 0)


def test_sparse_mean_power_lookup_equals_the_dense_one(monkeypatch: pytest.MonkeyPatch) -> None:
    _small_sparse(monkeypatch)
    cfg = apply_overrides(
        preset("highway-legacy"),
        ["road.length_m=4000", "link.max_range_m=800", "channel.fading=rayleigh", "link.model=rayleigh"],
    )
    sim = Simulator(cfg)
    sim.reset(3, warmup_subframes=150)
    res = sim.run(150)  # link.model=rayleigh uses the lookup
    assert 0.0 < res.metrics.summary()["prr_mean"] <= 1.0
    rng = np.random.default_rng(0)
    rx, tx = rng.integers(0, sim.n, 5000), rng.integers(0, sim.n, 5000)
    geo = sim._period_geometry()
    sparse = sim.chunks._mean_power_lookup(geo, rx, tx)
    sim.chunks.sparse_state = False
    dense = sim.chunks._mean_power_lookup(geo, rx, tx)
    np.testing.assert_array_equal(sparse, dense)
    assert np.any(sparse == 0.0) and np.any(sparse > 0.0)  # pairs beyond the cut-off, and within


def _arrays(obj: object) -> dict[str, np.ndarray]:
    return {k: v for k, v in vars(obj).items() if isinstance(v, np.ndarray)}


def test_nothing_n_by_n_with_a_cut_off() -> None:
    """3,000 vehicles on a 30 km ring with the preset's 1 km cut-off: no array with N^2 / 2 elements
    or two axes of length N after reset, and the snapshot's matrices only when read."""
    cfg = apply_overrides(preset("highway"), ["road.length_m=30000", "sim.warmup_subframes=200"])
    n = cfg.n_vehicles
    assert n == 3000 and uses_sparse_state(cfg)
    sim = Simulator(cfg)
    assert sim.pair_list.all_pairs is None
    snap = sim.reset(0)
    assert isinstance(snap, LazySnapshot) and "los" not in vars(snap) and "shadowing_db" not in vars(snap)
    geo = sim._period_geometry()
    found = {**_arrays(sim), **{f"shadowing.{k}": v for k, v in _arrays(sim.shadowing).items()}}
    for part in ("scheduler", "chunks", "pair_list"):
        found.update({f"{part}.{k}": v for k, v in _arrays(getattr(sim, part)).items()})
    found.update({f"geometry.{k}": v for k, v in _arrays(geo).items()})
    found.update({f"snapshot.{k}": v for k, v in _arrays(snap).items()})
    for name, arr in found.items():
        assert sum(d == n for d in arr.shape) <= 1, (name, arr.shape)
        # N x resources (x periods): linear in N
        if name not in (
            "scheduler.rssi_ring",
            "scheduler.period_rssi_mw",
            "scheduler.period_sci_mw",
            "scheduler.prev_sci_mw",
            "chunks.total",
            "chunks.total_slot",
        ):
            assert arr.size < n * (n - 1) / 8, (name, arr.shape)
    # ~7 % of the pairs in range (2 km of a 30 km ring)
    assert 0.05 < sim.shadowing.n_pairs / (n * (n - 1) / 2) < 0.08
    assert sim.shadowing.nbytes == 24 * sim.shadowing.n_pairs
    assert snap.los.shape == snap.shadowing_db.shape == (n, n)  # on demand


def test_sparse_estimate_against_measured_peak(monkeypatch: pytest.MonkeyPatch) -> None:
    """Estimate vs tracemalloc peak of Simulator + reset + run with the sparse state (3,000 vehicles)."""
    warm = Simulator(apply_overrides(preset("paper"), ["sim.warmup_subframes=0"]))  # compiled kernels loaded
    warm.reset(0)
    warm.run(100)
    del warm
    cfg = apply_overrides(
        preset("highway"), ["road.length_m=30000", "sim.warmup_subframes=200", "metrics.record_links=false"]
    )
    est = estimate_memory_bytes(cfg, 200)
    dense_shadowing = 16 * cfg.n_vehicles**2
    assert est["shadowing"] < dense_shadowing / 3 and est["pair_index"] == 0
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        sim = Simulator(cfg)
        snap = sim.reset(1)
        sim.run(200)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert isinstance(snap, LazySnapshot)
    monkeypatch.setattr(memory, "SPARSE_STATE_MIN_VEHICLES", 10**9)
    dense_total = estimate_memory_bytes(cfg, 200)["total"]  # the same run with the dense state
    assert peak < dense_total / 1.5, (peak, dense_total)
    assert 0.9 * peak <= est["total"] <= 1.5 * peak, (est["total"], peak)


@pytest.mark.parametrize(
    "extra",
    [
        [],
        ["link.per_interpolation=log", "radio.sensitivity_dbm=-95", "sps.reservation_signalling=standard"],
        ["link.model=threshold", "traffic.synchronous=true"],
    ],
)
def test_compiled_period_equals_the_numpy_period(
    monkeypatch: pytest.MonkeyPatch, extra: list[str], compiled_and_numpy: Callable[..., Any]
) -> None:
    """The compiled chunk (sparse state, no links table) against the numpy chunk on the same state
    (tests/sim/conftest.py: P to 1e-12, everything else exact)."""
    _small_sparse(monkeypatch)
    cfg = apply_overrides(
        preset("highway"),
        ["road.length_m=6000", "link.max_range_m=1500", "metrics.record_links=false", *extra],
    )
    a, _, _, _ = compiled_and_numpy(cfg, 7, 250, 440)  # half periods: chunks of part of a period
    assert a.sparse_state


@pytest.mark.parametrize(
    ("box", "range_m"),
    [((3000.0, np.inf), 1000.0), ((1500.0, np.inf), 1000.0), ((np.inf, np.inf), 700.0), ((2000.0, 2000.0), 300.0)],
)
def test_pair_sweep_equals_the_kd_tree(box: tuple[float, float], range_m: float) -> None:
    """kernels.pairs_within_range: the KD-tree's pairs (query_pairs), in (i, j) order."""
    from scipy.spatial import cKDTree

    from cv2x_marl.sim import kernels

    rng = np.random.default_rng(1)
    n = 600
    lx = box[0] if np.isfinite(box[0]) else 6000.0
    ly = box[1] if np.isfinite(box[1]) else 20.0
    pos = np.c_[rng.random(n) * lx, rng.random(n) * ly]
    b = np.array(box)
    if np.isfinite(b[0]):
        bb = np.where(np.isfinite(b), b, 1e12)
        tree = cKDTree(np.mod(pos, bb), boxsize=bb)
    else:
        tree = cKDTree(pos)
    p = tree.query_pairs(range_m, output_type="ndarray").astype(np.int64)
    p.sort(axis=1)
    p = p[np.lexsort((p[:, 1], p[:, 0]))]
    i, j = kernels.pairs_within_range(pos, b, range_m)
    assert p.shape[0] > 0
    np.testing.assert_array_equal(i, p[:, 0])
    np.testing.assert_array_equal(j, p[:, 1])


def test_pair_state_key_chooses_the_state() -> None:
    from cv2x_marl.config import ConfigError, apply_overrides, preset

    hw = preset("highway")  # link.max_range_m is set there
    assert hw.link.max_range_m is not None and hw.link.pair_state == "auto"
    assert not uses_sparse_state(hw)  # 200 vehicles: below the auto threshold
    assert uses_sparse_state(apply_overrides(hw, ["link.pair_state=sparse"]))
    big = apply_overrides(hw, ["vehicles.density_veh_per_m=null", "vehicles.n_vehicles=3000"])
    assert uses_sparse_state(big) and not uses_sparse_state(apply_overrides(big, ["link.pair_state=dense"]))
    no_cut = apply_overrides(preset("paper"), ["link.pair_state=sparse"])
    assert not uses_sparse_state(no_cut)  # without a cut-off every pair is in range: dense
    with pytest.raises(ConfigError, match=r"link.pair_state.*auto \| dense \| sparse"):
        apply_overrides(hw, ["link.pair_state=compact"])
    sim = Simulator(apply_overrides(hw, ["link.pair_state=sparse", "sim.warmup_subframes=100"]))
    assert isinstance(sim.reset(0), LazySnapshot)
