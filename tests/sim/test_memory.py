"""Memory estimate and up-front refusal (cv2x_marl.sim.memory)."""

from __future__ import annotations

import time
import tracemalloc

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.sim import memory
from cv2x_marl.sim.memory import ENV_LIMIT, LINK_ROW_BYTES, check_memory, estimate_memory_bytes
from cv2x_marl.sim.simulator import Simulator


@pytest.fixture(autouse=True)
def _no_env_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_LIMIT, raising=False)


def test_link_row_bytes_match_the_simulator_columns() -> None:
    sim = Simulator(apply_overrides(preset("paper"), ["sim.warmup_subframes=0"]))
    sim.reset(1)
    links = sim.run(100).links
    assert links is not None
    assert sum(v.dtype.itemsize for v in links.values()) == LINK_ROW_BYTES


def test_dense_parts_by_hand_and_growth_as_n_squared() -> None:
    n = 1000
    cfg = apply_overrides(preset("paper"), [f"vehicles.n_vehicles={n}", "metrics.record_links=false"])
    est = estimate_memory_bytes(cfg)
    # Shadowing.__init__: draw w, triu(w, 1) (its .T sum reuses it) and triu(w, 1) again, float64 N x N,
    # and the bool triu mask; then _z and _last_odo (16 N^2) stay
    assert est["shadowing"] == 3 * 8 * n * n + n * n == 25_000_000
    # Simulator.pair_list.all_pairs: two int64 per unordered pair, and their astype copies while built
    assert est["pair_index"] == 2 * 2 * 8 * (n * (n - 1) // 2) == 15_984_000
    assert est["snapshot"] >= 9 * n * n  # Snapshot.los (bool) + shadowing_db (float64)
    assert est["co_channel"] == est["links_table"] == 0
    big = estimate_memory_bytes(apply_overrides(cfg, [f"vehicles.n_vehicles={2 * n}"]))
    for key in ("shadowing", "pair_index", "pair_geometry"):
        assert 3.99 < big[key] / est[key] < 4.01, key
    # the compiled period (no links table): the chunk's power per receiver and resource (float64 [N, R]), the
    # kernel's per-link uniform / P (8 B) and cause (1 B) while it runs, and last_links (tx, rx, p: 8 B,
    # cause: 1 B per link, N (N - 1) links)
    n_res = cfg.traffic.rri_ms * cfg.sps.n_subchannels  # resources per period: 1 ms subframes x subchannels
    assert est["period_temporaries"] == 8 * n * n_res + (9 + 25) * n * (n - 1)
    assert 3.8 < big["total"] / est["total"] < 4.0  # plus terms linear in N (sensing window)
    assert est["total"] >= max(v for k, v in est.items() if k != "total")


def test_density_resolves_the_vehicle_count_and_range_limits_pairs() -> None:
    cfg = apply_overrides(preset("highway"), ["road.length_m=20000"])
    assert cfg.n_vehicles == 2000
    est = estimate_memory_bytes(cfg)
    assert est["shadowing"] == 25 * 2000**2
    # link.max_range_m = 1000 m of a 20 km ring: 10 % of the pairs in range (lanes add a little)
    all_pairs = estimate_memory_bytes(apply_overrides(cfg, ["link.max_range_m=null"]))
    assert 0.1 < est["pair_geometry"] / all_pairs["pair_geometry"] < 0.105


def test_links_table_grows_with_the_run_length() -> None:
    cfg = apply_overrides(preset("paper"), ["vehicles.n_vehicles=200"])
    one, two = estimate_memory_bytes(cfg, 1000), estimate_memory_bytes(cfg, 2000)
    assert two["links_table"] == pytest.approx(2 * one["links_table"], rel=1e-9)
    # 200 x 199 links per 100-subframe period, 10 periods, lists and their concatenation
    assert one["links_table"] == 2 * LINK_ROW_BYTES * 200 * 199 * 10
    none = estimate_memory_bytes(cfg, 0)
    assert none["links_table"] == none["co_channel"] == 0
    assert estimate_memory_bytes(cfg)["links_table"] > two["links_table"]  # sim.n_subframes = 10240


def _measured_peak(cfg_name: str, overrides: list[str], n_subframes: int) -> tuple[int, int]:
    """(tracemalloc peak of Simulator + reset + run, estimate), bytes."""
    cfg = apply_overrides(preset(cfg_name), overrides)
    warm = Simulator(cfg)  # the kernels this scenario uses (warm-up and run) compiled or loaded first
    warm.reset(0)
    warm.run(150)
    del warm
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        sim = Simulator(cfg)
        snap = sim.reset(1)
        result = sim.run(n_subframes)
        peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert snap.shadowing_db.shape == (cfg.n_vehicles, cfg.n_vehicles)
    assert (result.links is not None) == cfg.metrics.record_links
    return peak, estimate_memory_bytes(cfg, n_subframes)["total"]


@pytest.mark.parametrize(
    ("cfg_name", "overrides", "n_subframes"),
    [
        # 400 vehicles on a 4 km ring, 1 km range: links table and co-channel terms (measured ~80 MB)
        ("highway", ["road.length_m=4000", "sim.warmup_subframes=200"], 300),
        # 300 vehicles, all pairs, no links table: dense state and per-period pair arrays (~25 MB)
        ("paper", ["vehicles.n_vehicles=300", "sim.warmup_subframes=200", "metrics.record_links=false"], 300),
    ],
)
def test_estimate_against_measured_peak(cfg_name: str, overrides: list[str], n_subframes: int) -> None:
    peak, est = _measured_peak(cfg_name, overrides, n_subframes)
    # observed est / peak: 1.00-1.18 over 20 configurations (grid, highway, rayleigh, in-band, ranges)
    assert 0.9 * peak <= est <= 1.5 * peak, (est, peak)


def _refuse(cfg_overrides: tuple[str, list[str]], limit: int | None = None) -> str:
    cfg = apply_overrides(preset(cfg_overrides[0]), cfg_overrides[1])
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(ConfigError) as info:
            check_memory(cfg, limit_bytes=limit)
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert elapsed < 0.5
    assert peak < 1_000_000  # refused without allocating anything sizeable
    return str(info.value)


def test_refuses_the_documented_maximum_without_allocating() -> None:
    msg = _refuse(("paper", ["vehicles.n_vehicles=100000"]))  # limit: MemAvailable
    for part in ("100000 vehicles", "vehicles.n_vehicles", "metrics.record_links=false", "sim.n_subframes", ENV_LIMIT):
        assert part in msg, part
    assert "GB" in msg and "largest parts: co_channel" in msg
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"vehicles\.n_vehicles"):
        Simulator(apply_overrides(preset("paper"), ["vehicles.n_vehicles=100000"]))
    assert time.perf_counter() - t0 < 0.5


def test_refuses_density_times_length() -> None:
    msg = _refuse(("highway", ["road.length_m=500000"]), limit=16 * 10**9)
    for part in ("50000 vehicles", "vehicles.density_veh_per_m", "road.length_m", "limit 16 GB", ENV_LIMIT):
        assert part in msg, part
    # the suggested road length does fit
    fit = float(msg.split("road.length_m <= ")[1].split()[0])
    check_memory(apply_overrides(preset("highway"), [f"road.length_m={fit}"]), limit_bytes=16 * 10**9)


def test_env_limit_refuses_a_normal_config(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV_LIMIT, "0.000001")  # 1 kB
    with pytest.raises(ConfigError, match=ENV_LIMIT) as info:
        check_memory(preset("paper"))
    assert "21 vehicles" in str(info.value)
    with pytest.raises(ConfigError, match=ENV_LIMIT):
        Simulator(preset("paper"))
    monkeypatch.setenv(ENV_LIMIT, "64")
    assert check_memory(apply_overrides(preset("paper"), ["vehicles.n_vehicles=500"]))["total"] < 64e9


@pytest.mark.parametrize("value", ["lots", "-1", "0", "nan", "inf", "8GB"])
def test_bad_env_value_is_named(monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv(ENV_LIMIT, value)
    with pytest.raises(ConfigError, match=ENV_LIMIT):
        check_memory(preset("paper"))


def test_defaults_pass_cheaply(monkeypatch: pytest.MonkeyPatch) -> None:
    est = check_memory(preset("paper"))
    assert 0 < est["total"] < memory.QUICK_PASS_BYTES

    def no_meminfo() -> int:
        raise AssertionError("small configurations must not read /proc/meminfo")

    cfg = preset("paper")
    with monkeypatch.context() as m:
        m.setattr(memory, "available_memory_bytes", no_meminfo)
        t0 = time.perf_counter()
        for _ in range(1000):
            check_memory(cfg)
        assert (time.perf_counter() - t0) / 1000 < 200e-6  # measured ~15 us per call
    assert check_memory(preset("highway"))["total"] < 1e9  # 200 vehicles, 5000-subframe links table


def test_a_config_that_passed_is_not_checked_against_available_memory_again(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []

    def available() -> int:
        calls.append(1)
        return 10**12

    monkeypatch.setattr(memory, "_PASSED", set())
    monkeypatch.setattr(memory, "available_memory_bytes", available)
    cfg = apply_overrides(preset("paper"), ["vehicles.n_vehicles=2000"])  # ~60 GB with the links table
    check_memory(cfg)
    check_memory(cfg)
    assert len(calls) == 1
    check_memory(cfg, n_subframes=100)  # another run length: checked
    assert len(calls) == 2
    monkeypatch.setenv(ENV_LIMIT, "8")  # an explicit limit always applies
    with pytest.raises(ConfigError, match="limit 8 GB"):
        check_memory(cfg)


def test_available_memory() -> None:
    avail = memory.available_memory_bytes()
    assert isinstance(avail, int) and avail > 0
    assert np.isfinite(float(avail))


def test_open_population_arrays_are_sized_by_capacity() -> None:
    """Review of issue 14: with ``vehicles.population=open`` the per-vehicle arrays have
    ``vehicles.capacity`` slots (the dense shadowing and snapshot state, the sensing window) while
    the pairs are those of the vehicles present (``n_vehicles`` on average)."""
    base = ["vehicles.mobility=trace", "vehicles.trace_file=x.xml", "vehicles.population=open"]
    cfg = apply_overrides(preset("paper"), [*base, "vehicles.capacity=1000", "metrics.record_links=false"])
    fixed = apply_overrides(preset("paper"), ["metrics.record_links=false"])
    est, ref = estimate_memory_bytes(cfg), estimate_memory_bytes(fixed)
    assert est["shadowing"] == 25 * 1000**2  # as test_dense_parts_by_hand, for the 1,000 slots
    assert est["pair_geometry"] == ref["pair_geometry"]  # the 21 vehicles present
    assert est["sensing"] > 40 * ref["sensing"]
    huge = apply_overrides(cfg, ["vehicles.capacity=90000"])
    with pytest.raises(ConfigError, match=r"lower vehicles\.capacity \(the 90000 vehicle slots"):
        check_memory(huge, limit_bytes=2 * 2**30)
