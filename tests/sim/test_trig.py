"""The field's cosine (:mod:`cv2x_marl.sim.kernels.trig`) against 50-digit values and the C library."""

from __future__ import annotations

import math

import mpmath
import numpy as np
import pytest

from cv2x_marl.sim.kernels.trig import COS_REDUCTION_LIMIT, cos_into, cos_rad

ULP_OF_ONE = 2.0**-52


def _exact_cos(x: float) -> float:
    with mpmath.workdps(50):
        return float(mpmath.cos(mpmath.mpf(x)))


def test_cos_rad_is_within_one_ulp_of_the_50_digit_cosine() -> None:
    """Arguments the field produces (|x| up to 1e6 through the reduction, beyond through the C library),
    plus the quadrant edges: the error against mpmath's 50-digit cosine, rounded, is at most one ulp of 1."""
    rng = np.random.default_rng(20261127)
    xs = np.concatenate(
        [(rng.random(400) - 0.5) * 2.0 * scale for scale in (1.0, 10.0, 1e3, 1e5, COS_REDUCTION_LIMIT, 1e8)]
        + [np.array([0.0, -0.0, math.pi / 4, math.pi / 2, math.pi, 3 * math.pi / 2, 2 * math.pi, 1e6 - 0.5])]
    )
    worst = max(abs(cos_rad(float(x)) - _exact_cos(float(x))) for x in xs)
    assert worst <= ULP_OF_ONE / 2, worst  # 1.1e-16 absolute: within one ulp of 1
    assert cos_rad(0.0) == 1.0


def test_cos_rad_stays_within_one_ulp_of_one_of_the_c_library() -> None:
    """200,000 heavy-tailed arguments as the field's waves give (|k| d = sqrt((1 - U)^-2 - 1), 150 m moved)."""
    rng = np.random.default_rng(7)
    u = rng.random(200_000)
    xs = np.sqrt((1.0 - u) ** -2.0 - 1.0) / 10.0 * 150.0 + rng.random(200_000) * 2.0 * math.pi
    out = np.empty_like(xs)
    cos_into(xs, out)
    assert np.abs(out - np.cos(xs)).max() <= ULP_OF_ONE
    assert np.count_nonzero(np.abs(xs) > COS_REDUCTION_LIMIT) > 0  # the fallback is exercised


def test_cos_into_gives_the_bits_of_cos_rad_and_the_c_library_beyond_the_limit() -> None:
    rng = np.random.default_rng(3)
    xs = np.concatenate([(rng.random(1000) - 0.5) * 4e6, [np.inf, -np.inf, np.nan, 1e300]])
    out = np.empty_like(xs)
    cos_into(xs, out)
    one_by_one = np.array([cos_rad(float(x)) for x in xs])
    assert np.array_equal(out, one_by_one, equal_nan=True)
    big = np.abs(xs) > COS_REDUCTION_LIMIT
    finite = np.isfinite(xs)
    assert np.array_equal(out[big & finite], np.array([math.cos(float(x)) for x in xs[big & finite]]))
    assert np.isnan(out[~finite]).all()


@pytest.mark.parametrize("x", [math.pi / 2, -math.pi / 2, 1e6, -1e6])
def test_quadrant_edges_are_continuous(x: float) -> None:
    """Either side of a reduction boundary (the quadrant switches from a cosine to a sine polynomial)."""
    for y in (np.nextafter(x, -np.inf), x, np.nextafter(x, np.inf)):
        assert abs(cos_rad(float(y)) - _exact_cos(float(y))) <= ULP_OF_ONE / 2
