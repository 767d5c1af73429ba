"""numpy's ``PCG64`` stream, compiled: the same draws as ``Generator.random`` / ``standard_exponential`` /
``standard_normal``, bit for bit, inside numba kernels.

The batched one-mover step (:mod:`cv2x_marl.env.mover_batch_v3`) draws every copy's measurement period
(:func:`cv2x_marl.env.measurement.draw_period`'s order: ``U [N, N]``, ``Exp(1) [N, N]``, ``N(0, 1) [N, N]``)
inside its compiled loop instead of three numpy calls per copy. A generator's state travels as a
``uint64 [4]`` array ``(state_hi, state_lo, inc_hi, inc_lo)`` (:func:`state_of`, :func:`set_state`), so
that a kernel advances it in place and the ``numpy.random.Generator`` object is brought up to date only
when someone reads it.

What is reproduced (numpy's ``random/src``):

- ``PCG64`` (``pcg64.h``): the 128-bit LCG ``state <- state * M + inc`` (mod 2^128, ``M =
  0x2360ED051FC65DA44385DF649FCCF645``), then the XSL-RR output ``rotr64(hi ^ lo, hi >> 58)``; one
  ``uint64`` per step;
- ``next_double``: ``(next_uint64 >> 11) * 2^-53`` (``Generator.random``);
- ``random_standard_exponential`` and ``random_standard_normal`` (``distributions.c``): the 256-step
  ziggurats with numpy's tables (taken from numba's copy, :mod:`numba.np.random._constants`) and their
  tail and wedge fallbacks (``log1p``, ``exp`` of the C library, as numpy's).

Only generators whose bit generator is ``PCG64`` are accepted (``default_rng``'s, the env's streams of
:func:`cv2x_marl.rng.env_stream`). The buffered half word of ``PCG64`` (``has_uint32``, used by 32-bit
draws) is neither read nor changed: none of the three draws uses it. Tested against numpy draw for draw
(``tests/env/test_pcg64.py``).

Why not numba's own ``Generator`` support (which draws the same numbers): a ``Generator`` argument is unboxed
through Python code at every call (three ``ctypes.cast`` per generator), measured 5.56 us per call against
0.12 us for an array argument, on the env's per-step path; and a signal that lands during that unboxing
crashes the process unless the call is held in :func:`cv2x_marl.interrupts.signals_deferred` (about 4-12 us
more). The state as a ``uint64 [4]`` array costs neither. The simulator's period kernels, called a few
thousand times a second at most, do take numba ``Generator`` arguments.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic
from numba.np.random._constants import (
    fe_double,
    fi_double,
    ke_double,
    ki_double,
    we_double,
    wi_double,
    ziggurat_exp_r,
    ziggurat_nor_inv_r,
    ziggurat_nor_r,
)
from numpy.typing import NDArray

UintArray = NDArray[np.uint64]
FloatArray = NDArray[np.float64]

_MASK64 = (1 << 64) - 1
#: PCG's default 128-bit multiplier (``PCG_DEFAULT_MULTIPLIER_128``), high and low words
_MUL_HI = np.uint64(0x2360ED051FC65DA4)
_MUL_LO = np.uint64(0x4385DF649FCCF645)
_U58 = np.uint64(58)
_U64 = np.uint64(64)
_U63 = np.uint64(63)
_U1 = np.uint64(1)
_U3 = np.uint64(3)
_U8 = np.uint64(8)
_U11 = np.uint64(11)
_BYTE = np.uint64(0xFF)
_MANTISSA = np.uint64(0x000FFFFFFFFFFFFF)
_TWO_M53 = 1.0 / 9007199254740992.0
#: numpy's ziggurat tables: ``uint64 [2, 256]`` rows ``ki_double``, ``ke_double``; ``float64 [4, 256]`` rows
#: ``wi_double``, ``fi_double``, ``we_double``, ``fe_double`` (arguments, not globals: numba reads argument
#: arrays faster than frozen global ones)
ZIGGURAT_U64 = np.ascontiguousarray(np.stack([ki_double, ke_double]), dtype=np.uint64)
ZIGGURAT_F64 = np.ascontiguousarray(np.stack([wi_double, fi_double, we_double, fe_double]), dtype=np.float64)
_KI, _KE = 0, 1
_WI, _FI, _WE, _FE = 0, 1, 2, 3


def state_of(rng: np.random.Generator) -> UintArray:
    """``uint64 [4]`` ``(state_hi, state_lo, inc_hi, inc_lo)`` of ``rng``'s ``PCG64`` bit generator."""
    st = rng.bit_generator.state
    if st.get("bit_generator") != "PCG64":
        raise ValueError(f"rng must use the PCG64 bit generator, got {st.get('bit_generator')!r}")
    s, inc = int(st["state"]["state"]), int(st["state"]["inc"])
    return np.array([s >> 64, s & _MASK64, inc >> 64, inc & _MASK64], dtype=np.uint64)


def set_state(rng: np.random.Generator, state: UintArray) -> None:
    """Put ``state`` (:func:`state_of`'s layout) back into ``rng`` (its ``has_uint32`` buffer kept)."""
    st = dict(rng.bit_generator.state)
    if st.get("bit_generator") != "PCG64":
        raise ValueError(f"rng must use the PCG64 bit generator, got {st.get('bit_generator')!r}")
    hi, lo, inc_hi, inc_lo = (int(v) for v in state)
    st["state"] = {"state": (hi << 64) | lo, "inc": (inc_hi << 64) | inc_lo}
    rng.bit_generator.state = st


@intrinsic
def _mul_hi64(typingctx, a, b):
    """High 64 bits of the 128-bit product ``a * b`` of two ``uint64`` (one LLVM ``i128`` multiply)."""
    if a != types.uint64 or b != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        wide = ir.IntType(128)
        product = builder.mul(builder.zext(args[0], wide), builder.zext(args[1], wide))
        return builder.trunc(builder.lshr(product, ir.Constant(wide, 64)), ir.IntType(64))

    return types.uint64(types.uint64, types.uint64), codegen


@njit(cache=True)
def next_uint64(state: UintArray) -> np.uint64:
    """One ``PCG64`` step of ``state`` (in place) and its XSL-RR output."""
    s_hi = state[0]
    s_lo = state[1]
    # state * M (mod 2^128): the low words' full product plus the cross terms in the high word
    lo = s_lo * _MUL_LO
    carry_hi: np.uint64 = _mul_hi64(s_lo, _MUL_LO)  # type: ignore[call-arg]  # numba's intrinsic hides its signature
    hi = carry_hi + s_hi * _MUL_LO + s_lo * _MUL_HI
    # + inc, with the carry of the low word
    new_lo = lo + state[3]
    carry = _U1 if new_lo < lo else np.uint64(0)
    new_hi = hi + state[2] + carry
    state[0] = new_hi
    state[1] = new_lo
    value = new_hi ^ new_lo
    rot = new_hi >> _U58
    return (value >> rot) | (value << ((_U64 - rot) & _U63))


@njit(cache=True)
def next_double(state: UintArray) -> float:
    """``Generator.random()``: ``(next_uint64 >> 11) * 2^-53``."""
    return float(np.int64(next_uint64(state) >> _U11)) * _TWO_M53


@njit(cache=True)
def _exponential_tail(state: UintArray, zu: UintArray, zf: FloatArray, ri: np.uint64, idx: np.int64) -> float:
    """The draws :func:`standard_exponential`'s first try rejects (about 1 %): the tail, the wedge, a retry."""
    while True:
        x = float(np.int64(ri)) * zf[_WE, idx]
        if idx == 0:
            return ziggurat_exp_r - np.log1p(-next_double(state))
        if (zf[_FE, idx - 1] - zf[_FE, idx]) * next_double(state) + zf[_FE, idx] < np.exp(-x):
            return x
        ri = next_uint64(state) >> _U3
        idx = np.int64(ri & _BYTE)
        ri >>= _U8
        if ri < zu[_KE, idx]:
            return float(np.int64(ri)) * zf[_WE, idx]


@njit(cache=True)
def standard_exponential(state: UintArray, zu: UintArray, zf: FloatArray) -> float:
    """``Generator.standard_exponential()`` (numpy's ``random_standard_exponential``, ziggurat; tables
    :data:`ZIGGURAT_U64`, :data:`ZIGGURAT_F64`)."""
    ri = next_uint64(state) >> _U3
    idx = np.int64(ri & _BYTE)
    ri >>= _U8
    if ri < zu[_KE, idx]:
        return float(np.int64(ri)) * zf[_WE, idx]
    return _exponential_tail(state, zu, zf, ri, idx)


@njit(cache=True)
def _normal_tail(state: UintArray, zu: UintArray, zf: FloatArray, r: np.uint64, idx: np.int64) -> float:
    """The draws :func:`standard_normal`'s first try rejects (about 1 %): the tail, the wedge, a retry
    (``r``: the rejected word shifted right by 8)."""
    while True:
        rabs = (r >> _U1) & _MANTISSA
        x = float(np.int64(rabs)) * zf[_WI, idx]
        if r & _U1:
            x = -x
        if idx == 0:
            while True:
                xx = -ziggurat_nor_inv_r * np.log1p(-next_double(state))
                yy = -np.log1p(-next_double(state))
                if yy + yy > xx * xx:
                    if (rabs >> _U8) & _U1:
                        return -(ziggurat_nor_r + xx)
                    return ziggurat_nor_r + xx
        elif (zf[_FI, idx - 1] - zf[_FI, idx]) * next_double(state) + zf[_FI, idx] < np.exp(-0.5 * x * x):
            return x
        r = next_uint64(state)
        idx = np.int64(r & _BYTE)
        r >>= _U8
        if (r >> _U1) & _MANTISSA < zu[_KI, idx]:
            rabs = (r >> _U1) & _MANTISSA
            x = float(np.int64(rabs)) * zf[_WI, idx]
            return -x if r & _U1 else x


@njit(cache=True)
def standard_normal(state: UintArray, zu: UintArray, zf: FloatArray) -> float:
    """``Generator.standard_normal()`` (numpy's ``random_standard_normal``, ziggurat; tables
    :data:`ZIGGURAT_U64`, :data:`ZIGGURAT_F64`)."""
    r = next_uint64(state)
    idx = np.int64(r & _BYTE)
    r >>= _U8
    rabs = (r >> _U1) & _MANTISSA
    if rabs < zu[_KI, idx]:
        x = float(np.int64(rabs)) * zf[_WI, idx]
        return -x if r & _U1 else x
    return _normal_tail(state, zu, zf, r, idx)


def _split(value: int) -> tuple[int, int]:
    return (value >> 64) & _MASK64, value & _MASK64


def jump_table(count: int) -> UintArray:
    """``uint64 [count + 1, 4]``: row ``m`` advances a ``PCG64`` state by ``m`` steps in one go
    (:func:`advance`): ``(A_hi, A_lo, S_hi, S_lo)`` with ``A = M^m`` and ``S = 1 + M + ... + M^(m-1)``
    (mod 2^128), so that ``state <- A state + S inc``."""
    if count < 0:
        raise ValueError(f"invalid count={count!r}; allowed: an integer >= 0")
    mult = (int(_MUL_HI) << 64) | int(_MUL_LO)
    mod = 1 << 128
    out = np.zeros((count + 1, 4), dtype=np.uint64)
    a, total = 1, 0
    for m in range(count + 1):
        out[m] = (*_split(a), *_split(total))
        total = (total + a) % mod
        a = (a * mult) % mod
    return out


@njit(cache=True)
def _mul128(a_hi: np.uint64, a_lo: np.uint64, b_hi: np.uint64, b_lo: np.uint64) -> tuple[np.uint64, np.uint64]:
    """``a * b`` mod 2^128 as (high, low) words."""
    high: np.uint64 = _mul_hi64(a_lo, b_lo)  # type: ignore[call-arg]  # numba's intrinsic hides its signature
    return high + a_hi * b_lo + a_lo * b_hi, a_lo * b_lo


@njit(cache=True)
def advance(state: UintArray, jump: UintArray) -> None:
    """``state`` advanced by the steps of ``jump`` (a row of :func:`jump_table`), in place: the words those
    steps would have drawn are skipped."""
    s_hi, s_lo = _mul128(jump[0], jump[1], state[0], state[1])
    c_hi, c_lo = _mul128(jump[2], jump[3], state[2], state[3])
    lo = s_lo + c_lo
    carry = _U1 if lo < s_lo else np.uint64(0)
    state[0] = s_hi + c_hi + carry
    state[1] = lo


@njit(cache=True)
def draw_period_into(
    state: UintArray, zu: UintArray, zf: FloatArray, uniform: FloatArray, fade: FloatArray, normal: FloatArray
) -> None:
    """:func:`cv2x_marl.env.measurement.draw_period`'s draws into ``uniform``, ``fade``, ``normal``
    [N, N] (C order), from ``state`` (advanced in place): ``random((N, N))``, then
    ``standard_exponential((N, N))``, then ``standard_normal((N, N))``."""
    draw_column_into(state, np.zeros((0, 4), dtype=np.uint64), zu, zf, -1, uniform, fade, normal)


@njit(cache=True)
def draw_column_into(
    state: UintArray,
    jumps: UintArray,
    zu: UintArray,
    zf: FloatArray,
    col: int,
    uniform: FloatArray,
    fade: FloatArray,
    normal: FloatArray,
) -> None:
    """Column ``col`` of :func:`draw_period_into`'s draws (``col = -1``: all of them): ``state`` advances
    exactly as there (every pair's words drawn), only ``uniform[:, col]``, ``fade[:, col]``,
    ``normal[:, col]`` are written (the other entries are left as they were). The uniforms between two of
    the column are skipped by :func:`advance` (one word each; ``jumps`` = :func:`jump_table` of at least
    N), the other ziggurat draws by their acceptance test alone.

    The usual path of :func:`standard_exponential` / :func:`standard_normal` is written out here: numba
    runs these loops about 4x faster than with the call.
    """
    n0, n1 = uniform.shape
    for a in range(n0):
        if col < 0:
            for b in range(n1):
                uniform[a, b] = next_double(state)
        else:
            advance(state, jumps[col])
            uniform[a, col] = next_double(state)
            advance(state, jumps[n1 - 1 - col])
    for a in range(n0):
        for b in range(n1):
            ri = next_uint64(state) >> _U3
            idx = np.int64(ri & _BYTE)
            ri >>= _U8
            if ri < zu[_KE, idx]:
                if col < 0 or b == col:
                    fade[a, b] = float(np.int64(ri)) * zf[_WE, idx]
            else:
                x = _exponential_tail(state, zu, zf, ri, idx)
                if col < 0 or b == col:
                    fade[a, b] = x
    for a in range(n0):
        for b in range(n1):
            r = next_uint64(state)
            idx = np.int64(r & _BYTE)
            r >>= _U8
            rabs = (r >> _U1) & _MANTISSA
            if rabs < zu[_KI, idx]:
                if col < 0 or b == col:
                    x = float(np.int64(rabs)) * zf[_WI, idx]
                    normal[a, b] = -x if r & _U1 else x
            else:
                x = _normal_tail(state, zu, zf, r, idx)
                if col < 0 or b == col:
                    normal[a, b] = x
