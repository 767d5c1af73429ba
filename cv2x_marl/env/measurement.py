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
(scaled by ``error_db``). All pairs at once (numpy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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
        """The measurements after a window at the start positions.

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
        with np.errstate(over="ignore"):
            rx_mw = 10.0 ** (np.asarray(rx_dbm) / 10.0)
        error = np.zeros((n, n))
        for k in range(window):  # the same draws, in the same order, as ``window`` calls of update()
            decoded, fade, error = draw_period(rng, p, error_db)
            state.power_mw[k] = np.where(decoded, rx_mw * fade, 0.0)
            state.count[k] = decoded
            state.age = np.where(decoded, 0, state.age + 1)
        state._report(error)
        return state

    def _report(self, error: FloatArray) -> None:
        """The reports from the window's samples with this period's errors [N, N] (dB); stale where none."""
        heard = self.count.sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            report = 10.0 * np.log10(self.power_mw.sum(axis=0) / heard) + error
        self.rsrp_dbm = np.where(heard > 0, report, self.rsrp_dbm)

    def update(self, rx_dbm: FloatArray, p: FloatArray) -> None:
        """One period at the current positions: each link's packet, decoded or not, and the reports.

        Args:
            rx_dbm: [N(tx), N(rx)] mean received power of this period (dBm).
            p: [N(tx), N(rx)] decoding probability of this period.
        """
        decoded, fade, error = draw_period(self.rng, p, self.error_db)
        with np.errstate(over="ignore"):
            sample = np.where(decoded, 10.0 ** (np.asarray(rx_dbm) / 10.0) * fade, 0.0)
        k = self.head
        self.power_mw[k] = sample
        self.count[k] = decoded
        self.head = (k + 1) % self.window
        self._report(error)
        self.age = np.where(decoded, 0, self.age + 1)


def scaled_rsrp(rsrp_dbm: FloatArray) -> FloatArray:
    """The observation's RSRP entry: ``(rsrp_dbm + 100) / 20`` (0 where never heard)."""
    out = (np.asarray(rsrp_dbm) - RSRP_REF_DBM) / RSRP_SCALE_DB
    return np.where(np.isfinite(out), out, 0.0)
