"""Shared fixtures of the simulator tests."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test that takes :func:`compiled_and_numpy` (the compiled period against the numpy period) is a
    kernel-equality test: marked ``kernel_equality``, so ``make test-portable`` reruns it."""
    for item in items:
        if "compiled_and_numpy" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.kernel_equality)


@pytest.fixture(autouse=True, scope="module")
def _sumo_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """One generated-SUMO-scenario cache per test module, never the user's (``CV2X_MARL_SUMO_CACHE``)."""
    from cv2x_marl.sim.sumo import CACHE_ENV

    mp = pytest.MonkeyPatch()
    mp.setenv(CACHE_ENV, str(tmp_path_factory.mktemp("sumo-cache")))
    yield
    mp.undo()


@pytest.fixture()
def compiled_and_numpy() -> Callable[..., tuple[Any, Any, Any, Any]]:
    """``run(cfg, seed, warmup_subframes, n_subframes)``: the same scenario with the compiled chunk and with
    the numpy chunk (``Simulator.compiled_period``); asserts that they agree and returns
    ``(compiled_sim, its_metrics, numpy_sim, its_metrics)``. End the run mid-period so that the period's
    SCI map and S-RSSI sums are compared while they hold something.

    The two chunks take the same inputs (the period's geometry and received powers, shared) and the same
    uniforms, but not the same transcendental functions: the kernel's ``log10`` / ``pow`` / ``exp`` are the C
    library's, numpy's may be SIMD versions (AVX-512 / SVML on some CPUs) that differ in the last bits.

    - ``P`` to :data:`P_ATOL` and its sums (``bin_expected``, ``node_expected``) to ``P_ATOL`` per link
      summed (``bin_n``, ``node_n``) plus rtol 1e-12 for the summation.
    - Exact: transmitters, receivers, causes, decoded counts, SCI map, S-RSSI, resources (sums of the same
      powers in the same order, maxima). An outcome is ``u < P`` for a shared uniform ``u``, so a last-bit
      difference in P flips it only when ``u`` falls between the two values: probability ``|dP|`` per
      link. With ``|dP| <= P_ATOL`` (asserted first) the chance of any flip in a run is at most
      ``n_links * P_ATOL`` (asserted below 1e-4 for each scenario), and the same bound holds for the SCI
      draws and for the threshold / sensitivity comparisons (a dB value within a few ulp of a threshold).
      A mismatch in these is therefore a kernel defect, not rounding; comparing them only away from the
      boundary would need the per-link uniforms, which the chunks do not expose."""
    from cv2x_marl.sim import Simulator

    def run(cfg: Any, seed: int, warmup_subframes: int, n_subframes: int) -> tuple[Any, Any, Any, Any]:
        out = []
        for compiled in (True, False):
            sim = Simulator(cfg)
            sim.compiled_period = compiled
            sim.compiled_min_links = 0  # the compiled chunk at any size
            sim.reset(seed, warmup_subframes=warmup_subframes)  # part periods: chunks of part of a period
            out.append((sim, sim.run(n_subframes).metrics))
        (a, ma), (b, mb) = out
        assert a.subframe % a.rri != 0, "end the run mid-period: the period's maps are compared"
        assert a.last_links is not None and b.last_links is not None
        (tx_a, rx_a, p_a, cause_a), (tx_b, rx_b, p_b, cause_b) = a.last_links, b.last_links
        for x, y in ((tx_a, tx_b), (rx_a, rx_b), (cause_a, cause_b)):
            np.testing.assert_array_equal(x, y)
        np.testing.assert_allclose(p_a, p_b, rtol=0.0, atol=P_ATOL)
        n_links = int(ma.bin_n.sum())
        assert n_links * P_ATOL < 1e-4, f"{n_links} links: an outcome flip by rounding is no longer negligible"
        for key in ("bin_n", "bin_decoded", "bin_causes", "node_n", "node_decoded"):
            np.testing.assert_array_equal(getattr(ma, key), getattr(mb, key), err_msg=key)
        for key, count in (("bin_expected", "bin_n"), ("node_expected", "node_n")):
            assert_sums_close(getattr(ma, key), getattr(mb, key), getattr(ma, count), key)
        assert np.any(a.scheduler.period_sci_mw > 0) and np.any(a.scheduler.period_rssi_mw > 0)
        np.testing.assert_array_equal(a.scheduler.period_sci_mw, b.scheduler.period_sci_mw)
        np.testing.assert_array_equal(a.scheduler.period_rssi_mw, b.scheduler.period_rssi_mw)
        np.testing.assert_array_equal(a.scheduler.rssi_ring, b.scheduler.rssi_ring)
        np.testing.assert_array_equal(a.resource, b.resource)
        assert not np.any(a.chunks.total) and not np.any(a.chunks.total_slot)  # the scratches left zero
        assert a.n_reselections == b.n_reselections
        assert ma.n_transmissions == mb.n_transmissions > 0
        return a, ma, b, mb

    return run


def assert_sums_close(a: Any, b: Any, n: Any, name: str) -> None:
    """Sums of ``n`` link probabilities each within :data:`P_ATOL`: ``|a - b| <= n P_ATOL + 1e-12 |b|``
    (the relative part for the summation's own rounding)."""
    a, b, n = np.asarray(a), np.asarray(b), np.asarray(n)
    assert a.shape == b.shape == n.shape, (name, a.shape, b.shape, n.shape)
    bad = np.abs(a - b) > n * P_ATOL + 1e-12 * np.abs(b)
    assert not np.any(bad), f"{name}: {a[bad][:5]} vs {b[bad][:5]} at {np.flatnonzero(bad)[:5]}"


#: float64's machine epsilon (one ulp at 1.0)
EPS = float(np.finfo(np.float64).eps)
#: ulps allowed between two implementations of one ``exp`` / ``log`` / ``log10`` / ``pow`` call: numpy's own
#: accuracy tests hold its float64 versions (SIMD ones included) to 1 ulp of the correctly rounded result,
#: glibc documents 1 ulp for these too, so two of them differ by at most 2 ulp; 4 leaves a factor 2
ULPS_PER_CALL = 4
#: absolute tolerance of a link probability P computed with two implementations of log10 / pow / exp:
#: the dB value ``10 log10(ratio)`` moves by ``10 |log10(ratio)| 4 eps`` (< 2e-14 dB over the curves'
#: -6.2 to 16 dB), the steepest shipped PER curve is 0.2 per dB (its log-domain interpolation adds one exp,
#: 4 ulp), the PSCCH curve at most 1.73 per unit of ``ln(linear SINR)`` (its ``10^(x/10)`` adds 4 ulp):
#: |dP| < 1e-14 everywhere; 1e-13 leaves a factor 10 and is still 1e-13 of a probability
P_ATOL = 1e-13


def ar1_tolerance(rho: Any, z_prev: Any, w: Any) -> Any:
    """The absolute tolerance between two evaluations of the shadowing AR(1) step
    ``z = rho z_prev + sqrt(1 - rho^2) w`` whose ``rho = exp(-D / d_c)`` comes from two ``exp``
    implementations (the kernel's libm one, numpy's possibly SIMD one) and differs by up to
    :data:`ULPS_PER_CALL` ulp, propagated: ``d(rho z_prev) = rho delta |z_prev|``; ``1 - rho^2`` moves by
    ``2 rho^2 delta``, so ``s = sqrt(1 - rho^2)`` by ``rho^2 delta / s`` (and never more than
    ``sqrt(2 rho^2 delta)``, near ``rho = 1``); plus both sides' own rounding of the step (a few ulp of
    its terms). A relative tolerance alone fails where the two terms cancel."""
    rho, z_prev, w = (np.asarray(x, dtype=np.float64) for x in (rho, z_prev, w))
    delta = ULPS_PER_CALL * EPS
    s = np.sqrt(1.0 - rho * rho)
    d_var = 2.0 * rho * rho * delta
    with np.errstate(divide="ignore"):
        ds = np.minimum(np.where(s > 0, d_var / (2.0 * s), np.inf), np.sqrt(d_var))
    return rho * delta * np.abs(z_prev) + ds * np.abs(w) + 4.0 * EPS * (np.abs(rho * z_prev) + s * np.abs(w))


@pytest.fixture()
def tolerances() -> SimpleNamespace:
    """The tolerances of the kernel-equality tests (compiled kernel against numpy reference where the two
    use different ``exp`` / ``log10`` / ``pow`` implementations): ``eps``, ``ulps_per_call``, ``p_atol``,
    ``assert_sums_close(a, b, n, name)`` and ``ar1(rho, z_prev, w)`` (this module's definitions)."""
    return SimpleNamespace(
        eps=EPS,
        ulps_per_call=ULPS_PER_CALL,
        p_atol=P_ATOL,
        assert_sums_close=assert_sums_close,
        ar1=ar1_tolerance,
    )


@pytest.fixture()
def write_fcd() -> Callable[..., Any]:
    """``write(path, seconds, vehicles_at)``: a SUMO FCD trace (``<fcd-export>``) of 0.1 s steps from 0 to
    ``seconds``, ``vehicles_at(t)`` giving the ``(id, x)`` of the vehicles present at time ``t`` (on the
    paper grid's road ``y = 56.25`` m); returns ``path``."""
    from pathlib import Path

    def write(path: Path, seconds: float, vehicles_at: Callable[[float], list[tuple[str, float]]]) -> Path:
        lines = ["<fcd-export>"]
        for k in range(round(seconds / 0.1) + 1):
            t = k * 0.1
            lines.append(f'<timestep time="{t:.2f}">')
            for v, x in vehicles_at(t):
                lines.append(f'<vehicle id="{v}" x="{x:.3f}" y="56.25" angle="90" speed="1"/>')
            lines.append("</timestep>")
        lines.append("</fcd-export>")
        path.write_text("\n".join(lines))
        return path

    return write
