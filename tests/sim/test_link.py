"""Link abstraction: PER table interpolation and the Rayleigh closed form."""

import numpy as np
import pytest

from cv2x_marl.sim import link


def test_per_table_points_r05() -> None:
    curve = link.load_per_curve("r1-160284-190b-r0.5", "linear")
    table = {-2: 1.0, 0: 0.9, 2: 0.7, 4: 0.3, 6: 0.09, 8: 0.02, 10: 0.002, 12: 0.001}
    for sinr, per in table.items():
        assert curve.success(sinr) == pytest.approx(1.0 - per)
    assert curve.success(3.0) == pytest.approx(1.0 - 0.5)  # midway between 0.7 and 0.3
    assert curve.success(-10.0) == 0.0
    assert curve.success(30.0) == pytest.approx(0.999)
    assert "R1-160284" in curve.source


def test_per_table_points_r07() -> None:
    curve = link.load_per_curve("r1-160284-190b-r0.7", "linear")
    table = {0: 1.0, 2: 0.9, 4: 0.7, 6: 0.4, 8: 0.13, 10: 0.045, 12: 0.017, 14: 0.007, 16: 0.001}
    got = curve.success(np.array(list(table)))
    assert got == pytest.approx(1.0 - np.array(list(table.values())))


def test_unknown_curve_named() -> None:
    with pytest.raises(ValueError, match="nope"):
        link.load_per_curve("nope", "linear")


def test_rayleigh_closed_form_against_monte_carlo() -> None:
    rng = np.random.default_rng(11)
    s_mw, noise_mw = 1.0, 0.1
    interferers = np.array([0.3, 0.5])
    theta_db = 2.0
    p = link.rayleigh_success(np.array([s_mw]), noise_mw, interferers, np.array([0, 0]), theta_db)[0]
    theta = 10 ** (theta_db / 10)
    expected = np.exp(-theta * noise_mw / s_mw) / np.prod(1 + theta * interferers / s_mw)
    assert p == pytest.approx(expected)
    n = 400_000
    g_s = rng.exponential(size=n)
    g_i = rng.exponential(size=(n, 2))
    sinr = g_s * s_mw / (g_i @ interferers + noise_mw)
    mc = np.mean(sinr >= theta)
    sigma = np.sqrt(p * (1 - p) / n)
    assert abs(mc - p) < 4 * sigma


def test_rayleigh_without_interference_is_exponential() -> None:
    p = link.rayleigh_success(np.array([2.0, 0.5]), 1.0, np.empty(0), np.empty(0, dtype=np.int64), 0.0)
    assert p == pytest.approx(np.exp([-0.5, -2.0]))


def test_threshold() -> None:
    assert list(link.threshold_success([1.9, 2.0, 5.0], 2.0)) == [0.0, 1.0, 1.0]
