"""PRR metrics.

* Per-node PRR (paper Sec. 1 and 4): for a transmitter, the mean over its target receivers of
  the link's success; the target receivers are the vehicles not transmitting in its subframe
  (half duplex, paper Sec. 4). Reported both sampled (fraction decoded) and expected (mean P).
* PRR vs distance (3GPP TR 36.885 A.2): in each distance bin, packets decoded divided by the
  (transmission, vehicle) pairs at that distance, half-duplex losses included.
* Loss causes per bin, in this order of precedence: half duplex (the receiver transmits in the
  same subframe), below sensitivity, propagation (the link fails even without interference,
  with the same random numbers), collision (it fails only because of interference).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # the annotation only: the metrics need no numba
    from cv2x_marl.sim.kernels.period import ChunkResult

CAUSES: tuple[str, ...] = ("ok", "half_duplex", "sensitivity", "propagation", "collision")
CAUSE_CODE = {name: i for i, name in enumerate(CAUSES)}


class PrrAccumulator:
    """Running sums for per-node PRR, PRR vs distance and loss causes."""

    def __init__(self, n_vehicles: int, bin_m: float, max_distance_m: float) -> None:
        self.bin_m = bin_m
        self.n_bins = int(np.ceil(max_distance_m / bin_m))
        self.max_distance_m = self.n_bins * bin_m
        self.bin_n = np.zeros(self.n_bins, dtype=np.int64)
        self.bin_decoded = np.zeros(self.n_bins, dtype=np.int64)
        self.bin_expected = np.zeros(self.n_bins)
        self.bin_causes = np.zeros((len(CAUSES), self.n_bins), dtype=np.int64)
        self.node_n = np.zeros(n_vehicles, dtype=np.int64)
        self.node_decoded = np.zeros(n_vehicles, dtype=np.int64)
        self.node_expected = np.zeros(n_vehicles)
        self.n_transmissions = 0
        #: ``vehicles.population=open``: per-node sums [3, K] (n, decoded, expected) of the vehicles
        #: that left during the run (:meth:`retire`), or None when none has
        self._retired: list[NDArray[np.float64]] = []
        self.open_population = False
        #: the simulator's SPS state when the measurement started (:meth:`Simulator.sps_state`), or None
        self.sps_state_at_start: dict[str, Any] | None = None

    def add(
        self,
        tx: NDArray[np.int64],
        distance_m: NDArray[np.float64],
        p_success: NDArray[np.float64],
        outcome: NDArray[np.bool_],
        cause: NDArray[np.int8],
        n_transmissions: int,
    ) -> None:
        """Add one batch of links (arrays of length L)."""
        self.n_transmissions += n_transmissions
        b = np.floor(distance_m / self.bin_m).astype(np.int64)
        inside = b < self.n_bins
        bi = b[inside]
        nb = self.n_bins
        self.bin_n += np.bincount(bi, minlength=nb)
        self.bin_decoded += np.bincount(bi, weights=outcome[inside], minlength=nb).astype(np.int64)
        self.bin_expected += np.bincount(bi, weights=p_success[inside], minlength=nb)
        self.bin_causes += np.bincount(cause[inside].astype(np.int64) * nb + bi, minlength=len(CAUSES) * nb).reshape(
            len(CAUSES), nb
        )
        target = cause != CAUSE_CODE["half_duplex"]
        n = self.node_n.shape[0]
        self.node_n += np.bincount(tx[target], minlength=n)
        self.node_decoded += np.bincount(tx[target], weights=outcome[target], minlength=n).astype(np.int64)
        self.node_expected += np.bincount(tx[target], weights=p_success[target], minlength=n)

    def retire(self, slots: NDArray[np.int64]) -> None:
        """``vehicles.population=open``: the vehicles in ``slots`` [K] left (or their slots were given to
        new vehicles): keep their per-node sums as those of finished vehicles and start the slots
        afresh, so that a slot's next vehicle is a node of its own."""
        self.open_population = True
        if slots.size:
            self._retired.append(
                np.stack([self.node_n[slots], self.node_decoded[slots], self.node_expected[slots]]).astype(np.float64)
            )
            self.node_n[slots] = 0
            self.node_decoded[slots] = 0
            self.node_expected[slots] = 0.0

    def node_prr(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per-node PRR, (sampled, expected); NaN for a node that had no target receiver.

        [N] per vehicle slot; with an open population (after :meth:`retire`) one entry per vehicle
        that transmitted during the run instead: those that left, in the order they left, then
        those still present, by slot."""
        n, dec, exp = self.node_n, self.node_decoded, self.node_expected
        if self.open_population:
            sent = n > 0
            sums = np.concatenate([*self._retired, np.stack([n[sent], dec[sent], exp[sent]])], axis=1)
            sums = sums[:, sums[0] > 0]
            n, dec, exp = sums[0], sums[1], sums[2]
        with np.errstate(invalid="ignore", divide="ignore"):
            return dec / n, exp / n

    def summary(self) -> dict[str, Any]:
        """JSON-ready metrics: PRR means, PRR vs distance and loss causes per bin."""
        sampled, expected = self.node_prr()
        centres = (np.arange(self.n_bins) + 0.5) * self.bin_m
        with np.errstate(invalid="ignore", divide="ignore"):
            prr = self.bin_decoded / self.bin_n
            prr_exp = self.bin_expected / self.bin_n
        keep = self.bin_n > 0
        prr_vs_distance = [
            {"distance_m": float(c), "prr": float(p), "prr_expected": float(e), "n": int(n)}
            for c, p, e, n in zip(centres[keep], prr[keep], prr_exp[keep], self.bin_n[keep], strict=True)
        ]
        loss = []
        for j in np.flatnonzero(keep):
            row: dict[str, Any] = {"distance_m": float(centres[j]), "n": int(self.bin_n[j])}
            for c, name in enumerate(CAUSES[1:], start=1):
                row[name] = float(self.bin_causes[c, j] / self.bin_n[j])
            loss.append(row)
        total = self.bin_causes.sum(axis=1)
        lost = max(int(total[1:].sum()), 1)
        return {
            "prr_mean": float(np.nanmean(sampled)) if np.any(np.isfinite(sampled)) else float("nan"),
            "prr_mean_expected": float(np.nanmean(expected)) if np.any(np.isfinite(expected)) else float("nan"),
            "node_prr": [None if np.isnan(x) else float(x) for x in sampled],
            "prr_vs_distance": prr_vs_distance,
            "loss_causes": loss,
            "loss_cause_shares": {name: float(total[c] / lost) for c, name in enumerate(CAUSES) if c > 0},
            "n_transmissions": int(self.n_transmissions),
            "n_link_samples": int(self.bin_n.sum()),
        } | ({} if self.sps_state_at_start is None else {"sps_state_at_start": self.sps_state_at_start})

    def prr_at(self, distance_m: float) -> float:
        """PRR of the bin containing ``distance_m`` (NaN when the bin is empty or out of range)."""
        j = int(distance_m // self.bin_m)
        if j >= self.n_bins or self.bin_n[j] == 0:
            return float("nan")
        return float(self.bin_decoded[j] / self.bin_n[j])

    def add_counts(self, n_transmissions: int, counts: ChunkResult) -> None:
        """Add one batch already counted (:func:`cv2x_marl.sim.kernels.period_chunk`'s result): its per-bin
        ``[n_bins]`` and per-node ``[N]`` sums of :meth:`add`, ``bin_causes`` cause-major."""
        self.n_transmissions += n_transmissions
        self.bin_n += counts.bin_n
        self.bin_decoded += counts.bin_decoded
        self.bin_expected += counts.bin_expected
        self.bin_causes += counts.bin_causes.reshape(len(CAUSES), self.n_bins)
        self.node_n += counts.node_n
        self.node_decoded += counts.node_decoded
        self.node_expected += counts.node_expected
