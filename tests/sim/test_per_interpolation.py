"""link.per_interpolation (issue 13, defect 4): ``log`` interpolates ln PER linearly in SINR (dB);
``linear`` (the default) is unchanged. The numpy path (:class:`cv2x_marl.sim.link.PerCurve`) and the
compiled one (:func:`cv2x_marl.sim.kernels.per_success`) must agree."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.sim import Simulator, kernels, link

R05 = "r1-160284-190b-r0.5"
R07 = "r1-160284-190b-r0.7"


def test_seven_db_by_hand() -> None:
    # r0.5: 6 dB -> 0.09, 8 dB -> 0.02; halfway: linear (0.09 + 0.02) / 2, log sqrt(0.09 * 0.02)
    lin = 1.0 - float(link.load_per_curve(R05, "linear").success(7.0))
    log = 1.0 - float(link.load_per_curve(R05, "log").success(7.0))
    assert lin == pytest.approx(0.055, abs=1e-15)
    assert log == pytest.approx(math.sqrt(0.09 * 0.02), rel=1e-12)
    assert log == pytest.approx(0.0424264, abs=1e-7)


@pytest.mark.parametrize("name", [R05, R07])
def test_both_modes_equal_the_table_at_its_points(name: str) -> None:
    lin, log = link.load_per_curve(name, "linear"), link.load_per_curve(name, "log")
    np.testing.assert_allclose(1.0 - lin.success(lin.sinr_db), lin.per, rtol=0, atol=1e-15)
    np.testing.assert_allclose(1.0 - log.success(log.sinr_db), log.per, rtol=1e-12, atol=0)


@pytest.mark.parametrize("name", [R05, R07])
def test_log_between_points_is_geometric(name: str) -> None:
    curve = link.load_per_curve(name, "log")
    rng = np.random.default_rng(0)
    j = rng.integers(0, curve.sinr_db.size - 1, size=200)
    t = rng.random(200)
    x = curve.sinr_db[j] + t * (curve.sinr_db[j + 1] - curve.sinr_db[j])
    hand = curve.per[j] ** (1.0 - t) * curve.per[j + 1] ** t  # PER_j^(1-t) PER_{j+1}^t
    np.testing.assert_allclose(1.0 - curve.success(x), hand, rtol=1e-12)
    # never above the linear interpolation (a chord of a convex function in the log domain)
    assert np.all(1.0 - curve.success(x) <= 1.0 - link.load_per_curve(name, "linear").success(x) + 1e-15)


def test_outside_the_table() -> None:
    curve = link.load_per_curve(R05, "log")
    assert float(curve.success(-2.0001)) == 0.0
    assert float(curve.success(-np.inf)) == 0.0
    assert float(curve.success(50.0)) == pytest.approx(1.0 - 0.001, abs=1e-15)


@pytest.mark.kernel_equality
@pytest.mark.parametrize("name", [R05, R07])
@pytest.mark.parametrize("interp", ["linear", "log"])
def test_compiled_kernel_agrees_with_numpy(name: str, interp: str, tolerances: Any) -> None:
    """The kernel's PER interpolation against PerCurve.success on the same dB values: the log-domain one
    takes libm's log / exp in the kernel and numpy's (SIMD on some CPUs) in PerCurve, so to the tolerance
    of a link probability (tests/sim/conftest.py), exact arithmetic otherwise."""
    curve = link.load_per_curve(name, interp)
    x = np.r_[np.linspace(-5.0, 20.0, 2001), curve.sinr_db, -np.inf, np.inf, np.nan]
    want = curve.success(x)
    got = np.array([kernels.per_success(v, curve.sinr_db, curve.per, interp == "log") for v in x])
    want = np.where(np.isnan(x), 0.0, want)  # the kernel treats NaN as below the table
    np.testing.assert_allclose(got, want, rtol=0.0, atol=tolerances.p_atol)
    # through the model code the env kernels use
    lvl = np.array(
        [kernels.success_at_level(v, 0.0, curve.kernel_model, curve.sinr_db, curve.per, 2.0, -np.inf) for v in x[:-3]]
    )
    np.testing.assert_allclose(lvl, want[:-3], rtol=0.0, atol=tolerances.p_atol)
    assert curve.kernel_model == (kernels.MODEL_PER_TABLE_LOG if interp == "log" else kernels.MODEL_PER_TABLE)


def test_linear_kernel_is_unchanged_by_the_new_argument() -> None:
    curve = link.load_per_curve(R05, "linear")
    for v in (-1.0, 0.3, 7.0, 11.9):
        assert kernels.per_success(v, curve.sinr_db, curve.per) == kernels.per_success(
            v, curve.sinr_db, curve.per, False
        )


def test_simulator_uses_the_configured_interpolation() -> None:
    cfg = apply_overrides(preset("paper"), ["sim.warmup_subframes=0", "link.per_interpolation=log"])
    sim = Simulator(cfg)
    sim.reset(3, warmup_subframes=0)
    links = sim.run(300).links
    assert links is not None
    ok = links["cause"] != 1  # not half duplex (the paper preset has no sensitivity floor)
    want = link.load_per_curve(cfg.link.per_curve, "log").success(links["sinr_db"][ok])
    np.testing.assert_array_equal(links["p_success"][ok], want)
    assert Simulator(preset("paper")).curve.interpolation == "linear"  # the default


def test_unknown_interpolation_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"link\.per_interpolation: 'cubic' is not allowed; allowed values: linear"):
        apply_overrides(preset("paper"), ["link.per_interpolation=cubic"])
    with pytest.raises(ValueError, match="unknown PER interpolation"):
        link.load_per_curve(R05, "cubic")


@pytest.mark.kernel_equality
def test_env_links_follow_the_configured_interpolation() -> None:
    """The env's ground truth (SnapshotLinks: compiled kernel and numpy reference) and the
    one-mover row use the configured interpolation too, so env rewards agree with the simulator."""
    from cv2x_marl.sim.ground_truth import SnapshotLinks

    cfg_lin = preset("paper")
    cfg_log = apply_overrides(cfg_lin, ["link.per_interpolation=log"])
    snap = Simulator(cfg_log).reset(3)
    pos = snap.positions_m + np.random.default_rng(0).normal(0.0, 20.0, snap.positions_m.shape)
    fast = SnapshotLinks(cfg_log, snap).success(pos)
    ref = SnapshotLinks(cfg_log, snap, compiled=False).success(pos)
    np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-12)
    linear = SnapshotLinks(cfg_lin, snap).success(pos)
    between = (fast > 0) & (fast < 0.999) & (linear > 0)
    assert between.any() and np.all(fast[between] >= linear[between] - 1e-12)  # log PER <= linear PER
    assert np.any(fast[between] > linear[between] + 1e-6)
    row = SnapshotLinks(cfg_log, snap).mover_row(4, pos).success(pos[4:5])[0]
    np.testing.assert_array_equal(row, fast[4])
