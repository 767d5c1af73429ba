"""Expected success of every link of a snapshot when any vehicles move: :class:`SnapshotLinks` (``P[tx, rx]`` of
all N x N links; numpy reference and the compiled kernel, tested equal) and :class:`MoverRow` (one transmitter's
links for many positions of it), with what they share with :class:`~cv2x_marl.sim.ground_truth.MoverLinks`:
:func:`mean_rx_dbm` (the reference mean received power) and the refusal of ``link.interference=independent``;
the pair geometry (:class:`PairGeometry`, :func:`pair_geometry`) and :func:`row_index_table`.

:mod:`cv2x_marl.sim.ground_truth` re-exports these names; the module docstring there describes ``truth_los``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import TRUTH_LOS, ScenarioConfig
from cv2x_marl.sim import channel, inband, kernels, link
from cv2x_marl.sim.road import Road
from cv2x_marl.sim.shadow_field import ShadowField
from cv2x_marl.sim.snapshot import Snapshot
from cv2x_marl.units import db_to_linear, noise_power_dbm

FloatArray = NDArray[np.float64]


def refuse_independent_interference(config: ScenarioConfig) -> None:
    """The evaluators sum the interferers (eq. 8): refuse ``link.interference=independent`` (``validate
    --assumptions model`` only) rather than evaluate links another way than the simulator does."""
    if config.link.interference != "sum":
        raise ValueError(
            "link.interference must be sum for the snapshot evaluators (they sum the interferers, eq. 8); "
            f"got {config.link.interference!r}, the analytical model's assumption of validate --assumptions model"
        )


def mean_rx_dbm(
    config: ScenarioConfig,
    road: Road,
    pos_tx: FloatArray,
    pos_rx: FloatArray,
    los: NDArray[np.bool_],
    shadow_db: FloatArray,
) -> FloatArray:
    """Mean received power (dBm) for transmitter/receiver positions ``[..., 2]`` (broadcast)."""
    disp = np.asarray(pos_rx - pos_tx, dtype=np.float64)
    if config.road.wrap_distances:
        road.minimum_image(disp)
    radio = config.radio
    pl = channel.path_loss_db(config.channel, radio.carrier_hz, disp, los)
    eirp = radio.tx_power_dbm + radio.tx_antenna_gain_dbi + radio.rx_antenna_gain_dbi
    return eirp - pl - shadow_db


def row_index_table(mask: NDArray[np.bool_]) -> NDArray[np.int64]:
    """[N, G] the column indices of the True entries of each row of ``mask`` [N, M], in order,
    padded with -1 (G = the largest row count, at least 1): a sparse row table for the kernels."""
    rows, cols = np.nonzero(mask)
    table = np.full((mask.shape[0], max(int(mask.sum(axis=1).max(initial=0)), 1)), -1, dtype=np.int64)
    table[rows, np.arange(rows.size) - np.searchsorted(rows, rows)] = cols  # rank within the row
    return table


class PairGeometry(NamedTuple):
    """Displacements and squared distances of every ordered vehicle pair (shared per step).

    Attributes:
        disp_m: [2, N, N] ``disp_m[:, i, j] = position_j - position_i`` (m).
        dist2_m2: [N, N] squared distances (m^2), 0 on the diagonal.
    """

    disp_m: FloatArray
    dist2_m2: FloatArray


def pair_geometry(positions_m: FloatArray, road: Road | None = None) -> PairGeometry:
    """:class:`PairGeometry` of positions ``[N, 2]`` (m), array code over the N x N pairs.

    Args:
        positions_m: [N, 2] vehicle positions (m).
        road: fold the displacements onto this road's torus (``road.wrap_distances``); None: plain.
    """
    pt = np.asarray(positions_m, dtype=np.float64).T
    disp = pt[:, None, :] - pt[:, :, None]
    if road is not None:
        road.minimum_image(np.moveaxis(disp, 0, -1))  # in place through the [N, N, 2] view
    return PairGeometry(disp, disp[0] * disp[0] + disp[1] * disp[1])


class LinkKernelArgs(NamedTuple):
    """The compiled link kernels' arguments after the positions (:func:`cv2x_marl.sim.kernels.snapshot_links`),
    for N vehicles and G interferer slots.

    Attributes:
        period_m: [2] the torus of the pair geometry (inf where distances do not wrap).
        los: [N, N] line of sight of each pair.
        gain_db: [N, N] EIRP minus the shadowing of each pair (dBm).
        wb1: the WINNER+ B1 constants (:func:`cv2x_marl.sim.kernels.winner_b1_constants`).
        range2_m2: the squared link range (m^2; inf: none).
        interferer_idx, interferer_val: [N, G] each transmitter's interferers and their weights (-1 / 0: none).
        noise_mw: the noise power (mW).
        link_model: the link model's code; per_sinr_db, per: its PER table (dB, probability).
        threshold_db: the SINR threshold (dB); sensitivity_dbm: the receiver sensitivity (dBm; -inf: none).
        target: [N, N] the target receivers of each transmitter.
    """

    period_m: FloatArray
    los: NDArray[np.bool_]
    gain_db: FloatArray
    wb1: FloatArray
    range2_m2: float
    interferer_idx: NDArray[np.int64]
    interferer_val: FloatArray
    noise_mw: float
    link_model: int
    per_sinr_db: FloatArray
    per: FloatArray
    threshold_db: float
    sensitivity_dbm: float
    target: NDArray[np.bool_]


class MoverRowArgs(NamedTuple):
    """The row kernels' arguments after the candidates (:func:`cv2x_marl.sim.kernels.mover_row_success`): one
    mover's links with the others where they stand.

    Attributes:
        positions_m: [N, 2] every vehicle's position (m); mover: the mover's index.
        period_m, wb1, range2_m2, noise_mw, link_model, per_sinr_db, per, threshold_db, sensitivity_dbm: as
            :class:`LinkKernelArgs`.
        los_row: [N] line of sight of the mover's links; gain_row_db: [N] (or [M, N] per candidate) their gains.
        interference_mw: [N] the interference at each receiver from the others (fixed while they stand still).
        target_row: [N] the mover's target receivers.
    """

    positions_m: FloatArray
    mover: int
    period_m: FloatArray
    los_row: NDArray[np.bool_]
    gain_row_db: FloatArray
    wb1: FloatArray
    range2_m2: float
    interference_mw: FloatArray
    noise_mw: float
    link_model: int
    per_sinr_db: FloatArray
    per: FloatArray
    threshold_db: float
    sensitivity_dbm: float
    target_row: NDArray[np.bool_]


class SnapshotLinks:
    """Expected success of every link of a snapshot when any vehicles move (the env's reward).

    Resources, shadowing and (with ``truth_los="snapshot"``) LOS states stay those of the
    snapshot; positions are free. ``success(positions)`` returns ``P[tx, rx]`` for all N x N
    links: the signal from the moved transmitter (WINNER+ B1 or eq. 3 path loss, the snapshot's
    shadowing), interference from the moved co-channel transmitters (plus in-band emission from
    the other subchannels of the subframe when configured: ``link.inband_emission_model`` flat or
    3gpp), half duplex, noise, then the PER table
    or the threshold. Distances fold on the torus when ``road.wrap_distances``.

    Two implementations, tested equal: numpy array code over the N x N pairs built on
    :func:`mean_rx_dbm` (the reference; every path-loss model and LOS rule), and the fused kernel
    :func:`cv2x_marl.sim.kernels.snapshot_links` (WINNER+ B1 with the snapshot's or forced LOS: the
    env's default, about 10x faster), used when ``compiled`` and the configuration allows it.
    """

    def __init__(
        self,
        config: ScenarioConfig,
        snapshot: Snapshot,
        truth_los: str = "snapshot",
        compiled: bool = True,
        field: ShadowField | None = None,
    ) -> None:
        if truth_los not in TRUTH_LOS:
            raise ValueError(f"truth_los must be one of {', '.join(TRUTH_LOS)}, got {truth_los!r}")
        if config.link.model == "rayleigh":
            raise ValueError("SnapshotLinks supports link.model per_table and threshold")
        refuse_independent_interference(config)
        self.config = config
        self.road = Road.from_config(config.road)
        self.snapshot = snapshot
        self.truth_los = truth_los
        n = snapshot.positions_m.shape[0]
        self.n = n
        eye = np.eye(n, dtype=bool)
        self.shadow_db = np.asarray(snapshot.shadowing_db, dtype=np.float64)
        #: the shadowing that follows the vehicles (:class:`~cv2x_marl.sim.shadow_field.ShadowField`), or
        #: None: every pair keeps the snapshot's shadowing wherever the vehicles move
        self.field = field
        self.los = np.asarray(snapshot.los, dtype=bool) if truth_los == "snapshot" else np.ones((n, n), bool)
        res = snapshot.slot * snapshot.n_subchannels + snapshot.subchannel
        same_res = res[:, None] == res[None, :]
        slot = snapshot.slot
        self.target = slot[:, None] != slot[None, :]  # [tx, rx]: half duplex excluded (and the diagonal)
        # interference weights W[tx, c]: 1 for the other transmitters on tx's resource, the in-band
        # emission factor for the other subchannels of tx's subframe; I[tx, rx] = sum_c W[tx, c] m[c, rx]
        self.interference_weight = (same_res & ~eye).astype(np.float64)
        if config.link.inband_emission_db is not None:
            same_slot_other = (slot[:, None] == slot[None, :]) & ~same_res
            self.interference_weight += float(db_to_linear(config.link.inband_emission_db)) * same_slot_other
        elif config.link.inband_emission_model == "3gpp":  # M[subchannel of tx, subchannel of c]
            leakage = inband.pool_leakage_weights(config)
            assert leakage is not None
            sub = snapshot.subchannel
            same_slot_other = (slot[:, None] == slot[None, :]) & ~same_res
            self.interference_weight += leakage[sub[:, None], sub[None, :]] * same_slot_other
        radio = config.radio
        self.eirp_dbm = radio.tx_power_dbm + radio.tx_antenna_gain_dbi + radio.rx_antenna_gain_dbi
        self.noise_mw = float(db_to_linear(noise_power_dbm(radio.noise_dbm, radio.noise_figure_db)))
        self.curve = link.load_per_curve(config.link.per_curve, config.link.per_interpolation)
        rng = config.link.max_range_m
        self._range2 = None if rng is None else rng * rng
        self._wrap_road = self.road if config.road.wrap_distances else None
        self.compiled = compiled and config.channel.pathloss == "winner_b1" and truth_los != "geometry"
        if self.compiled:
            ch = config.channel
            #: the compiled kernels' arguments after the positions (:class:`LinkKernelArgs`)
            self.kernel_args = self._kernel_arguments(
                kernels.winner_b1_constants(radio.carrier_hz, ch.effective_height_m, ch.min_distance_m)
            )

    def _kernel_arguments(self, wb1: FloatArray) -> LinkKernelArgs:
        w = self.interference_weight
        idx = row_index_table(w > 0)
        val = np.where(idx >= 0, w[np.arange(self.n)[:, None], idx], 0.0)
        cfg = self.config
        period = self.road.periodic_box_m if self._wrap_road is not None else np.full(2, np.inf)
        return LinkKernelArgs(
            np.asarray(period, dtype=np.float64),
            np.ascontiguousarray(self.los),
            np.ascontiguousarray(self.eirp_dbm - self.shadow_db),
            wb1,
            np.inf if self._range2 is None else float(self._range2),
            idx,
            val,
            self.noise_mw,
            self.curve.kernel_model if cfg.link.model == "per_table" else kernels.MODEL_THRESHOLD,
            np.ascontiguousarray(self.curve.sinr_db, dtype=np.float64),
            np.ascontiguousarray(self.curve.per, dtype=np.float64),
            float(cfg.link.sinr_threshold_db),
            -np.inf if cfg.radio.sensitivity_dbm is None else float(cfg.radio.sensitivity_dbm),
            np.ascontiguousarray(self.target),
        )

    def geometry(self, positions_m: FloatArray) -> PairGeometry:
        """:func:`pair_geometry` of ``positions_m`` (folded on the torus when ``road.wrap_distances``)."""
        return pair_geometry(positions_m, self._wrap_road)

    def rx_dbm(self, positions_m: FloatArray, shadow_db: FloatArray | None = None) -> FloatArray:
        """[N(tx), N(rx)] mean received power (dBm), numpy reference: EIRP - path loss - shadowing;
        -inf on the diagonal and beyond ``link.max_range_m``.

        Args:
            positions_m: [N, 2] vehicle positions (m).
            shadow_db: [N, N] the field's shadowing at ``positions_m`` when already computed (None: computed here).
        """
        los = self.los
        if self.truth_los == "geometry" and self.road.kind == "grid":
            hc, vc = self.road.corridors(positions_m)
            los = Road.corridor_los((hc[:, None], vc[:, None]), (hc[None, :], vc[None, :]))
        pos = np.asarray(positions_m, dtype=np.float64)
        shadow = self._shadow(pos, shadow_db)
        dbm = mean_rx_dbm(self.config, self.road, pos[:, None, :], pos[None, :, :], los, shadow)
        dbm[np.diag_indices(self.n)] = -np.inf
        if self._range2 is not None:
            dbm = np.where(self.geometry(pos).dist2_m2 <= self._range2, dbm, -np.inf)
        return dbm

    def _shadow(self, pos: FloatArray, shadow_db: FloatArray | None) -> FloatArray:
        """[N, N] the shadowing at ``pos``: the snapshot's, or the field's (``shadow_db`` when given)."""
        if self.field is None:
            return self.shadow_db
        return self.field.shadow_db(pos, compiled=self.compiled) if shadow_db is None else shadow_db

    def evaluate_rx(self, positions_m: FloatArray) -> tuple[FloatArray, PairGeometry, FloatArray]:
        """:meth:`evaluate` and :meth:`rx_dbm` together, the shadowing field read once: ``(P, geometry,
        rx_dbm)``, each equal bit for bit to the separate calls (compiled: :func:`cv2x_marl.sim.kernels.pair_rx_dbm`,
        the numpy reference's arithmetic; tested).

        Args:
            positions_m: [N, 2] vehicle positions (m).
        """
        pos = np.ascontiguousarray(positions_m, dtype=np.float64)
        shadow = None if self.field is None else self.field.shadow_db(pos, compiled=self.compiled)
        p, geometry = self.evaluate(pos, shadow)
        if not self.compiled:
            return p, geometry, self.rx_dbm(pos, shadow)
        a = self.kernel_args
        rx = kernels.pair_rx_dbm(
            pos, a.period_m, a.los, self._shadow(pos, shadow), float(self.eirp_dbm), a.wb1, a.range2_m2
        )
        return p, geometry, rx

    def evaluate(self, positions_m: FloatArray, shadow_db: FloatArray | None = None) -> tuple[FloatArray, PairGeometry]:
        """Expected success of every link and the pair geometry it used.

        Args:
            positions_m: [N, 2] vehicle positions (m).
            shadow_db: [N, N] the field's shadowing at ``positions_m`` when already computed (None: computed here).

        Returns:
            ``P[tx, rx]`` [N, N] (0 where rx is not a target of tx) and the :class:`PairGeometry`.
        """
        pos = np.ascontiguousarray(positions_m, dtype=np.float64)
        if pos.shape != (self.n, 2):
            raise ValueError(f"positions_m must have shape ({self.n}, 2) for this snapshot, got {pos.shape}")
        if self.compiled:
            args = self.kernel_args
            if self.field is not None:  # the gains at these positions: EIRP - the field's shadowing
                args = args._replace(gain_db=np.ascontiguousarray(self.eirp_dbm - self._shadow(pos, shadow_db)))
            disp, dist2, p = kernels.snapshot_links(pos, *args)
            return p, PairGeometry(disp, dist2)
        s_dbm = self.rx_dbm(pos, shadow_db)
        interference_mw = self.interference_weight @ 10.0 ** (s_dbm / 10.0)  # [tx, rx]
        sinr_db = s_dbm - 10.0 * np.log10(interference_mw + self.noise_mw)
        if self.config.link.model == "per_table":
            p = self.curve.success(sinr_db)
        else:
            p = link.threshold_success(sinr_db, self.config.link.sinr_threshold_db)
        sens = self.config.radio.sensitivity_dbm
        if sens is not None:
            p = np.where(s_dbm < sens, 0.0, p)
        return np.where(self.target, p, 0.0), self.geometry(pos)

    def success(self, positions_m: FloatArray) -> FloatArray:
        """[N(tx), N(rx)] expected success probability; 0 where rx is not a target of tx.

        Args:
            positions_m: [N, 2] vehicle positions (m).
        """
        return self.evaluate(positions_m)[0]

    def gain_db(self, positions_m: FloatArray) -> FloatArray:
        """[N, N] EIRP minus the shadowing of every pair (dBm) with the vehicles at ``positions_m``
        [N, 2]: the snapshot's (``positions_m`` unused) or, with a field, the field's there. Compiled
        path only (the kernels' ``gain_db``)."""
        if self.field is None:
            return self.kernel_args.gain_db
        pos = np.ascontiguousarray(positions_m, dtype=np.float64)
        return np.ascontiguousarray(self.eirp_dbm - self.field.shadow_db(pos))

    def _check_row(self, mover: int, positions_m: FloatArray) -> FloatArray:
        if not 0 <= mover < self.n:
            raise ValueError(f"mover must be a vehicle index 0 .. {self.n - 1}, got {mover}")
        pos = np.ascontiguousarray(positions_m, dtype=np.float64)
        if pos.shape != (self.n, 2):
            raise ValueError(f"positions_m must have shape ({self.n}, 2) for this snapshot, got {pos.shape}")
        return pos

    def mover_row(self, mover: int, positions_m: FloatArray) -> MoverRow:
        """The links of one transmitter as a function of its own position, the others where they are.

        With a shadowing field (:attr:`field`) the mover's own links read the field with the mover at
        each candidate and the others at ``positions_m``; the interference at each receiver (from the
        other transmitters) reads it at ``positions_m``: row ``mover`` of :meth:`evaluate` with the
        mover at the candidate (tested).

        Args:
            mover: index of the transmitter that moves.
            positions_m: [N, 2] positions of every vehicle (the mover's row is where it starts).
        """
        return MoverRow(self, int(mover), self._check_row(mover, positions_m))

    def sensed_row(self, mover: int, positions_m: FloatArray) -> MoverRow:
        """The mover's own estimate of its links (what it can know from Mode 4 sensing), not the truth.

        A vehicle that senses the channel for the 1000 ms window of TS 36.213 clause 14.1.1.6 knows
        the positions of its neighbours (their CAMs), their resources (decoded SCI, hence half duplex
        and who shares its resource) and the mean received power (RSRP) of each neighbour; by channel
        reciprocity the RSRP gives the path gain, shadowing included, of each of its own links. It
        cannot measure the channel between two other vehicles. The estimate is therefore the true row
        (:meth:`mover_row`) except for the interference at each receiver, which is recomputed with the
        shadowing of every pair that does not include the mover set to 0 dB (its median). LOS states
        are the snapshot's (in the Manhattan grid they follow from the road map). Used by the
        ``-v2`` observation and the ``sensing`` planner; compiled kernels only.

        With a shadowing field (:attr:`field`) the vehicle knows its links' shadowing only where it
        stands (what it measured there): for every candidate position the estimate keeps the own
        links' shadowing at ``positions_m`` (path loss from the candidate, shadowing from here), so it
        differs from the truth by the field's change between here and the candidate (TR 36.885 A.1.4:
        correlation ``exp(-r / d)`` at a distance r).

        Args:
            mover: index of the transmitter that moves.
            positions_m: [N, 2] positions of every vehicle (the mover's row is where it starts).
        """
        if not self.compiled:
            raise ValueError("sensed_row needs the compiled link kernels (WINNER+ B1, truth_los snapshot or always)")
        pos = self._check_row(mover, positions_m)
        row = MoverRow(self, int(mover), pos, follow_field=False)
        (period, los, _gain, wb1, range2, idx, val, *_rest) = self.kernel_args
        gain = self.gain_db(pos)
        own = np.zeros((self.n, self.n), dtype=bool)
        own[mover, :] = own[:, mover] = True
        sensed_gain = np.ascontiguousarray(np.where(own, gain, self.eirp_dbm))
        interference = kernels.mover_interference(
            row.positions_m, period, los, sensed_gain, wb1, range2, idx, val, int(mover)
        )
        row.args = row.args._replace(interference_mw=interference)
        return row


class MoverRow:
    """Row ``mover`` of :meth:`SnapshotLinks.evaluate` for many positions of the mover at once.

    With the other vehicles fixed, the interference on the mover's links does not depend on where
    the mover stands (a transmitter never interferes with its own packet), so it is computed once;
    each candidate position then costs one path loss per target receiver (and, with a shadowing
    field, the field of each of its links there: :meth:`ShadowField.row_db`). Compiled: the additions
    of :func:`cv2x_marl.sim.kernels.snapshot_links` in the same order (bit-identical to the row of a
    full evaluation without a field, tested; with a field equal to the field's tolerance);
    otherwise one full numpy evaluation per candidate.

    Args:
        links: the snapshot's links.
        mover: the transmitter that moves.
        positions_m: [N, 2] every vehicle's position (m).
        follow_field: with a field, whether the mover's own links read it at each candidate (the
            truth) or keep its values at ``positions_m`` (the sensing estimate, :meth:`SnapshotLinks.sensed_row`).
    """

    def __init__(self, links: SnapshotLinks, mover: int, positions_m: FloatArray, follow_field: bool = True) -> None:
        self.links = links
        self.mover = mover
        self.positions_m = positions_m
        self.target_row = np.ascontiguousarray(links.target[mover])
        self._field = links.field if follow_field else None
        if links.compiled:
            (period, los, _gain, wb1, range2, idx, val, noise, model, per_sinr, per, thr, sens, _) = links.kernel_args
            gain = links.gain_db(positions_m)  # the interference at each receiver: the field here
            interference = kernels.mover_interference(positions_m, period, los, gain, wb1, range2, idx, val, mover)
            #: the row kernels' arguments (:class:`MoverRowArgs`)
            self.args = MoverRowArgs(
                positions_m,
                mover,
                period,
                np.ascontiguousarray(los[mover]),
                np.ascontiguousarray(gain[mover]),  # [N]: the own links' gains where the mover stands
                wb1,
                range2,
                interference,
                noise,
                model,
                per_sinr,
                per,
                thr,
                sens,
                self.target_row,
            )

    def _gain_rows(self, cand: FloatArray) -> FloatArray:
        """[G, N] the own links' gains: [1, N] (the snapshot's shadowing, or the field where the mover
        stands for the sensing estimate) or [M, N] (the field at each candidate)."""
        if self._field is None:
            return self.args.gain_row_db[None, :]
        return np.ascontiguousarray(self.links.eirp_dbm - self._field.rows_db(self.mover, self.positions_m, cand))

    def _row_args(self, cand: FloatArray) -> MoverRowArgs:
        """The arguments of the row kernels after ``candidates_m``, with the gains of :meth:`_gain_rows`."""
        return self.args._replace(gain_row_db=self._gain_rows(cand))

    def success_with_gains(self, candidates_m: FloatArray, gain_rows_db: FloatArray) -> FloatArray:
        """:meth:`success` (compiled) with the own links' gains given: ``gain_rows_db`` [1, N] or [M, N]
        (EIRP minus the shadowing, dBm), e.g. the field's row already read for the step."""
        return kernels.mover_row_success(candidates_m, *self.args._replace(gain_row_db=gain_rows_db))

    def success(self, candidates_m: FloatArray) -> FloatArray:
        """[M, N] expected success of the mover's links with the mover at each candidate [M, 2] (m)."""
        cand = np.ascontiguousarray(np.asarray(candidates_m, dtype=np.float64).reshape(-1, 2))
        if self.links.compiled:
            return kernels.mover_row_success(cand, *self._row_args(cand))
        out = np.empty((cand.shape[0], self.links.n))
        pos = self.positions_m.copy()
        for m, c in enumerate(cand):  # reference path (power law, geometry LOS): one evaluation each
            pos[self.mover] = c
            out[m] = self.links.evaluate(pos)[0][self.mover]
        return out

    def utility(self, candidates_m: FloatArray, p_min: float, chunk: int = 65_536) -> FloatArray:
        """[M] eq. 12 utility of the mover at each candidate [M, 2] (m), in chunks of ``chunk`` rows
        (compiled: :func:`cv2x_marl.sim.kernels.mover_row_utility`, bit-identical to the utility of
        :meth:`success`)."""
        cand = np.asarray(candidates_m, dtype=np.float64).reshape(-1, 2)
        if self.links.compiled and self._field is None:
            c = np.ascontiguousarray(cand)
            return kernels.mover_row_utility(c, *self._row_args(c), float(p_min))
        out = np.empty(cand.shape[0])
        for lo in range(0, cand.shape[0], chunk):
            c = np.ascontiguousarray(cand[lo : lo + chunk])
            if self.links.compiled:
                out[lo : lo + chunk] = kernels.mover_row_utility(c, *self._row_args(c), float(p_min))
            else:
                out[lo : lo + chunk] = kernels.row_utility(self.success(c), self.target_row, p_min)
        return out
