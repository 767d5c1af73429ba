"""channel.shadowing_correlation (issue 13, defect 6): ``pair_distance`` decorrelates a pair's
shadowing with the change of its distance, ``rho = exp(-|d(t) - d(t')| / d_c)`` (TR 36.885 A.1.4);
``travelled`` (the default) with the sum of both vehicles' travelled distances."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from cv2x_marl.config import ConfigError, apply_overrides, preset
from cv2x_marl.sim import Simulator, channel

A = np.array([0, 0, 1])
B = np.array([1, 2, 2])


def _pair(correlation: str, seed: int = 5) -> tuple[channel.Shadowing, np.random.Generator]:
    """A shadowing object and a twin of its generator advanced past the initial draw."""
    sh = channel.Shadowing(3, 25.0, np.random.default_rng(seed), correlation)
    twin = np.random.default_rng(seed)
    twin.standard_normal((3, 3))
    return sh, twin


@pytest.mark.kernel_equality
def test_pair_distance_follows_its_formula_for_a_hand_built_motion(tolerances: Any) -> None:
    sh, twin = _pair("pair_distance")
    z0 = sh._z[A, B].copy()
    odo = np.zeros(3)
    # period 1: pair distances 40, 100, 60 m -> first read: D = 0, the initial draw stays
    d1 = np.array([40.0, 100.0, 60.0])
    z1 = sh.sample(A, B, odo, d1)
    g1 = twin.standard_normal(3)
    np.testing.assert_array_equal(z1, z0)  # rho = 1: sqrt(1 - 1) * g = 0
    # period 2: vehicle 0 and 1 drive together (40 m apart still), vehicle 2 closes in by 10 m on 0
    # and 20 m on 1; everybody travelled 3 m, which must not matter
    odo = odo + 3.0
    d2 = np.array([40.0, 90.0, 80.0])
    z2 = sh.sample(A, B, odo, d2)
    g2 = twin.standard_normal(3)
    rho = np.exp(-np.array([0.0, 10.0, 20.0]) / 25.0)
    # the step is compiled (libm's exp), the formula here numpy's exp (SIMD on some CPUs): the AR(1)
    # step's propagated tolerance (tests/sim/conftest.py), not bit for bit
    want = rho * z1 + np.sqrt(1.0 - rho**2) * g2
    assert np.all(np.abs(z2 - want) <= tolerances.ar1(rho, z1, g2)), z2 - want
    assert z2[0] == z1[0]
    # symmetric storage
    np.testing.assert_array_equal(sh._z[B, A], z2)
    del g1


@pytest.mark.kernel_equality
def test_travelled_is_unchanged(tolerances: Any) -> None:
    sh, twin = _pair("travelled")
    z0 = sh._z[A, B].copy()
    odo = np.array([3.0, 3.0, 7.0])
    z1 = sh.sample(A, B, odo, np.array([40.0, 90.0, 80.0]))  # distances ignored
    g = twin.standard_normal(3)
    rho = np.exp(-(odo[A] + odo[B]) / 25.0)
    # compiled step (libm's exp) against numpy's exp (SIMD on some CPUs; 1.4e-14 relative apart on an
    # AVX-512 Xeon, where the two terms partly cancel): the AR(1) step's propagated tolerance
    want = rho * z0 + np.sqrt(1.0 - rho**2) * g
    assert np.all(np.abs(z1 - want) <= tolerances.ar1(rho, z0, g)), z1 - want
    default = channel.Shadowing(3, 25.0, np.random.default_rng(5))
    np.testing.assert_array_equal(default.sample(A, B, odo), z1)


def test_pair_distance_needs_distances() -> None:
    sh, _ = _pair("pair_distance")
    with pytest.raises(ValueError, match="needs the pairs' distances"):
        sh.sample(A, B, np.zeros(3))


def test_simulator_keeps_the_shadowing_of_a_constant_geometry() -> None:
    """Every vehicle at the same speed in the same direction: pair distances never change, so with
    pair_distance the shadowing is frozen, while with travelled it decorrelates."""
    sets = [
        "road.kind=highway",
        "road.length_m=2000",
        "road.wrap_distances=true",
        "vehicles.n_vehicles=20",
        "vehicles.speed_min_mps=30",
        "vehicles.speed_max_mps=30",
        "road.lanes_per_direction=1",
        "sim.warmup_subframes=0",
        "channel.los=always",
    ]
    out = {}
    for mode in ("pair_distance", "travelled"):
        sim = Simulator(apply_overrides(preset("paper"), [*sets, f"channel.shadowing_correlation={mode}"]))
        sim.reset(1, warmup_subframes=0)
        same_dir = sim.snapshot().velocities_mps[:, 0] > 0
        sh0 = sim.snapshot().shadowing_db
        sim.run(5 * sim.rri, record=False)
        sh1 = sim.snapshot().shadowing_db
        both = np.outer(same_dir, same_dir) & ~np.eye(sim.n, dtype=bool)
        out[mode] = np.abs(sh1 - sh0)[both]
    np.testing.assert_allclose(out["pair_distance"], 0.0, atol=1e-9)
    assert np.all(out["travelled"] > 0)


def test_unknown_mode_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"channel\.shadowing_correlation: 'x' is not allowed; allowed values"):
        apply_overrides(preset("paper"), ["channel.shadowing_correlation=x"])
