"""Path loss, noise, shadowing and Doppler against hand-computed reference values."""

import numpy as np
import pytest

from cv2x_marl.sim import channel
from cv2x_marl.units import noise_power_dbm, thermal_noise_dbm

# WINNER+ B1 LOS (TR 36.885), fc = 2 GHz, evaluated by hand:
#   h' = 1.5 m: d_BP = 4 * 1.5^2 * 2e9 / c = 60.04 m
#     50 m  (< d_BP): 22.7 log10(50) + 41 + 20 log10(0.4)                    = 71.6078
#     200 m (> d_BP): 40 log10(200) + 9.45 - 34.6 log10(1.5) + 2.7 log10(0.4) = 94.3240
#   h' = 0.5 m: d_BP = 6.67 m, so both are beyond the breakpoint
#     50 m: 40 log10(50) + 9.45 - 34.6 log10(0.5) + 2.7 log10(0.4)  = 86.7500
#     200 m:                                                         = 110.8324
LOS_REFERENCE = [
    (1.5, 50.0, 71.6078),
    (1.5, 100.0, 82.2828),
    (1.5, 200.0, 94.3240),
    (1.5, 300.0, 101.3677),
    (0.5, 50.0, 86.7500),
    (0.5, 100.0, 98.7912),
    (0.5, 200.0, 110.8324),
    (0.5, 300.0, 117.8761),
]


# free space (TR 36.885 form) at 2 GHz: 20 log10 d + 46.4 + 20 log10(0.4)
FREE_SPACE_REFERENCE = {50.0: 72.4206, 100.0: 78.4412, 200.0: 84.4618, 300.0: 87.9836}


@pytest.mark.parametrize(("h_m", "d_m", "expected_db"), LOS_REFERENCE)
def test_winner_b1_los_reference(h_m: float, d_m: float, expected_db: float) -> None:
    assert channel.winner_b1_los_db(d_m, 2e9, h_m) == pytest.approx(expected_db, abs=1e-3)
    assert channel.free_space_db(d_m, 2e9) == pytest.approx(FREE_SPACE_REFERENCE[d_m], abs=1e-3)
    # the model floors the LOS formula by free space: below 100 m the 22.7 dB/dec branch is under it
    full = channel.winner_b1_db(d_m, 0.0, True, 2e9, h_m)
    assert full == pytest.approx(max(expected_db, FREE_SPACE_REFERENCE[d_m]), abs=1e-3)


def test_antenna_height_variants_differ_by_reported_margin() -> None:
    # READING.md: the two effective heights disagree by 10-17 dB at 50-200 m
    d = np.array([50.0, 100.0, 200.0])
    gap = channel.winner_b1_db(d, 0 * d, True, 2e9, 0.5) - channel.winner_b1_db(d, 0 * d, True, 2e9, 1.5)
    assert np.all((gap > 10.0) & (gap < 17.0))


def test_winner_b1_nlos_reference_and_symmetry() -> None:
    # d1 = d2 = 100 m, h' = 1.5 m: n = 2.8 - 0.24 = 2.56
    # PL_LOS(100) + 20 - 12.5 * 2.56 + 25.6 * 2 + 3 log10(0.4) = 120.2890
    assert channel.winner_b1_db(100.0, 100.0, False, 2e9, 1.5) == pytest.approx(120.2890, abs=1e-3)
    # the minimum over the two street orderings is symmetric in (dx, dy)
    a = channel.winner_b1_db(40.0, 250.0, False, 2e9, 1.5)
    b = channel.winner_b1_db(250.0, 40.0, False, 2e9, 1.5)
    assert a == pytest.approx(b)
    # d1 = 40 m (n = 2.704, LOS part below the breakpoint): 69.408 + 20 - 33.8 + 27.04 log10(250) - 1.194
    #   = 119.254 dB; the other ordering (d1 = 250 m, n = 2.2) gives 124.752 dB; the minimum is kept
    assert channel.winner_b1_nlos_db(40.0, 250.0, 2e9, 1.5) == pytest.approx(119.254, abs=2e-3)


def test_free_space_floor() -> None:
    # at 5 m with h' = 0.5 m the LOS formula gives 48.91 dB, below free space 52.42 dB
    assert channel.winner_b1_los_db(5.0, 2e9, 0.5) == pytest.approx(48.9078, abs=1e-3)
    assert channel.winner_b1_db(5.0, 0.0, True, 2e9, 0.5) == pytest.approx(52.4206, abs=1e-3)


def test_power_law_eq3() -> None:
    # free-space K at d0 = 1 m, 2 GHz: lambda = 0.149896 m, 20 log10(lambda / 4 pi) = -38.4684 dB;
    # omega = 2 then gives free-space loss at 100 m: 38.4684 + 40
    pl = channel.power_law_db(100.0, None, 1.0, 2.0, 2e9)
    assert pl == pytest.approx(38.4684 + 40.0, abs=1e-3)
    assert channel.power_law_db(100.0, -40.0, 10.0, 3.5, 2e9) == pytest.approx(40.0 + 35.0)


def test_noise_over_10_rb_with_nf_9db() -> None:
    assert noise_power_dbm(-112.45, 9.0) == pytest.approx(-103.45)
    # kT0B over 10 RB (1.8 MHz)
    assert thermal_noise_dbm(10 * 180e3) == pytest.approx(-111.42, abs=0.01)


def test_doppler_eq4() -> None:
    # D = 2 c v / 3e8: 2 GHz, 15 m/s -> 200 Hz
    assert channel.doppler_hz(2e9, 15.0) == pytest.approx(200.0)


def test_shadowing_statistics_and_correlation() -> None:
    rng = np.random.default_rng(3)
    n = 400
    sh = channel.Shadowing(n, decorrelation_m=10.0, rng=rng)
    i, j = np.triu_indices(n, 1)
    odo = np.zeros(n)
    z0 = sh.sample(i, j, odo).copy()
    assert z0.std() == pytest.approx(1.0, abs=0.01)
    assert z0.mean() == pytest.approx(0.0, abs=0.01)
    odo = odo + 2.5  # both ends travel 2.5 m: D = 5 m -> correlation exp(-0.5)
    z1 = sh.sample(i, j, odo)
    assert np.corrcoef(z0, z1)[0, 1] == pytest.approx(np.exp(-0.5), abs=0.01)
    assert z1.std() == pytest.approx(1.0, abs=0.01)


@pytest.mark.kernel_equality
@pytest.mark.parametrize("h_m", [0.5, 1.5])
def test_compiled_winner_b1_equals_the_formula_composition(h_m: float) -> None:
    """winner_b1_db (one compiled pass) against the numpy LOS / NLOS / free-space formulas."""
    rng = np.random.default_rng(2)
    dx = rng.uniform(-600.0, 600.0, 4000) * (rng.random(4000) < 0.9)  # some exact zeros (street-aligned)
    dy = rng.uniform(-600.0, 600.0, 4000) * (rng.random(4000) < 0.9)
    dx[:50] = rng.uniform(-2.0, 2.0, 50)  # below the 3 m clip
    los = rng.random(4000) < 0.5
    dmin = 3.0
    d = np.maximum(np.hypot(dx, dy), dmin)
    ax, ay = np.maximum(np.abs(dx), dmin), np.maximum(np.abs(dy), dmin)
    want = np.where(los, channel.winner_b1_los_db(d, 5.9e9, h_m), channel.winner_b1_nlos_db(ax, ay, 5.9e9, h_m))
    want = np.maximum(want, channel.free_space_db(d, 5.9e9))
    np.testing.assert_allclose(channel.winner_b1_db(dx, dy, los, 5.9e9, h_m, dmin), want, rtol=1e-12, atol=1e-10)
    # broadcasting: a [2, 1] column of dx against a [3] row of dy
    got = channel.winner_b1_db(np.array([[10.0], [300.0]]), np.array([0.0, 5.0, 80.0]), False, 5.9e9, h_m)
    assert got.shape == (2, 3)
