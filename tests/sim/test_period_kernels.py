"""The compiled period (kernels.period_chunk, pair_geometry, shadowing_update_dense, received_powers)
against the numpy formulas they replace, value by value, and the whole compiled period against the
numpy period on dense-state scenarios (the sparse state: tests/sim/test_scale.py)."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cv2x_marl.config import PER_CURVES, apply_overrides, preset
from cv2x_marl.sim import Simulator, kernels
from cv2x_marl.sim.chunk import ChunkRunner
from cv2x_marl.sim.link import load_per_curve, load_pscch_curve

# every test here is rerun by `make test-portable` (numpy's baseline SIMD paths, numba's generic target).
# Kernel against numpy: exact where both sides run the same arithmetic (libm's log10 / pow / exp through
# _db or Python's math on the reference side, np.interp, sqrt, hypot: numpy's is the C library's too,
# integer outputs); to tests/sim/conftest.py's tolerances where numpy's own exp / log10 / power (SIMD
# versions on some CPUs) meet the kernel's libm ones.
pytestmark = pytest.mark.kernel_equality


def _db(x: np.ndarray) -> np.ndarray:
    """10 log10 with libm's logarithm, the one the kernels take (numpy may use a SIMD one)."""
    return np.array([10.0 * math.log10(v) if v > 0 else -math.inf for v in np.atleast_1d(x)])


def test_db_below_agrees_with_the_logarithm_at_and_around_the_threshold() -> None:
    """The linear pre-test decides only outside the margin; at the threshold the logarithm decides."""
    rng = np.random.default_rng(3)
    for threshold_db in (-2.0, 0.0, 12.0, -95.0, 7.3):
        lin = 10.0 ** (threshold_db / 10.0)
        # exactly at, a few ulps around, inside the margin, and far on either side
        ulps = lin + np.arange(-40, 41) * np.spacing(lin)
        near = lin * (1.0 + rng.uniform(-3e-9, 3e-9, 400))
        far = lin * 10.0 ** rng.uniform(-3, 3, 400)
        x = np.concatenate([[lin], ulps, near, far])
        got = np.array([kernels.db_below(float(v), lin, threshold_db) for v in x])
        np.testing.assert_array_equal(got, _db(x) < threshold_db)
    # a value whose dB is exactly the threshold is not below it (10 log10(100) = 20 exactly)
    assert not kernels.db_below(100.0, 100.0, 20.0)
    v = float(np.nextafter(100.0, 0.0))  # one ulp below: its dB value rounds to 20.0, not below either
    assert kernels.db_below(v, 100.0, 20.0) == bool(10.0 * math.log10(v) < 20.0) is False
    assert kernels.db_below(99.9999, 100.0, 20.0)


@pytest.mark.parametrize("model", [kernels.MODEL_PER_TABLE, kernels.MODEL_PER_TABLE_LOG, kernels.MODEL_THRESHOLD])
def test_success_of_ratio_equals_the_table_on_the_db_value(model: int) -> None:
    """P from the linear SINR equals _per_success on numpy's dB value, bit for bit, including the
    table's ends, the ulps around them, far outside, and 0 / NaN."""
    sinr_db = np.array([-2.0, 0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0])
    per = np.array([1.0, 0.9, 0.7, 0.3, 0.09, 0.02, 0.002, 0.001])
    lo, hi = 10.0 ** (sinr_db[0] / 10.0), 10.0 ** (sinr_db[-1] / 10.0)
    thr_db = 3.0
    thr = 10.0 ** (thr_db / 10.0)
    rng = np.random.default_rng(5)
    ends = [v + k * np.spacing(v) for v in (lo, hi, thr) for k in range(-20, 21)]
    x = np.concatenate([ends, 10.0 ** rng.uniform(-3.0, 2.0, 5000), 10.0 ** (sinr_db / 10.0), [0.0, 1e-300, 1e300]])
    log_domain = model == kernels.MODEL_PER_TABLE_LOG
    for v in x:
        got = kernels.success_of_ratio(float(v), model, sinr_db, per, lo, hi, thr_db, thr)
        d = float(_db(np.array([v]))[0])
        if model == kernels.MODEL_THRESHOLD:
            want = 1.0 if d >= thr_db else 0.0
        else:
            want = kernels.per_success(d, sinr_db, per, log_domain)
        assert got == want, (v, d, got, want)
    assert kernels.success_of_ratio(math.nan, kernels.MODEL_PER_TABLE, sinr_db, per, lo, hi, thr_db, thr) == 0.0


@pytest.mark.parametrize("offset_db", [0.0, -6.0, 3.0])
def test_sci_probability_equals_the_pscch_curve(offset_db: float, tolerances: Any) -> None:
    """The kernel's PSCCH decoding probability (shortcut outside the curve) equals PscchCurve's arithmetic
    bit for bit when both take libm's log10 and pow, at SINRs across and beyond the curve, a few ulps
    either side of its ends, 0 and NaN; and PscchCurve itself (numpy's log10 / power, SIMD on some CPUs)
    to the tolerance those two calls allow."""
    curve = load_pscch_curve()
    lin = np.power(10.0, curve.sinr_db / 10.0)
    off = 10.0 ** (offset_db / 10.0)
    lo, hi = lin[0] / off, lin[-1] / off
    ends = [np.nextafter(e, d, dtype=np.float64) for e in (lo, hi) for d in (0.0, np.inf)] + [lo, hi]
    ends += [e * f for e in (lo, hi) for f in (1 - 1e-9, 1 + 1e-9, 1 - 2e-9, 1 + 2e-9)]
    ratios = np.concatenate([np.power(10.0, np.linspace(-4, 3, 2001)), np.array(ends), [0.0, np.inf]])
    got = np.array([kernels.sci_probability(float(r), offset_db, lin, curve.bler, lo, hi) for r in ratios])
    # bit for bit: decoding_probability's arithmetic with the kernel's (libm's) log10 and pow, so the
    # shortcuts are checked to give exactly what the arithmetic would
    x = _db(ratios) + offset_db
    bler = np.interp(np.array([10.0 ** (v / 10.0) for v in x]), lin, curve.bler, left=1.0, right=curve.bler[-1])
    np.testing.assert_array_equal(got, 1.0 - bler)
    # PscchCurve with numpy's log10 and power: the dB value moves by 10 |log10(r)| 4 ulp (+ its rounding),
    # 10^(x/10) by ln(10)/10 of that relative, + 4 ulp, and 1 - BLER by at most the curve's steepest
    # |dBLER / d ln(lin)| (1.73) times that: < 1e-14 here, compared to p_atol (1e-13)
    with np.errstate(divide="ignore"):  # log10(0) = -inf: probability 0
        want = curve.decoding_probability(10.0 * np.log10(ratios) + offset_db)
    np.testing.assert_allclose(got, want, rtol=0.0, atol=tolerances.p_atol)
    assert kernels.sci_probability(math.nan, offset_db, lin, curve.bler, lo, hi) == 0.0
    assert want.min() == 0.0 and want.max() == 1.0 - curve.bler[-1]  # both shortcuts taken


@pytest.mark.parametrize("interpolation", ["linear", "log"])
def test_success_of_ratio_equals_the_shipped_curve(interpolation: str, tolerances: Any) -> None:
    """On the shipped PER curve, the kernel's P equals :meth:`PerCurve.success` (numpy's np.interp) at the
    dB value of the ratio, over the table and beyond it."""
    curve = load_per_curve(PER_CURVES[0], interpolation)
    lo, hi = 10.0 ** (curve.sinr_db[0] / 10.0), 10.0 ** (curve.sinr_db[-1] / 10.0)
    x = 10.0 ** np.linspace(-1.0, 2.0, 4001)  # -10 to 20 dB
    got = np.array(
        [kernels.success_of_ratio(float(v), curve.kernel_model, curve.sinr_db, curve.per, lo, hi, 0.0, 1.0) for v in x]
    )
    # PerCurve.success's log-domain interpolation takes numpy's log and exp: to the tolerance of P
    np.testing.assert_allclose(got, curve.success(_db(x)), rtol=0.0, atol=tolerances.p_atol)
    assert got[0] == 0.0 and got[-1] == 1.0 - curve.per[-1]


def test_interp_clamped_equals_np_interp() -> None:
    xp = np.array([0.1, 0.5, 1.0, 3.0, 10.0])
    fp = np.array([1.0, 0.8, 0.4, 0.05, 0.0])
    rng = np.random.default_rng(2)
    x = np.concatenate([xp, rng.uniform(0.0, 12.0, 3000), [np.nextafter(0.1, 0.0), np.nextafter(10.0, 11.0), -1.0]])
    want = np.interp(x, xp, fp, left=1.0, right=0.0)
    got = np.array([kernels.interp_clamped(float(v), xp, fp, 1.0, 0.0) for v in x])
    np.testing.assert_array_equal(got, want)
    assert math.isnan(kernels.interp_clamped(math.nan, xp, fp, 1.0, 0.0))


@pytest.mark.parametrize("box", [(3000.0, np.inf), (2000.0, 1500.0), (np.inf, np.inf)])
def test_pair_geometry_equals_numpy(box: tuple[float, float]) -> None:
    rng = np.random.default_rng(11)
    n = 150
    pos = rng.uniform(0.0, 2500.0, (n, 2))
    vel = rng.normal(0.0, 20.0, (n, 2))
    i, j = (a.astype(np.int64) for a in np.triu_indices(n, 1))
    b = np.array(box)
    dx, dy, dist, rel = kernels.pair_geometry(pos, vel, i, j, b)
    disp = pos[j] - pos[i]
    periodic = np.isfinite(b)
    disp[:, periodic] -= b[periodic] * np.round(disp[:, periodic] / b[periodic])  # Road.minimum_image
    np.testing.assert_array_equal(dx, disp[:, 0])
    np.testing.assert_array_equal(dy, disp[:, 1])
    np.testing.assert_array_equal(dist, np.hypot(disp[:, 0], disp[:, 1]))  # both the C library's hypot
    np.testing.assert_array_equal(rel, np.hypot(*(vel[i] - vel[j]).T))
    if periodic[0]:
        assert np.all(np.abs(dx) <= b[0] / 2)
    # a hand-made pair: 100 m ahead across the seam of a 3 km ring, 4 m apart laterally
    p2 = np.array([[2950.0, 2.0], [50.0, 6.0]])
    v2 = np.array([[30.0, 0.0], [-25.0, 0.0]])
    g = kernels.pair_geometry(p2, v2, np.array([0]), np.array([1]), np.array([3000.0, np.inf]))
    assert (g[0][0], g[1][0], g[3][0]) == (100.0, 4.0, 55.0)
    assert g[2][0] == pytest.approx(math.hypot(100.0, 4.0), rel=1e-15)


@pytest.mark.parametrize("pair_distance", [False, True])
def test_shadowing_update_dense_equals_the_numpy_ar1_step(pair_distance: bool, tolerances: Any) -> None:
    rng = np.random.default_rng(4)
    n = 40
    z0 = rng.standard_normal((n, n))
    z0 = np.triu(z0, 1) + np.triu(z0, 1).T
    last0 = rng.uniform(0.0, 300.0, (n, n))
    last0 = np.triu(last0, 1) + np.triu(last0, 1).T
    if pair_distance:
        last0[0, 5] = last0[5, 0] = np.nan  # never read: keeps its Z (rho = 1)
    a, b = (x.astype(np.int64) for x in np.triu_indices(n, 1))
    # travelled: the odometer sum only grows; pair_distance: any new distance
    ref = (
        last0[a, b] + rng.uniform(0.0, 100.0, a.shape[0]) if not pair_distance else rng.uniform(0.0, 400.0, a.shape[0])
    )
    w = rng.standard_normal(a.shape[0])
    dc = 25.0
    # the numpy step (channel.Shadowing.sample before it was compiled)
    ab = a * n + b
    prev = z0.reshape(-1)[ab]
    if pair_distance:
        change = np.abs(ref - last0.reshape(-1)[ab])
        rho = np.exp(-np.where(np.isnan(change), 0.0, change) / dc)
    else:
        rho = np.exp(-(ref - last0.reshape(-1)[ab]) / dc)
    want = rho * prev + np.sqrt(1.0 - rho * rho) * w
    z, last = z0.copy(), last0.copy()
    got = kernels.shadowing_update_dense(z.reshape(-1), last.reshape(-1), a, b, n, ref, w, dc, pair_distance)
    assert np.all(np.isfinite(want))
    # numpy's exp (SIMD on some CPUs) against the kernel's libm exp: the AR(1) step's propagated bound
    assert np.all(np.abs(got - want) <= tolerances.ar1(rho, prev, w)), np.max(np.abs(got - want))
    np.testing.assert_array_equal(z[a, b], got)
    np.testing.assert_array_equal(z[b, a], got)  # symmetric
    np.testing.assert_array_equal(last[a, b], ref)
    np.testing.assert_array_equal(last[b, a], ref)
    if pair_distance:
        k = int(np.flatnonzero((a == 0) & (b == 5))[0])
        assert got[k] == z0[0, 5]  # rho = 1: sqrt(0) * w adds 0


@pytest.mark.parametrize(("shadow", "fading"), [(True, True), (False, True), (True, False), (False, False)])
def test_received_powers_equal_numpy(shadow: bool, fading: bool, tolerances: Any) -> None:
    rng = np.random.default_rng(9)
    p = 500
    pl = rng.uniform(50.0, 130.0, p)
    los = rng.random(p) < 0.6
    z = rng.standard_normal(p) if shadow else np.empty(0)
    gains = rng.standard_exponential(2 * p) if fading else np.empty(0)
    mean, rx = kernels.received_powers(29.0, pl, z, los, 3.0, 4.0, gains)
    want_pl = pl + np.where(los, 3.0, 4.0) * z if shadow else pl
    want_mean = 29.0 - want_pl
    half = np.power(10.0, want_mean / 10.0)
    want_rx = np.concatenate([half, half])
    if fading:
        want_rx = want_rx * gains
    np.testing.assert_array_equal(mean, want_mean)
    # numpy's power (SIMD on some CPUs) against the kernel's libm pow of the same argument: ulps_per_call,
    # and one more for each side's rounding of the product with the fading gain
    np.testing.assert_allclose(rx, want_rx, rtol=(tolerances.ulps_per_call + 1) * tolerances.eps, atol=0.0)
    assert mean[0] == 29.0 - want_pl[0]  # by hand: EIRP minus the shadowed loss


@pytest.mark.parametrize(
    ("name", "extra"),
    [
        ("paper", []),  # Manhattan grid, LOS / NLOS, all pairs
        ("highway", ["road.length_m=2500", "link.per_interpolation=log", "sps.reservation_signalling=standard"]),
        ("highway", ["road.length_m=2500", "link.model=threshold", "radio.sensitivity_dbm=-92"]),
        ("highway", ["road.length_m=2500", "sps.sci_decoding=sinr", "sps.sci_sinr_offset_db=-6"]),
        ("paper", ["channel.shadowing_correlation=pair_distance", "sps.reselection_timing=per_ue"]),
    ],
)
def test_compiled_period_equals_the_numpy_period_on_the_dense_state(
    name: str, extra: list[str], compiled_and_numpy: Callable[..., Any]
) -> None:
    """The compiled chunk against the numpy chunk from the same state, with the dense pair state."""
    cfg = apply_overrides(preset(name), ["metrics.record_links=false", *extra])
    a, _, _, _ = compiled_and_numpy(cfg, 3, 350, 640)
    assert not a.sparse_state
    assert a.n_reselections > 0


def test_links_grouped_by_transmitter_and_a_chunks_links_in_order() -> None:
    tx = np.array([2, 0, 2, 1, 0, 2, 3], dtype=np.int64)
    start, index = kernels.links_by_transmitter(tx, 5)
    np.testing.assert_array_equal(start, [0, 2, 3, 6, 7, 7])  # vehicle 4 sends on no link
    np.testing.assert_array_equal(index, [1, 4, 3, 0, 2, 5, 6])
    np.testing.assert_array_equal(kernels.active_links(start, index, np.array([2, 0])), [0, 1, 2, 4, 5])
    np.testing.assert_array_equal(kernels.active_links(start, index, np.array([4])), np.empty(0))
    rng = np.random.default_rng(0)
    tx = rng.integers(0, 50, 3000)
    start, index = kernels.links_by_transmitter(tx, 50)
    senders = np.flatnonzero(rng.random(50) < 0.2)
    np.testing.assert_array_equal(kernels.active_links(start, index, senders), np.flatnonzero(np.isin(tx, senders)))


@pytest.mark.parametrize("size", [0, 1, 255, 256, 4097, 100_000])
@pytest.mark.parametrize("bound", [1, 4096, 4097, 1 << 24, (1 << 24) + 1, 1 << 40])
def test_radix_sort_equals_numpy_sort(size: int, bound: int) -> None:
    """One, two and several 12-bit passes (an odd count ends in the scratch), duplicates, short arrays."""
    a = np.random.default_rng(size + bound).integers(0, bound, size)
    want = np.sort(a)
    kernels.radix_sort(a, bound)
    np.testing.assert_array_equal(a, want)


def test_compiled_chunks_of_a_few_transmitters_equal_the_numpy_chunks(tolerances: Any) -> None:
    """Runs cut every 7 subframes: each chunk has a few transmitters, so the compiled chunk visits only
    their links (Simulator.chunks._chunk_links); the same results as the numpy chunks (P and its sums to the
    tolerance of tests/sim/conftest.py's compiled_and_numpy, outcomes, resources and S-RSSI exact)."""
    cfg = apply_overrides(preset("highway"), ["road.length_m=2000", "metrics.record_links=false"])
    out = []
    for compiled in (True, False):
        sim = Simulator(cfg)
        sim.compiled_period = compiled
        sim.compiled_min_links = 0  # the compiled chunk at any size
        sim.reset(5, warmup_subframes=100)
        geo = sim._period_geometry()
        subset, links = sim.chunks._chunk_links(geo, sim.slot < 7)
        assert subset and links.shape[0] > 0  # the subset path is the one taken
        sums = [sim.run(7).metrics for _ in range(60)]
        out.append((sim, sums))
    (a, ma), (b, mb) = out
    for x, y in zip(ma, mb, strict=True):
        np.testing.assert_array_equal(x.bin_decoded, y.bin_decoded)
        np.testing.assert_array_equal(x.node_n, y.node_n)
        tolerances.assert_sums_close(x.node_expected, y.node_expected, x.node_n, "node_expected")
    assert a.last_links is not None and b.last_links is not None
    (tx_a, rx_a, p_a, cause_a), (tx_b, rx_b, p_b, cause_b) = a.last_links, b.last_links
    for x, y in ((tx_a, tx_b), (rx_a, rx_b), (cause_a, cause_b)):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_allclose(p_a, p_b, rtol=0.0, atol=tolerances.p_atol)
    np.testing.assert_array_equal(a.scheduler.rssi_ring, b.scheduler.rssi_ring)
    np.testing.assert_array_equal(a.resource, b.resource)
    assert a.n_reselections == b.n_reselections > 0


def _fcd_trace(path: Path, n: int, seconds: float) -> Path:
    """An FCD trace of ``n`` vehicles on a 600 m line of the paper's grid, each present for 0.3-4 s."""
    rng = np.random.default_rng(0)
    births = rng.uniform(-2.0, seconds, n)
    deaths = births + rng.uniform(0.3, 4.0, n)
    lines = ["<fcd-export>"]
    for k in range(round(seconds / 0.1) + 1):
        t = k * 0.1
        lines.append(f'<timestep time="{t:.2f}">')
        for i in range(n):
            if births[i] <= t < deaths[i]:
                x = (13.0 * i + 20.0 * (t - births[i])) % 600.0 + 10.0
                lines.append(f'<vehicle id="v{i}" x="{x:.3f}" y="56.25" angle="90" speed="20"/>')
        lines.append("</timestep>")
    lines.append("</fcd-export>")
    path.write_text("\n".join(lines))
    return path


@pytest.mark.parametrize(
    ("extra", "tile_subframes", "n_subframes"),
    [
        (["link.inband_emission_model=3gpp", "sps.n_subchannels=5", "sps.reselection_timing=per_ue"], None, 3030),
        (
            ["link.inband_emission_db=-15", "sps.n_subchannels=3", "sps.sci_decoding=sinr", "sps.sci_gates_pssch=true"],
            None,
            3030,
        ),
        (["link.inband_emission_model=3gpp", "sps.n_subchannels=5"], 3, 1030),  # tiles of 3 subframes
    ],
)
def test_compiled_period_equals_the_numpy_period_with_an_open_population(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    extra: list[str],
    tile_subframes: int | None,
    n_subframes: int,
    compiled_and_numpy: Callable[..., Any],
) -> None:
    """Vehicles entering and leaving (a trace): absent slots hold no resource and no links; the compiled
    chunk agrees with the numpy chunk, including the chunks of a period with few or no senders (and with
    the kernel's tiles forced to 3 subframes)."""
    if tile_subframes is not None:
        monkeypatch.setattr(kernels, "chunk_tile_subframes", lambda n, n_sub, rri: tile_subframes)
    trace = _fcd_trace(tmp_path / "fcd.xml", 150, 8.0)
    base = [
        "vehicles.mobility=trace",
        f"vehicles.trace_file={trace}",
        "vehicles.population=open",
        "vehicles.sumo_begin_s=0",
        "vehicles.capacity=150",
        "metrics.record_links=false",
    ]
    a, _, _, _ = compiled_and_numpy(apply_overrides(preset("paper"), [*base, *extra]), 3, 137, n_subframes)
    assert a.n_departures > 0 and a.n_entries > 0


def test_small_periods_run_the_numpy_chunk_and_large_ones_the_compiled_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """Below Simulator.compiled_min_links links a period runs the numpy chunk (the same results, less
    dispatch cost at the paper's 420 links); at or above it the compiled one."""
    calls: list[int] = []
    orig = ChunkRunner._run_compiled

    def spy(self: ChunkRunner, geo: object, sched: object, active: object, acc: object) -> object:
        calls.append(1)
        return orig(self, geo, sched, active, acc)  # type: ignore[arg-type]

    monkeypatch.setattr(ChunkRunner, "_run_compiled", spy)
    small = Simulator(apply_overrides(preset("paper"), ["metrics.record_links=false"]))  # 21 vehicles: 420 links
    small.reset(1, warmup_subframes=0)
    small.run(200)
    assert not calls
    small.compiled_min_links = 420
    small.run(200)
    assert len(calls) == 2  # one chunk per period
    big = Simulator(apply_overrides(preset("paper"), ["metrics.record_links=false", "vehicles.n_vehicles=40"]))
    big.reset(1, warmup_subframes=0)  # 1,560 links
    big.run(100)
    assert len(calls) == 3


@pytest.mark.parametrize("correlation", ["travelled", "pair_distance"])
def test_sparse_shadowing_step_equals_its_numpy_reference(correlation: str, tolerances: Any) -> None:
    """channel.SparseShadowing: the compiled merge step (kernels.shadowing_update_sparse) against the numpy
    step (_step_numpy) on the same state and stream, over reads where pairs leave, stay and come back."""
    from cv2x_marl.sim.channel import SparseShadowing

    n = 300
    rng = np.random.default_rng(8)
    sims = [SparseShadowing(n, 25.0, np.random.default_rng(3), correlation) for _ in range(2)]
    odometer = np.zeros(n)
    prev_keys = np.empty(0, dtype=np.int64)
    prev_diff = np.empty(0)
    for step in range(6):
        keep = rng.random(n * (n - 1) // 2) < 0.05  # a different ~5 % of the pairs each read, ascending
        a, b = (x[keep].astype(np.int64) for x in np.triu_indices(n, 1))
        odometer = odometer + rng.uniform(0.0, 3.0, n)
        dist = rng.uniform(5.0, 900.0, a.shape[0])
        fast = sims[0].sample(a, b, odometer, dist)
        keys = a * n + b
        reference = odometer[a] + odometer[b] if correlation == "travelled" else dist
        # the numpy step's rho, previous values and normals (its stream replayed), for the tolerance
        pos = np.minimum(np.searchsorted(prev_keys, keys), max(prev_keys.shape[0] - 1, 0))
        found = (prev_keys[pos] == keys) if prev_keys.shape[0] else np.zeros(keys.shape[0], dtype=bool)
        replay = copy.deepcopy(sims[1]._rng)
        z_prev = np.where(found, sims[1]._z[pos] if prev_keys.shape[0] else 0.0, 0.0)
        z_prev[~found] = replay.standard_normal(int((~found).sum()))
        w = replay.standard_normal(keys.shape[0])
        last = np.where(found, sims[1]._last[pos] if prev_keys.shape[0] else 0.0, 0.0)
        change = reference - last if correlation == "travelled" else np.where(found, np.abs(reference - last), 0.0)
        rho = np.exp(-change / 25.0)
        ref = sims[1]._step_numpy(keys, reference)
        np.testing.assert_array_equal(rho * z_prev + np.sqrt(1.0 - rho * rho) * w, ref)  # the replay is right
        sims[1]._keys, sims[1]._z = keys, ref.copy()
        sims[1]._last = odometer[a] + odometer[b] if correlation == "travelled" else dist.copy()
        # numpy's exp (SIMD on some CPUs) against the kernel's libm exp: the AR(1) step's bound, plus the
        # difference each side carries in its own previous value (times rho)
        carried = np.where(found, prev_diff[pos] if prev_keys.shape[0] else 0.0, 0.0)
        diff = np.abs(fast - ref)
        assert np.all(diff <= tolerances.ar1(rho, z_prev, w) + rho * carried), (step, diff.max())
        prev_diff = diff
        np.testing.assert_array_equal(sims[0]._keys, keys)
        assert step == 0 or np.any(np.isin(keys, prev_keys))  # some pairs were read before
        prev_keys = keys
    assert np.std(fast) == pytest.approx(1.0, abs=0.05)


def test_chunk_tile_subframes() -> None:
    """Subframes per tile of kernels.period_chunk: as many as fit the scratch budget, at least 1, at most RRI."""
    assert kernels.chunk_tile_subframes(10_000, 5, 100) == 1
    assert kernels.chunk_tile_subframes(21, 5, 100, tile_bytes=8 * 21 * 5 * 7 + 5) == 7
    assert kernels.chunk_tile_subframes(21, 5, 100, tile_bytes=8 * 21 * 5 * 1000) == 100
    assert kernels.chunk_tile_subframes(0, 5, 20) == 20
    assert kernels.chunk_tile_subframes(21, 5, 100) == kernels.CHUNK_TILE_BYTES // (8 * 21 * 5)


def _chunk_args(rng: np.random.Generator, n: int, n_sub: int, rri: int, variant: str) -> dict[str, Any]:
    """Random inputs of kernels.period_chunk: ``n`` vehicles, all ordered pairs as links (pairs i < j, then
    doubled, as the simulator's), half the vehicles active, in-band ``variant`` (none, flat, 3gpp + SCI); the
    named tuples' fields as lists (``pairs``, ``vehicles``, ``model``, ``sci``, ``buffers`` less the tile size,
    ``bins``) and the two streams."""
    i, j = np.triu_indices(n, 1)
    rx, tx = np.concatenate([i, j]).astype(np.int64), np.concatenate([j, i]).astype(np.int64)
    dist = np.concatenate([np.abs(i - j) * 37.0] * 2)
    rx_mw = 10.0 ** (rng.uniform(-11.5, -8.0, rx.shape[0]))
    resource = rng.integers(0, n_sub * rri, n)
    slot = resource // n_sub
    active = rng.random(n) < 0.5
    n_res = n_sub * rri
    curve = load_per_curve(PER_CURVES[0], "linear")
    per_db, per = curve.sinr_db, curve.per
    sci_lin, sci_bler = np.empty(0), np.empty(0)
    leakage, flat = np.empty((0, 0)), 0.0
    if variant == "3gpp":
        sci_lin, sci_bler = 10.0 ** (np.linspace(-5.0, 10.0, 16) / 10.0), np.linspace(1.0, 0.01, 16) ** 2
        leakage = rng.random((n_sub, n_sub)) * 1e-3
    if variant == "flat":
        flat = 1e-3
    releasing = rng.random(n) < 0.2
    period_rssi = rng.random(n * n_res) * (rng.random(n * n_res) < 0.3)
    sensitivity = -95.0 if variant == "3gpp" else -np.inf
    return {
        "pairs": [rx, tx, dist, rx_mw, False, np.empty(0, dtype=np.int64)],
        "vehicles": [active, resource, slot, releasing],
        "model": [n_res, n_sub, 10.0**-10.2, kernels.MODEL_PER_TABLE, per_db, per, 3.0, sensitivity, flat, leakage],
        "sci": [sci_lin, sci_bler, 1.5, variant == "3gpp"],
        "buffers": [period_rssi, np.zeros(n * n_res), np.zeros(n * n_res), np.zeros(n * rri)],
        "bins": [100.0, 20, 5],
        "link_rng": np.random.default_rng(1),
        "sci_rng": np.random.default_rng(2),
    }


@pytest.mark.parametrize("variant", ["none", "flat", "3gpp"])
@pytest.mark.parametrize("subset", [False, True])
def test_period_chunk_is_the_same_for_any_tile_size(variant: str, subset: bool) -> None:
    """kernels.period_chunk processes the chunk tile by tile (a few subframes at a time, the links of a tile
    in link order): any tile size gives the same bits (outputs, PRR sums, S-RSSI, SCI map, the streams'
    states, the scratches left zero), with every link visited or a subset (a few senders), tiles of one
    subframe, of several with a shorter last one, or the whole period."""
    n, n_sub, rri = 40, 3, 20
    ref = None
    for tile in (1, 3, 7, rri):
        args = _chunk_args(np.random.default_rng(5), n, n_sub, rri, variant)
        pairs, vehicles, buffers = args["pairs"], args["vehicles"], args["buffers"]
        if subset:
            senders = np.flatnonzero(vehicles[0] & (vehicles[2] < 9))
            vehicles[0] = np.isin(np.arange(n), senders)
            start, index = kernels.links_by_transmitter(pairs[1], n)
            pairs[4], pairs[5] = True, kernels.active_links(start, index, senders)
        out = kernels.period_chunk(
            kernels.ChunkLinks(*pairs),
            kernels.ChunkVehicles(*vehicles),
            kernels.LinkModel(*args["model"]),
            kernels.SciModel(*args["sci"]),
            kernels.ChunkBuffers(*buffers, tile),
            kernels.DistanceBins(*args["bins"]),
            args["link_rng"],
            args["sci_rng"],
        )
        assert isinstance(out, kernels.ChunkResult)
        assert not np.any(buffers[2]) and not np.any(buffers[3])
        got = (*out, buffers[0], buffers[1], args["link_rng"].random(), args["sci_rng"].random())
        assert out.tx.shape[0] > 100 and np.any(buffers[1] > 0)
        if ref is None:
            ref = got
            continue
        for x, y in zip(ref, got, strict=True):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("tile", [1, 3, 100])
@pytest.mark.parametrize(
    ("name", "extra"),
    [
        ("highway", []),  # per_ue (chunks of a few senders), standard signalling, SCI sinr + gate, 3gpp leakage
        ("highway-legacy", ["link.inband_emission_db=-30"]),  # flat in-band emission
        ("highway-legacy", ["sps.sci_decoding=sinr", "sps.sci_gates_pssch=true", "radio.sensitivity_dbm=-95"]),
    ],
)
def test_tiled_compiled_period_equals_the_numpy_period(
    monkeypatch: pytest.MonkeyPatch, name: str, extra: list[str], tile: int, compiled_and_numpy: Callable[..., Any]
) -> None:
    """The compiled chunk with tiles of 1, 3 and 100 subframes (kernels.chunk_tile_subframes forced) against
    the numpy chunk (tests/sim/conftest.py: P to 1e-12, everything else exact)."""
    monkeypatch.setattr(kernels, "chunk_tile_subframes", lambda n, n_sub, rri: min(rri, tile))
    cfg = apply_overrides(preset(name), ["road.length_m=2500", "metrics.record_links=false", *extra])
    compiled_and_numpy(cfg, 2, 250, 440)
