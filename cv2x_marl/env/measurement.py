"""What a Mode 4 vehicle has measured after its sensing window: the RSRP of every neighbour's link.

Observation version 3 (``cv2x/Mobility-v3``, ``cv2x/SingleMover-v3``, ``cv2x/Cooperative-v0``) and the
``sensing`` planner on it read these measurements instead of the exact mean power.

Every 100-ms period each vehicle j sends one packet (its SPS reservation); vehicle i decodes it with
probability ``P[j, i]`` of the link model (:meth:`cv2x_marl.sim.ground_truth.SnapshotLinks.evaluate`:
0 within half duplex, where i transmits in j's subframe). A decoded packet gives i one power sample

    x = rx_mw[j, i] * |h|^2,   |h|^2 ~ Exp(1)   (Rayleigh fast fading)

with ``rx_mw`` the mean received power at the positions of that period (``SnapshotLinks.rx_dbm``: path
loss and shadowing, the shadowing field included). After each period vehicle i reports, for every
neighbour j with at least one decoded packet in the last ``window`` periods (the sensing window of
TS 36.213 clause 14.1.1.6: 1000 ms, 10 periods), the linear mean of those samples in dBm plus a
measurement error ``e ~ N(0, error_db^2)`` drawn per report (the RSRP accuracy of TS 36.133, see
:data:`cv2x_marl.env.options.RSRP_ERROR_DB`):

    rsrp_dbm[j, i] = 10 log10(mean of the decoded samples in the window) + e

A neighbour none of whose packets in the window was decoded keeps its last report (stale); ``age[j, i]``
counts the periods since the last decoded packet (0: one was decoded this period). A neighbour never
heard has ``rsrp_dbm = nan``.

At reset the window is filled as if the vehicles had stood at their start positions for the whole
window (``window`` periods with the start's ``rx_mw`` and ``P``); each env step is one period at the
new positions. Randomness: the episode's ``measurement`` stream
(:func:`cv2x_marl.rng.env_stream`), drawn per period in this order: the decoding uniforms
``U [N, N]`` (decoded where ``U < P``), the fading ``Exp(1) [N, N]``, the errors ``N(0, 1) [N, N]``
(scaled by ``error_db``), always for all pairs; the reports are updated by a compiled pass over the
receivers asked for (all, or the mover's column alone in a one-mover step: the same values).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.env.pcg64 import ZIGGURAT_F64, ZIGGURAT_U64, draw_period_into, set_state, state_of

FloatArray = NDArray[np.float64]

#: RSRP (dBm) at which the observation's scaled entry ``(rsrp_dbm - RSRP_REF_DBM) / RSRP_SCALE_DB`` is 0
RSRP_REF_DBM = -100.0
#: dB per unit of the observation's scaled RSRP entry
RSRP_SCALE_DB = 20.0


def draw_period(
    rng: np.random.Generator, p: FloatArray, error_db: float
) -> tuple[NDArray[np.bool_], FloatArray, FloatArray]:
    """One period's draws for all N x N pairs: (decoded [N, N], fading |h|^2 [N, N], error [N, N] dB).

    Args:
        rng: the episode's ``measurement`` stream.
        p: [N(tx), N(rx)] decoding probability of each link.
        error_db: standard deviation of the measurement error (dB).
    """
    n = p.shape[0]
    decoded = rng.random((n, n)) < p
    fade = rng.standard_exponential((n, n))
    error = rng.standard_normal((n, n)) * error_db
    return decoded, fade, error


@dataclass
class Measurements:
    """The RSRP reports of every ordered pair, kept over the sensing window (module docstring).

    Attributes:
        window: the sensing window (periods).
        error_db: standard deviation of the report error (dB).
        rng: the ``measurement`` stream of the episode.
        power_mw: [W, N, N] the decoded samples of the last W periods (0 where not decoded), a ring.
        count: [W, N, N] 1 where the sample of that period was decoded.
        head: the ring slot the next period writes.
        rsrp_dbm: [N(tx), N(rx)] the last report (nan: never heard; -inf never: samples are > 0).
        age: [N(tx), N(rx)] periods since the last decoded packet (int64).
    """

    window: int
    error_db: float
    rng: np.random.Generator
    power_mw: FloatArray
    count: FloatArray
    head: int
    rsrp_dbm: FloatArray
    age: NDArray[np.int64]

    @classmethod
    def start(
        cls, rx_dbm: FloatArray, p: FloatArray, window: int, error_db: float, rng: np.random.Generator
    ) -> Measurements:
        """The measurements after a window at the start positions: ``window`` periods of :meth:`update`
        with the start's ``rx_dbm`` and ``p`` (the reports of the last one cover them all).

        Args:
            rx_dbm: [N(tx), N(rx)] mean received power at the start positions (dBm; -inf: none).
            p: [N(tx), N(rx)] decoding probability at the start positions.
            window: periods in the sensing window (>= 1).
            error_db: standard deviation of the report error (dB).
            rng: the episode's ``measurement`` stream (:func:`cv2x_marl.rng.env_stream`).
        """
        n = p.shape[0]
        state = cls(
            int(window),
            float(error_db),
            rng,
            np.zeros((window, n, n)),
            np.zeros((window, n, n)),
            0,
            np.full((n, n), np.nan),
            np.zeros((n, n), dtype=np.int64),
        )
        uniform, fade, normal = (np.empty((window, n, n)) for _ in range(3))
        _draw_window(rng, uniform, fade, normal)
        _start_window(
            state.power_mw, state.count, state.rsrp_dbm, state.age, np.ascontiguousarray(rx_dbm),
            np.ascontiguousarray(p), uniform, fade, normal, state.error_db,
        )  # fmt: skip
        return state

    def update(self, rx_dbm: FloatArray, p: FloatArray, receivers: NDArray[np.int64] | None = None) -> None:
        """One period at the current positions: each link's packet, decoded or not, and the reports.

        The draws cover every pair (:func:`draw_period`'s order), whatever ``receivers``; the reports of
        the receivers' columns are updated (compiled, :func:`update_columns`), bit for bit the same
        whether one column or all are.

        Args:
            rx_dbm: [N(tx), N(rx)] mean received power of this period (dBm).
            p: [N(tx), N(rx)] decoding probability of this period.
            receivers: [R] the columns (receivers) to update (None: all); the others keep their state
                (a one-mover step observes only the mover's).
        """
        n = p.shape[0]
        uniform = self.rng.random((n, n))
        fade = self.rng.standard_exponential((n, n))
        normal = self.rng.standard_normal((n, n))
        cols = _ALL.get(n) if receivers is None else receivers
        if cols is None:
            cols = _ALL[n] = np.arange(n, dtype=np.int64)
        update_columns(
            self.power_mw, self.count, self.head, self.rsrp_dbm, self.age, np.ascontiguousarray(rx_dbm),
            np.ascontiguousarray(p), uniform, fade, normal, self.error_db, cols,
        )  # fmt: skip
        self.head = (self.head + 1) % self.window


def _draw_window(rng: np.random.Generator, uniform: FloatArray, fade: FloatArray, normal: FloatArray) -> None:
    """``W`` periods of :func:`draw_period` into ``uniform``, ``fade``, ``normal`` [W, N, N], in the stream's
    order (per period U, then Exp(1), then N(0, 1)): compiled for a PCG64 stream (the env's: numpy's draws
    bit for bit, :mod:`cv2x_marl.env.pcg64`), numpy's calls for any other bit generator."""
    if rng.bit_generator.state.get("bit_generator") != "PCG64":
        for k in range(uniform.shape[0]):
            rng.random(out=uniform[k])
            rng.standard_exponential(out=fade[k])
            rng.standard_normal(out=normal[k])
        return
    state = state_of(rng)
    _draw_window_pcg64(state, ZIGGURAT_U64, ZIGGURAT_F64, uniform, fade, normal)
    set_state(rng, state)


@njit(cache=True)
def _draw_window_pcg64(
    state: NDArray[np.uint64],
    zig_u64: NDArray[np.uint64],
    zig_f64: FloatArray,
    uniform: FloatArray,
    fade: FloatArray,
    normal: FloatArray,
) -> None:
    for k in range(uniform.shape[0]):
        draw_period_into(state, zig_u64, zig_f64, uniform[k], fade[k], normal[k])


@njit(cache=True)
def _start_window(
    power_mw: FloatArray,
    count: FloatArray,
    rsrp_dbm: FloatArray,
    age: NDArray[np.int64],
    rx_dbm: FloatArray,
    p: FloatArray,
    uniform: FloatArray,
    fade: FloatArray,
    normal: FloatArray,
    error_db: float,
) -> None:
    """``W`` periods of :func:`update_columns` for every receiver with the same ``rx_dbm`` and ``p`` and the
    draws ``uniform``, ``fade``, ``normal`` [W, N, N], in one pass: the samples and ages period by period,
    the report once, from the last period's error (the earlier reports are all overwritten: the window
    then holds every period, so a pair heard in any period is heard in the last report's window)."""
    window = power_mw.shape[0]
    n = rx_dbm.shape[0]
    for j in range(n):
        for i in range(n):
            heard = 0.0
            total = 0.0
            for k in range(window):
                decoded = uniform[k, j, i] < p[j, i]
                if decoded:
                    power_mw[k, j, i] = 10.0 ** (rx_dbm[j, i] / 10.0) * fade[k, j, i]
                    count[k, j, i] = 1.0
                else:
                    power_mw[k, j, i] = 0.0
                    count[k, j, i] = 0.0
                heard += count[k, j, i]
                total += power_mw[k, j, i]
                age[j, i] = 0 if decoded else age[j, i] + 1
            if heard > 0.0:
                rsrp_dbm[j, i] = 10.0 * math.log10(total / heard) + normal[window - 1, j, i] * error_db


#: ``np.arange(n)`` by n: every receiver's column
_ALL: dict[int, NDArray[np.int64]] = {}


@njit(cache=True)
def update_columns(
    power_mw: FloatArray,
    count: FloatArray,
    head: int,
    rsrp_dbm: FloatArray,
    age: NDArray[np.int64],
    rx_dbm: FloatArray,
    p: FloatArray,
    uniform: FloatArray,
    fade: FloatArray,
    normal: FloatArray,
    error_db: float,
    receivers: NDArray[np.int64],
) -> None:
    """One period of the measurements of the receivers' columns, in place (module docstring): decoded
    where ``uniform < p``, the sample ``10^(rx_dbm / 10) * fade`` into ring slot ``head``, the report
    ``10 log10(sum of the window's samples / their count) + error_db * normal`` where any was decoded
    (the sums in slot order), the age. Arrays [W, N, N] / [N, N] as :class:`Measurements`'."""
    window = power_mw.shape[0]
    n = rx_dbm.shape[0]
    for r in range(receivers.shape[0]):
        i = receivers[r]
        for j in range(n):
            decoded = uniform[j, i] < p[j, i]
            if decoded:
                power_mw[head, j, i] = 10.0 ** (rx_dbm[j, i] / 10.0) * fade[j, i]
                count[head, j, i] = 1.0
            else:
                power_mw[head, j, i] = 0.0
                count[head, j, i] = 0.0
            heard = 0.0
            total = 0.0
            for k in range(window):
                heard += count[k, j, i]
                total += power_mw[k, j, i]
            if heard > 0.0:
                rsrp_dbm[j, i] = 10.0 * math.log10(total / heard) + normal[j, i] * error_db
            age[j, i] = 0 if decoded else age[j, i] + 1


def scaled_rsrp(rsrp_dbm: FloatArray) -> FloatArray:
    """The observation's RSRP entry: ``(rsrp_dbm + 100) / 20`` (0 where never heard)."""
    out = (np.asarray(rsrp_dbm) - RSRP_REF_DBM) / RSRP_SCALE_DB
    return np.where(np.isfinite(out), out, 0.0)
