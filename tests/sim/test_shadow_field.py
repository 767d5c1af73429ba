"""The shadowing field that follows the vehicles (sim/shadow_field.py, sim/kernels/field.py).

Statistics: with the snapshot's value ``s0 ~ N(0, sigma^2)`` drawn independently of the waves, the
conditional field ``s = rho s0 + sigma (G - rho G0)`` has covariance ``sigma^2 c(x, x')`` with
``c = exp(-|dx_a - dx_a'| / d) exp(-|dx_b - dx_b'| / d)`` (TR 36.885 A.1.4's exponential, per end), so
its correlation with the start value is ``exp(-(r_a + r_b) / d)`` and its variance ``sigma^2`` everywhere.
Each pair of a draw has its own waves and its own ``s0``, so the pairs of one draw are independent
samples. Tolerances: 4 standard errors (Fisher z: ``1 / sqrt(n - 3)`` on ``atanh(r)``; the variance:
``sqrt(2 / (n - 1))`` relative, the Gaussian value; the field's excess kurtosis ``-1.5 / W`` only lowers
it), so a correct field fails with probability below 1e-4 per check (the seeds are fixed anyway).
"""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.config import from_dict, preset
from cv2x_marl.rng import env_stream
from cv2x_marl.sim.shadow_field import ShadowField

CFG = preset("paper")
D_M = float(CFG.channel.shadowing_decorrelation_m)


def _draw(n: int, seed: int, los_fraction: float = 0.0, cfg=CFG) -> tuple[ShadowField, np.ndarray]:
    """A field of n vehicles at random starts with s0 ~ N(0, sigma^2) per pair (its LOS state's sigma)."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.0, 500.0, size=(n, 2))
    los = np.triu(rng.random((n, n)) < los_fraction, 1)
    los = los | los.T
    sigma = np.where(los, cfg.channel.shadowing_std_db, cfg.channel.shadowing_nlos_std_db)
    s0 = np.triu(rng.normal(size=(n, n)) * sigma, 1)
    s0 = s0 + s0.T
    return ShadowField.draw(cfg, start, s0, los, rng), start


def _moved(start: np.ndarray, movers: np.ndarray, r_m: float, rng: np.random.Generator) -> np.ndarray:
    """``start`` with vehicles ``movers`` displaced by ``r_m`` in random directions."""
    pos = start.copy()
    ang = rng.uniform(0.0, 2.0 * np.pi, size=movers.size)
    pos[movers] += r_m * np.stack((np.cos(ang), np.sin(ang)), axis=1)
    return pos


def _fisher_ok(x: np.ndarray, y: np.ndarray, rho: float) -> tuple[float, float, float]:
    r = float(np.corrcoef(x, y)[0, 1])
    se = 1.0 / np.sqrt(x.size - 3)
    return r, abs(np.arctanh(r) - np.arctanh(rho)), 4.0 * se


def test_equal_to_the_snapshot_at_the_start_and_symmetric() -> None:
    field, start = _draw(12, 0, 0.5)
    n = start.shape[0]
    off = ~np.eye(n, dtype=bool)
    for compiled in (True, False):
        s = field.shadow_db(start, compiled=compiled)
        assert np.array_equal(s[off], field.shadow0_db[off])  # exactly: no end moved
        assert np.all(np.diag(s) == 0.0)
    pos = start + np.random.default_rng(1).uniform(-40.0, 40.0, size=(n, 2))
    for compiled in (True, False):
        s = field.shadow_db(pos, compiled=compiled)
        assert np.array_equal(s, s.T) and np.all(np.diag(s) == 0.0)
    # only vehicle 3 moved: the pairs without it keep the snapshot's value, exactly
    one = start.copy()
    one[3] += [7.0, -2.0]
    s = field.shadow_db(one)
    keep = off.copy()
    keep[3, :] = keep[:, 3] = False
    assert np.array_equal(s[keep], field.shadow0_db[keep])
    assert np.all(s[3, off[3]] != field.shadow0_db[3, off[3]])


@pytest.mark.kernel_equality
def test_compiled_equals_the_numpy_reference() -> None:
    """numba's cos / exp against numpy's: equal to 1e-9 dB (measured about 1e-12)."""
    field, start = _draw(15, 2, 0.3)
    rng = np.random.default_rng(3)
    for scale in (1.0, 30.0, 400.0):
        pos = start + rng.uniform(-scale, scale, size=start.shape)
        np.testing.assert_allclose(field.shadow_db(pos), field.shadow_db(pos, compiled=False), rtol=0, atol=1e-9)
    # the mover's row at many candidates equals row `mover` of the full field with it there
    pos = start + rng.uniform(-20.0, 20.0, size=start.shape)
    for mover in (0, 7, 14):
        cand = pos[mover] + rng.uniform(-60.0, 60.0, size=(25, 2))
        rows = field.row_db(mover, pos, cand)
        for m, c in enumerate(cand):
            q = pos.copy()
            q[mover] = c
            np.testing.assert_allclose(rows[m], field.shadow_db(q, compiled=False)[mover], rtol=0, atol=1e-9)


@pytest.mark.parametrize("r_m", [3.0, 10.0, 25.0])
def test_correlation_with_the_start_is_exponential_in_the_displacement(r_m: float) -> None:
    """Even vehicles move by r, odd ones stay: (even, odd) pairs have one end moved (rho = exp(-r/d)),
    (even, even) pairs both (exp(-2r/d))."""
    n = 40
    rng = np.random.default_rng(10)
    x1, y1, x2, y2 = [], [], [], []
    even = np.arange(0, n, 2)
    odd = np.arange(1, n, 2)
    iu = np.triu_indices(even.size, 1)
    for seed in range(12):
        field, start = _draw(n, 100 + seed)
        s = field.shadow_db(_moved(start, even, r_m, rng))
        x1.append(field.shadow0_db[np.ix_(even, odd)].ravel())
        y1.append(s[np.ix_(even, odd)].ravel())
        x2.append(field.shadow0_db[np.ix_(even, even)][iu])
        y2.append(s[np.ix_(even, even)][iu])
    for xs, ys, rho in ((x1, y1, np.exp(-r_m / D_M)), (x2, y2, np.exp(-2.0 * r_m / D_M))):
        r, err, tol = _fisher_ok(np.concatenate(xs), np.concatenate(ys), rho)
        assert err < tol, (r_m, r, rho, err, tol)


def test_correlation_between_two_moved_positions() -> None:
    """One end at 10 m and at 25 m along the same line: corr exp(-15/d) (the covariance sigma^2 c(x, x'))."""
    n = 40
    rng = np.random.default_rng(11)
    movers = np.arange(0, n, 2)
    stay = np.arange(1, n, 2)
    xs, ys = [], []
    for seed in range(12):
        field, start = _draw(n, 200 + seed)
        ang = rng.uniform(0.0, 2.0 * np.pi, size=movers.size)
        u = np.stack((np.cos(ang), np.sin(ang)), axis=1)
        a, b = start.copy(), start.copy()
        a[movers] += 10.0 * u
        b[movers] += 25.0 * u
        xs.append(field.shadow_db(a)[np.ix_(movers, stay)].ravel())
        ys.append(field.shadow_db(b)[np.ix_(movers, stay)].ravel())
    r, err, tol = _fisher_ok(np.concatenate(xs), np.concatenate(ys), np.exp(-15.0 / D_M))
    assert err < tol, (r, err, tol)


def test_variance_far_from_the_start_is_the_presets() -> None:
    """200 m away (rho = e^-20): the LOS pairs' variance sigma_LOS^2, the NLOS pairs' sigma_NLOS^2."""
    n = 40
    rng = np.random.default_rng(12)
    los_s, nlos_s = [], []
    iu = np.triu_indices(n, 1)
    for seed in range(8):
        field, start = _draw(n, 300 + seed, los_fraction=0.5)
        s = field.shadow_db(_moved(start, np.arange(n), 200.0, rng))[iu]
        los = field.sigma_db[iu] == CFG.channel.shadowing_std_db
        los_s.append(s[los])
        nlos_s.append(s[~los])
    for samples, sigma in (
        (np.concatenate(los_s), CFG.channel.shadowing_std_db),
        (np.concatenate(nlos_s), CFG.channel.shadowing_nlos_std_db),
    ):
        var = float(np.mean(samples**2))  # mean 0 by construction
        tol = 4.0 * np.sqrt(2.0 / (samples.size - 1))
        assert abs(var / sigma**2 - 1.0) < tol, (var, sigma**2, tol)
        assert abs(samples.mean()) < 4.0 * sigma / np.sqrt(samples.size)


def test_zero_std_gives_a_zero_field() -> None:
    cfg = from_dict({"channel": {"shadowing_std_db": 0.0, "shadowing_nlos_std_db": 0.0}}, CFG)
    n = 6
    rng = np.random.default_rng(0)
    start = rng.uniform(0.0, 300.0, size=(n, 2))
    field = ShadowField.draw(cfg, start, np.zeros((n, n)), np.zeros((n, n), dtype=bool), env_stream(1, "shadow_field"))
    pos = start + rng.uniform(-100.0, 100.0, size=(n, 2))
    assert np.array_equal(field.shadow_db(pos), np.zeros((n, n)))
    assert np.array_equal(field.shadow_db(pos, compiled=False), np.zeros((n, n)))


def test_draws_depend_only_on_the_rng() -> None:
    rng = np.random.default_rng(5)
    n = 8
    start = rng.uniform(0.0, 300.0, size=(n, 2))
    s0 = np.triu(rng.normal(size=(n, n)), 1)
    s0 = s0 + s0.T
    los = np.zeros((n, n), dtype=bool)
    pos = start + rng.uniform(-50.0, 50.0, size=(n, 2))
    a = ShadowField.draw(CFG, start, s0, los, env_stream(7, "shadow_field")).shadow_db(pos)
    b = ShadowField.draw(CFG, start, s0, los, env_stream(7, "shadow_field")).shadow_db(pos)
    c = ShadowField.draw(CFG, start, s0, los, env_stream(8, "shadow_field")).shadow_db(pos)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)


# -- the links with the field (sim/ground_truth.py) ----------------------------------------------


@pytest.fixture(scope="module")
def links_with_field():
    from cv2x_marl.sim import Simulator
    from cv2x_marl.sim.ground_truth import SnapshotLinks

    cfg = from_dict({"sim": {"warmup_subframes": 500}, "link": {"inband_emission_db": -25.0}}, CFG)
    snap = Simulator(cfg).reset(seed=5)
    field = ShadowField.draw(cfg, snap.positions_m, snap.shadowing_db, snap.los, env_stream(5, "shadow_field"))
    return SnapshotLinks(cfg, snap, field=field), SnapshotLinks(cfg, snap, compiled=False, field=field), snap


@pytest.mark.kernel_equality
def test_links_with_the_field_compiled_equal_numpy(links_with_field) -> None:
    sl, ref, snap = links_with_field
    assert sl.compiled and not ref.compiled
    rng = np.random.default_rng(0)
    pos = snap.positions_m + rng.uniform(-30.0, 30.0, size=snap.positions_m.shape)
    np.testing.assert_allclose(sl.success(pos), ref.success(pos), rtol=1e-9, atol=1e-12)
    # at the start the field is the snapshot's shadowing: the links without a field, to the bit
    from cv2x_marl.sim.ground_truth import SnapshotLinks

    plain = SnapshotLinks(sl.config, snap)
    assert np.array_equal(sl.success(snap.positions_m), plain.success(snap.positions_m))
    # moved, the field differs from the snapshot's shadowing
    assert not np.allclose(sl.success(pos), plain.success(pos))


@pytest.mark.kernel_equality
def test_mover_row_with_the_field_equals_the_evaluated_row(links_with_field) -> None:
    """The mover's own links read the field at the candidate, the interference at the current positions:
    row `mover` of evaluate() with the mover there (numpy reference, 1e-9)."""
    from cv2x_marl.sim.kernels import row_utility

    sl, ref, snap = links_with_field
    rng = np.random.default_rng(1)
    pos = snap.positions_m + rng.uniform(-20.0, 20.0, size=snap.positions_m.shape)
    for mover in (0, 4, snap.positions_m.shape[0] - 1):
        cand = pos[mover] + rng.uniform(-60.0, 60.0, size=(12, 2))
        row = sl.mover_row(mover, pos)
        got = row.success(cand)
        want = np.empty_like(got)
        for m, c in enumerate(cand):
            q = pos.copy()
            q[mover] = c
            want[m] = ref.success(q)[mover]
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
        assert (got > 0).sum() > 5
        np.testing.assert_array_equal(row.utility(cand, 1e-3), row_utility(got, row.target_row, 1e-3))
        np.testing.assert_array_equal(row.utility(cand, 1e-3, chunk=5), row.utility(cand, 1e-3))


def test_sensed_row_keeps_the_own_shadowing_measured_where_it_stands(links_with_field) -> None:
    """With a field the estimate's own links keep the field at the current position for every candidate:
    at the current position it equals the estimate without moving; elsewhere it equals a sensed row
    built on the snapshot links whose shadowing is the field's at the current positions."""
    import dataclasses

    from cv2x_marl.sim.ground_truth import SnapshotLinks

    sl, _ref, snap = links_with_field
    rng = np.random.default_rng(2)
    pos = snap.positions_m + rng.uniform(-20.0, 20.0, size=snap.positions_m.shape)
    frozen = SnapshotLinks(sl.config, dataclasses.replace(snap, shadowing_db=sl.field.shadow_db(pos)))
    for mover in (1, 6):
        cand = pos[mover] + rng.uniform(-80.0, 80.0, size=(10, 2))
        np.testing.assert_allclose(
            sl.sensed_row(mover, pos).success(cand), frozen.sensed_row(mover, pos).success(cand), rtol=1e-12, atol=1e-15
        )


def test_lattice_rows_equal_the_rows() -> None:
    """The rotation recurrence of lattice_row_db against row_db at the same points: 1e-9 dB (measured
    about 1e-10 over 51 steps with the heavy tail of the wave numbers)."""
    field, start = _draw(12, 4, 0.5)
    rng = np.random.default_rng(5)
    pos = start + rng.uniform(-30.0, 30.0, size=start.shape)
    for mover, pitch, shape in ((0, 20.0, (51, 51)), (5, 1.0, (11, 7)), (11, 5.0, (3, 40))):
        origin = pos[mover] - 0.5 * pitch * np.array(shape)
        axes = [origin[c] + np.arange(shape[c]) * pitch for c in range(2)]
        gx, gy = np.meshgrid(*axes, indexing="ij")
        pts = np.stack((gx.ravel(), gy.ravel()), axis=1)
        got = field.lattice_row_db(mover, pos, origin, pitch, shape)
        np.testing.assert_allclose(got, field.row_db(mover, pos, pts), rtol=0, atol=1e-9)
    # a lattice point at the start of an unmoved scene: exactly the snapshot's value
    got = field.lattice_row_db(2, start, start[2], 1.0, (1, 1))[0]
    keep = np.arange(start.shape[0]) != 2
    assert np.array_equal(got[keep], field.shadow0_db[2, keep])


def test_mover_links_with_fields_equal_the_snapshot_links_row(links_with_field) -> None:
    """MoverLinks with a field per copy (and a copy without): row `mover` of SnapshotLinks with the same
    field, the mover moved, the others at the snapshot (1e-9)."""
    from cv2x_marl.sim.ground_truth import MoverLinks, SnapshotLinks

    sl, _ref, snap = links_with_field
    movers = [2, 9, 2]
    ml = MoverLinks.from_snapshots(sl.config, [snap, snap, snap], movers, fields=[sl.field, sl.field, None])
    moved = ml.start_m + np.random.default_rng(4).uniform(-40.0, 40.0, size=(3, 2))
    got = ml.success(moved)
    plain = SnapshotLinks(sl.config, snap)
    for b, (i, links) in enumerate(zip(movers, (sl, sl, plain), strict=True)):
        pos = snap.positions_m.copy()
        pos[i] = moved[b]
        np.testing.assert_allclose(got[b], np.where(ml.target[b], links.success(pos)[i], 0.0), rtol=1e-9, atol=1e-12)
    assert ml.take(np.array([1, 1])).fields == (sl.field, sl.field)


def test_rows_on_a_search_grid_use_the_lattice_and_equal_row_db() -> None:
    """A search's candidates (the start, then a linspace grid filtered to a disc) are recognised as a lattice;
    rows_db equals row_db to 1e-9 dB; scattered candidates fall back to row_db."""
    from cv2x_marl.sim.shadow_field import square_lattice

    field, start = _draw(10, 6)
    pos = start.copy()
    axes = [np.linspace(pos[3, c] - 100.0, pos[3, c] + 100.0, 41) for c in range(2)]
    gx, gy = np.meshgrid(*axes, indexing="ij")
    grid = np.stack((gx.ravel(), gy.ravel()), axis=1)
    grid = grid[np.hypot(*(grid - pos[3]).T) <= 100.0]
    cand = np.concatenate([pos[3][None] + 0.3, grid])
    assert square_lattice(cand) is None and square_lattice(grid) is not None
    np.testing.assert_allclose(field.rows_db(3, pos, cand), field.row_db(3, pos, cand), rtol=0, atol=1e-9)
    scattered = pos[3] + np.random.default_rng(0).uniform(-50.0, 50.0, size=(100, 2))
    assert square_lattice(scattered) is None
    assert np.array_equal(field.rows_db(3, pos, scattered), field.row_db(3, pos, scattered))


def test_gathered_mover_pairs_and_their_row_equal_the_full_field() -> None:
    """gather_mover_pairs against numpy fancy indexing (pair (min, max) by the other end), and the row from
    the gathered arrays equal to row ``mover`` of the compiled full field bit for bit (same pair_field_db calls)."""
    from cv2x_marl.sim.kernels.field import field_pairs_row_into, field_shadow_db, gather_mover_pairs

    field, start = _draw(9, 5, 0.4)
    n, w = field.n, field.phase.shape[-1]
    rng = np.random.default_rng(8)
    pos = start + rng.uniform(-30.0, 30.0, size=start.shape)
    for mover in (0, 4, 8):
        outs = (np.empty(n), np.empty(n), np.empty((n, w, 2)), np.empty((n, w, 2)), np.empty((n, w)), np.empty(n))
        gather_mover_pairs(
            mover, field.shadow0_db, field.sigma_db, field.k_lo, field.k_hi, field.phase, field.g0, *outs
        )
        others = np.array([j for j in range(n) if j != mover])
        lo, hi = np.minimum(mover, others), np.maximum(mover, others)
        refs = (field.shadow0_db, field.sigma_db, field.k_lo, field.k_hi, field.phase, field.g0)
        for got, full in zip(outs, refs, strict=True):
            assert np.array_equal(got[others], full[lo, hi])
            assert (got[mover] == 0.0).all()
        row = np.empty(n)
        x, y = pos[mover] + np.array([12.5, -3.0])
        field_pairs_row_into(x, y, pos, mover, field.start_m, outs[0], outs[1], field.decorrelation_m, *outs[2:], row)
        moved = pos.copy()
        moved[mover] = (x, y)
        full_row = field_shadow_db(moved, field.start_m, field.shadow0_db, field.sigma_db, field.decorrelation_m,
                                   field.k_lo, field.k_hi, field.phase, field.g0)[mover]  # fmt: skip
        assert np.array_equal(row, full_row)
