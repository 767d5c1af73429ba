"""The links a lone mover changes in one step: its row (what it sends) and its column (what it hears).

:meth:`MobilityEnv.step_mover <cv2x_marl.env.mobility_env.MobilityEnv.step_mover>` moves one vehicle
while the others stand still, so of the N x N links only the pairs that include the mover change
(the others' shadowing, path loss and interference on the mover's resource stay; the interference
the mover causes at other receivers changes too, but those links are neither the mover's reward nor
its observation). :class:`MoverLinksStep` computes, with the shadowing field read once for the
mover's new position (:meth:`ShadowField.row_db <cv2x_marl.sim.shadow_field.ShadowField.row_db>`,
bit-identical to the field's row in a full evaluation, tested):

- row ``mover`` of ``P`` (:meth:`MoverRow.success_with_gains <cv2x_marl.sim.ground_truth.MoverRow.success_with_gains>`);
- with ``column=True`` (observation version 3: the mover's measurements), column ``mover`` of ``P``
  and of the mean received power (:func:`cv2x_marl.sim.kernels.mover_column`): what the measurement
  update (:meth:`cv2x_marl.env.measurement.Measurements.update`) reads for the mover as receiver.

Each entry equals that of :meth:`SnapshotLinks.evaluate_rx <cv2x_marl.sim.ground_truth.SnapshotLinks.evaluate_rx>`
with the others where they are, bit for bit (the same compiled arithmetic; ``tests/env/test_v3_fast.py``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.sim import kernels
from cv2x_marl.sim.ground_truth import SnapshotLinks

FloatArray = NDArray[np.float64]


class MoverLinksStep:
    """The changing links of one mover (compiled link kernels only).

    Args:
        links: the episode's links (``links.compiled``).
        mover: the vehicle that moves.
        positions_m: [N, 2] every vehicle's position (the others stay there).
        column: also compute the mover's column (P and received power).
    """

    def __init__(self, links: SnapshotLinks, mover: int, positions_m: FloatArray, column: bool) -> None:
        if not links.compiled:
            raise ValueError(
                "MoverLinksStep needs the compiled link kernels (WINNER+ B1, truth_los snapshot or always)"
            )
        self.links = links
        self.mover = int(mover)
        self.column = column
        self.row = links.mover_row(self.mover, positions_m)
        args = links.kernel_args
        i = self.mover
        self._gain_row = self.row.args.gain_row_db[None, :]  # [1, N] without a field: the snapshot's row
        self._gain_col = np.ascontiguousarray(args.gain_db[:, i])
        self._shadow_col = np.ascontiguousarray(links.shadow_db[:, i])
        self._eirp = float(links.eirp_dbm)
        (period, los, _gain, wb1, range2, idx, val, noise, model, per_sinr, per, thr, sens, target) = args
        self._col_args = (period, los, wb1, range2, idx, val, noise, model, per_sinr, per, thr, sens)
        self._target_col = np.ascontiguousarray(target[:, i])

    def step(self, positions_m: FloatArray, link_p: FloatArray, rx_dbm: FloatArray | None) -> None:
        """Write row ``mover`` of ``link_p`` [N, N] (and, with ``column``, column ``mover`` of ``link_p`` and
        of ``rx_dbm`` [N, N]) for the mover at ``positions_m[mover]``, in place."""
        i = self.mover
        cand = np.ascontiguousarray(positions_m[i : i + 1])
        field = self.links.field
        if field is None:
            gain_row, gain_col, shadow_col = self._gain_row, self._gain_col, self._shadow_col
        else:  # the field's row where the mover now stands (the pair shadowing is symmetric)
            shadow_col = field.row_db(i, positions_m, cand)[0]
            gain_col = np.ascontiguousarray(self._eirp - shadow_col)
            gain_row = gain_col[None, :]
        link_p[i] = self.row.success_with_gains(cand, gain_row)[0]
        if not self.column:
            return
        assert rx_dbm is not None
        (period, los, wb1, range2, idx, val, noise, model, per_sinr, per, thr, sens) = self._col_args
        p_col, rx_col = kernels.mover_column(
            float(cand[0, 0]), float(cand[0, 1]), positions_m, i, period, los, gain_col, shadow_col, self._eirp, wb1,
            range2, idx, val, noise, model, per_sinr, per, thr, sens, self._target_col,
        )  # fmt: skip
        link_p[:, i] = p_col
        rx_dbm[:, i] = rx_col
