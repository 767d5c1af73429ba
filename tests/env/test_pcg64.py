"""The compiled PCG64 draws (cv2x_marl.env.pcg64) against numpy's Generator, draw for draw.

These are integer and bit-exact float computations (no transcendental function on the usual path; the
rare tail and wedge draws call the C library's ``log1p`` / ``exp`` as numpy does), so equality is asked
bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.env.pcg64 import (
    ZIGGURAT_F64,
    ZIGGURAT_U64,
    advance,
    draw_column_into,
    draw_period_into,
    jump_table,
    next_uint64,
    set_state,
    standard_exponential,
    standard_normal,
    state_of,
)
from cv2x_marl.rng import env_stream


def test_state_round_trip() -> None:
    """The four words are numpy's 128-bit state and increment; writing them back leaves the generator as it was."""
    rng = np.random.default_rng(12345)
    rng.random(3)
    before = rng.bit_generator.state
    state = state_of(rng)
    assert (int(state[0]) << 64) | int(state[1]) == before["state"]["state"]
    assert (int(state[2]) << 64) | int(state[3]) == before["state"]["inc"]
    other = np.random.default_rng(1)
    set_state(other, state)
    assert other.bit_generator.state == before


def test_raw_words_equal_numpy() -> None:
    state = state_of(np.random.default_rng(7))
    ref = np.random.default_rng(7).bit_generator.random_raw(1000)
    got = np.array([next_uint64(state) for _ in range(1000)], dtype=np.uint64)
    assert np.array_equal(got, ref)


@pytest.mark.parametrize("seed", [0, 1, 99, 2**40 + 3])
def test_single_draws_equal_numpy(seed: int) -> None:
    """Each scalar draw, interleaved as a kernel would, against the same calls on numpy's Generator."""
    ours = state_of(np.random.default_rng(seed))
    ref = np.random.default_rng(seed)
    for _ in range(3000):
        assert standard_exponential(ours, ZIGGURAT_U64, ZIGGURAT_F64) == ref.standard_exponential()
        assert standard_normal(ours, ZIGGURAT_U64, ZIGGURAT_F64) == ref.standard_normal()
    got = np.random.default_rng(0)
    set_state(got, ours)
    assert got.bit_generator.state == ref.bit_generator.state


def test_period_draws_equal_numpy_over_many_streams() -> None:
    """300 episode streams x 3 periods of 21 x 21 pairs (about 1.2 M draws, the rare tail and wedge
    branches included: about 1 % of ziggurat draws), every array bit for bit and the final states equal."""
    n = 21
    u, e, z = (np.empty((n, n)) for _ in range(3))
    tails = 0
    for seed in range(300):
        rng = env_stream(seed, "measurement")
        ref = env_stream(seed, "measurement")
        state = state_of(rng)
        for _ in range(3):
            draw_period_into(state, ZIGGURAT_U64, ZIGGURAT_F64, u, e, z)
            assert np.array_equal(u, ref.random((n, n)))
            assert np.array_equal(e, ref.standard_exponential((n, n)))
            z_ref = ref.standard_normal((n, n))
            assert np.array_equal(z, z_ref)
            tails += int((np.abs(z_ref) > 3.6541528853610088).sum())  # beyond the ziggurat base r: the tail branch
        set_state(rng, state)
        assert rng.bit_generator.state == ref.bit_generator.state
    assert tails > 0  # the tail branch was exercised


def test_column_draws_equal_full_draws() -> None:
    """One column written, the state advanced as by the full draw; the other entries untouched."""
    n = 21
    jumps = jump_table(n)
    for seed in range(40):
        col = seed % n
        full = state_of(np.random.default_rng(seed))
        part = full.copy()
        fu, fe, fz = (np.empty((n, n)) for _ in range(3))
        cu, ce, cz = (np.full((n, n), -7.0) for _ in range(3))
        for _ in range(3):
            draw_period_into(full, ZIGGURAT_U64, ZIGGURAT_F64, fu, fe, fz)
            draw_column_into(part, jumps, ZIGGURAT_U64, ZIGGURAT_F64, col, cu, ce, cz)
            for got, ref in ((cu, fu), (ce, fe), (cz, fz)):
                assert np.array_equal(got[:, col], ref[:, col])
                assert (np.delete(got, col, axis=1) == -7.0).all()
            assert np.array_equal(part, full)


def test_jump_table_closed_form_and_advance() -> None:
    """Row m is (M^m, 1 + M + ... + M^(m-1)) mod 2^128, and advancing by it equals m single steps."""
    mult = 0x2360ED051FC65DA44385DF649FCCF645
    table = jump_table(4)
    expect = [(1, 0), (mult, 1), (mult * mult, 1 + mult), (mult**3, 1 + mult + mult * mult)]
    for m, (a, total) in enumerate(expect):
        a %= 1 << 128
        total %= 1 << 128
        assert (int(table[m, 0]) << 64) | int(table[m, 1]) == a
        assert (int(table[m, 2]) << 64) | int(table[m, 3]) == total
    stepped = state_of(np.random.default_rng(5))
    jumped = stepped.copy()
    for _ in range(3):
        next_uint64(stepped)
    advance(jumped, table[3])
    assert np.array_equal(stepped, jumped)


def test_refusals() -> None:
    with pytest.raises(ValueError, match="PCG64"):
        state_of(np.random.Generator(np.random.MT19937(1)))
    with pytest.raises(ValueError, match="count"):
        jump_table(-1)


@pytest.mark.parametrize("bit_generator", [np.random.PCG64, np.random.MT19937])
def test_measurement_window_draws_equal_numpy(bit_generator: type) -> None:
    """Measurements.start's window of draws (compiled for PCG64, numpy's calls otherwise) against numpy."""
    from cv2x_marl.env.measurement import _draw_window

    rng = np.random.Generator(bit_generator(17))
    ref = np.random.Generator(bit_generator(17))
    u, e, z = (np.empty((10, 21, 21)) for _ in range(3))
    _draw_window(rng, u, e, z)
    for k in range(10):
        assert np.array_equal(u[k], ref.random((21, 21)))
        assert np.array_equal(e[k], ref.standard_exponential((21, 21)))
        assert np.array_equal(z[k], ref.standard_normal((21, 21)))
    assert rng.random(4).tolist() == ref.random(4).tolist()  # left where numpy leaves it
