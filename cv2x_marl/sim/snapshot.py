"""The network at one instant, as :meth:`cv2x_marl.sim.simulator.Simulator.snapshot` returns it.

:class:`Snapshot` holds copies of the positions, velocities, SPS resources and the ``[N, N]`` LOS and
shadowing matrices; with the sparse pair state (:func:`~cv2x_marl.sim.memory.uses_sparse_state`) the
simulator returns a :class:`LazySnapshot`, whose matrices :class:`PairMatrices` builds from the pairs in
range when first read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ScenarioConfig
from cv2x_marl.sim import channel
from cv2x_marl.sim.road import Road

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def tx_eirp_dbm(config: ScenarioConfig) -> float:
    """Transmit power plus both antenna gains, dBm."""
    r = config.radio
    return r.tx_power_dbm + r.tx_antenna_gain_dbi + r.rx_antenna_gain_dbi


@dataclass(frozen=True)
class Snapshot:
    """The network at one instant: what the env (and GBMU) start from.

    Attributes:
        subframe: absolute subframe index of the snapshot.
        positions_m: [N, 2] positions.
        velocities_mps: [N, 2] velocity vectors.
        slot: [N] subframe of each vehicle's reserved resource within the period, ``[0, RRI)``.
        subchannel: [N] subchannel of each reserved resource.
        generation_slot: [N] slot at which each vehicle generates its packets.
        counter: [N] SPS reselection counters.
        los: [N, N] line-of-sight flags (symmetric).
        shadowing_db: [N, N] shadowing (symmetric, dB, added as a loss).
        rri_ms: reservation interval.
        n_subchannels: subchannels per subframe.
        present: [N] which vehicle slots hold a vehicle (``vehicles.population=open``; None: all).
            An empty slot has NaN position and velocity and slot -1; a vehicle that entered and is
            still listening (no resource selected yet) has slot -1 too.
    """

    subframe: int
    positions_m: FloatArray
    velocities_mps: FloatArray
    slot: IntArray
    subchannel: IntArray
    generation_slot: IntArray
    counter: IntArray
    los: NDArray[np.bool_]
    shadowing_db: FloatArray
    rri_ms: int
    n_subchannels: int
    present: NDArray[np.bool_] | None = None


class PairMatrices:
    """Builds a snapshot's ``[N, N]`` LOS and shadowing matrices from the unordered pairs in range.

    Pairs out of range (no entry) read LOS and 0 dB, as before. The shadowing of a pair is its
    large-scale loss minus the path loss: ``(EIRP - PL(d, LOS)) - mean received power``.
    """

    def __init__(
        self,
        config: ScenarioConfig,
        road: Road,
        n: int,
        positions_m: FloatArray,
        i: IntArray,
        j: IntArray,
        los: NDArray[np.bool_],
        mean_rx_dbm: FloatArray,
    ) -> None:
        self.config, self.road, self.n = config, road, n
        self.positions_m, self.i, self.j, self.los, self.mean_rx_dbm = positions_m, i, j, los, mean_rx_dbm

    def copy(self) -> PairMatrices:
        """The same builder over copies of the pair arrays (the caller's may be views of larger ones)."""
        return PairMatrices(
            self.config, self.road, self.n, self.positions_m, self.i.copy(), self.j.copy(), self.los.copy(),
            self.mean_rx_dbm.copy(),
        )  # fmt: skip

    def __call__(self) -> tuple[NDArray[np.bool_], FloatArray]:
        """``(los, shadowing_db)``, both ``[N, N]`` and symmetric."""
        n, a, b = self.n, self.i, self.j
        los = np.ones((n, n), dtype=bool)
        sh = np.zeros((n, n))
        los[a, b] = los[b, a] = self.los
        d = self.positions_m[b] - self.positions_m[a]
        disp = self.road.minimum_image(d) if self.config.road.wrap_distances else d
        pl_free = channel.path_loss_db(self.config.channel, self.config.radio.carrier_hz, disp, self.los)
        sh[a, b] = sh[b, a] = (tx_eirp_dbm(self.config) - pl_free) - self.mean_rx_dbm
        return los, sh


class _LazyPairMatrix:
    """``Snapshot.los`` / ``.shadowing_db`` of a :class:`LazySnapshot`: built on first read, then kept."""

    def __set_name__(self, owner: type, name: str) -> None:
        self._name = name

    def __get__(self, obj: LazySnapshot | None, objtype: type | None = None) -> np.ndarray:
        if obj is None:
            return self  # type: ignore[return-value]  # the descriptor itself, read on the class
        los, sh = obj.__dict__.pop("_build")()
        object.__setattr__(obj, "los", los)  # instance attributes from now on (this is not a data descriptor)
        object.__setattr__(obj, "shadowing_db", sh)
        return obj.__dict__[self._name]


class LazySnapshot(Snapshot):
    """A :class:`Snapshot` whose ``[N, N]`` ``los`` and ``shadowing_db`` are built when first read.

    With the sparse pair state (:func:`~cv2x_marl.sim.memory.uses_sparse_state`)
    :meth:`cv2x_marl.sim.simulator.Simulator.reset` returns one: until read it holds the pair arrays only
    (25 bytes per pair in range); the values, once read, are those an eager snapshot has.
    """

    los = _LazyPairMatrix()
    shadowing_db = _LazyPairMatrix()

    @classmethod
    def create(cls, fields: dict[str, object], build: PairMatrices) -> LazySnapshot:
        """The snapshot with the given non-matrix ``fields`` and the matrices' builder."""
        obj = object.__new__(cls)
        for name, value in fields.items():
            object.__setattr__(obj, name, value)
        object.__setattr__(obj, "_build", build)
        return obj
