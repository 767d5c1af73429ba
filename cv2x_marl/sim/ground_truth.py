"""Ground truth for a moved transmitter: its links' success probability from the link model.

Given stage-1 snapshots and one mover per snapshot, :class:`MoverLinks` answers "if the mover
stood at position x, what would be the success probability of its packet at every receiver?"
with the simulator's own link model: path loss from x to each receiver (the snapshot's shadowing
and, by default, its LOS state per link), interference at each receiver from the other vehicles
transmitting on the mover's resource (fixed: they do not move; plus the in-band emission of those
on the other subchannels of its subframe when configured), noise, then the PER table / Rayleigh
closed form / threshold. Expected values (no fading draw). Batched over snapshots: arrays are
``[B, N]`` for B snapshots of N vehicles.

``truth_los``: ``snapshot`` keeps each link's LOS/NLOS state from the snapshot (the mover is
taken to stay in its street system), ``geometry`` recomputes it from x with the corridor rule,
``always`` forces LOS.

:class:`SnapshotLinks` (every link of a snapshot when any vehicles move), :class:`MoverRow`,
:func:`mean_rx_dbm` and the pair geometry are :mod:`cv2x_marl.sim.snapshot_links`' (re-exported here).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import TRUTH_LOS, ScenarioConfig
from cv2x_marl.sim import inband, link
from cv2x_marl.sim.road import Road
from cv2x_marl.sim.shadow_field import ShadowField
from cv2x_marl.sim.snapshot import Snapshot
from cv2x_marl.sim.snapshot_links import (  # noqa: F401 - re-exported: ground_truth's names before the split
    MoverRow,
    PairGeometry,
    SnapshotLinks,
    mean_rx_dbm,
    pair_geometry,
    refuse_independent_interference,
    row_index_table,
)
from cv2x_marl.units import db_to_linear, noise_power_dbm

FloatArray = NDArray[np.float64]


def _power_at_all(config: ScenarioConfig, road: Road, snap: Snapshot, tx: NDArray[np.int64]) -> FloatArray:
    """[N, T] mean power of transmitters ``tx`` at every vehicle of the snapshot (0 at themselves and
    beyond ``link.max_range_m``)."""
    pos = snap.positions_m
    p = db_to_linear(mean_rx_dbm(config, road, pos[tx][None], pos[:, None], snap.los[:, tx], snap.shadowing_db[:, tx]))
    if config.link.max_range_m is not None:
        disp = pos[:, None, :] - pos[tx][None, :, :]
        if config.road.wrap_distances:
            road.minimum_image(disp)
        p = np.where(np.hypot(disp[..., 0], disp[..., 1]) <= config.link.max_range_m, p, 0.0)
    p[tx, np.arange(tx.size)] = 0.0  # a transmitter does not interfere with itself
    return p


@dataclass
class MoverLinks:
    """Everything fixed about a mover's links in B snapshots; :meth:`success` varies its position.

    Attributes:
        rx_pos_m: [B, N, 2] receiver positions (the mover's own row is masked out).
        target: [B, N] target receivers (not the mover, not transmitting in its subframe, in range).
        los: [B, N] LOS state of each mover link in the snapshot.
        shadow_db: [B, N] shadowing of each mover link.
        interference_mw: [B, N] mean interference at each receiver on the mover's resource.
        interferer_mw: [B, N, C] the individual terms (Rayleigh closed form), zero-padded.
        start_m: [B, 2] mover positions in the snapshots.
        mover: [B] index of the mover in each snapshot.
        truth_los: ``snapshot``, ``geometry`` or ``always`` (module docstring).
        fields: per snapshot its shadowing field (:class:`~cv2x_marl.sim.shadow_field.ShadowField`,
            None: the snapshot's shadowing), or None for none at all. With a field the mover's links read
            it with the mover at the evaluated position and the receivers at ``rx_pos_m``; the
            interference stays the snapshot's (the receivers and the interferers do not move).
    """

    config: ScenarioConfig
    road: Road
    rx_pos_m: FloatArray
    target: NDArray[np.bool_]
    los: NDArray[np.bool_]
    shadow_db: FloatArray
    interference_mw: FloatArray
    interferer_mw: FloatArray
    start_m: FloatArray
    mover: NDArray[np.int64]
    truth_los: str = "snapshot"
    fields: tuple[ShadowField | None, ...] | None = None

    @classmethod
    def from_snapshots(
        cls,
        config: ScenarioConfig,
        snapshots: Sequence[Snapshot],
        movers: Sequence[int],
        truth_los: str = "snapshot",
        neighbourhood_m: float | None = None,
        fields: Sequence[ShadowField | None] | None = None,
    ) -> MoverLinks:
        """Collect the mover links of each snapshot (all with the same vehicle count); ``fields``: one
        shadowing field (or None) per snapshot, drawn at the snapshot's positions."""
        if truth_los not in TRUTH_LOS:
            raise ValueError(f"truth_los must be one of {', '.join(TRUTH_LOS)}, got {truth_los!r}")
        refuse_independent_interference(config)
        road = Road.from_config(config.road)
        n = snapshots[0].positions_m.shape[0]
        b = len(snapshots)
        rx_pos = np.zeros((b, n, 2))
        target = np.zeros((b, n), dtype=bool)
        los = np.zeros((b, n), dtype=bool)
        shadow = np.zeros((b, n))
        interf = np.zeros((b, n))
        terms: list[FloatArray] = []
        leakage = inband.pool_leakage_weights(config) if config.link.inband_emission_model == "3gpp" else None
        for k, (snap, i) in enumerate(zip(snapshots, movers, strict=True)):
            if snap.positions_m.shape[0] != n:
                raise ValueError("all snapshots must hold the same number of vehicles")
            pos = snap.positions_m
            res = snap.slot * snap.n_subchannels + snap.subchannel
            rx_pos[k] = pos
            los[k] = snap.los[i]
            shadow[k] = snap.shadowing_db[i]
            tgt = snap.slot != snap.slot[i]
            disp = pos - pos[i]
            if config.road.wrap_distances:
                road.minimum_image(disp)
            dist = np.hypot(disp[:, 0], disp[:, 1])
            if config.link.max_range_m is not None:
                tgt &= dist <= config.link.max_range_m
            if neighbourhood_m is not None:
                tgt &= dist <= neighbourhood_m
            tgt[i] = False
            target[k] = tgt
            co = np.flatnonzero((res == res[i]) & (np.arange(n) != i))
            p_cj = _power_at_all(config, road, snap, co)  # [N, C]: co-channel transmitters at every receiver
            interf[k] = p_cj.sum(axis=1)
            terms.append(p_cj)
            if config.link.inband_emission_db is not None:  # leakage from the other subchannels of the subframe
                oth = np.flatnonzero((snap.slot == snap.slot[i]) & (res != res[i]))
                p_oj = _power_at_all(config, road, snap, oth)
                interf[k] += db_to_linear(config.link.inband_emission_db) * p_oj.sum(axis=1)
            elif leakage is not None:  # 3gpp: weighted by the leakage from each one's subchannel into i's
                oth = np.flatnonzero((snap.slot == snap.slot[i]) & (res != res[i]))
                p_oj = _power_at_all(config, road, snap, oth)
                interf[k] += p_oj @ leakage[snap.subchannel[i], snap.subchannel[oth]]
        c_max = max((t.shape[1] for t in terms), default=0)
        interferer = np.zeros((b, n, c_max))
        for k, t in enumerate(terms):
            interferer[k, :, : t.shape[1]] = t
        start = rx_pos[np.arange(b), np.asarray(movers)]
        if fields is not None and len(fields) != b:
            raise ValueError(f"fields must hold one entry per snapshot ({b}), got {len(fields)}")
        return cls(
            config, road, rx_pos, target, los, shadow, interf, interferer, start, np.asarray(movers), truth_los,
            None if fields is None else tuple(fields),
        )  # fmt: skip

    def take(self, index: NDArray[np.int64]) -> MoverLinks:
        """The mover links of snapshots ``index`` [M] (repeats allowed: M copies of one snapshot
        evaluate M candidate positions of its mover in one :meth:`success` call)."""
        return MoverLinks(
            self.config,
            self.road,
            self.rx_pos_m[index],
            self.target[index],
            self.los[index],
            self.shadow_db[index],
            self.interference_mw[index],
            self.interferer_mw[index],
            self.start_m[index],
            self.mover[index],
            self.truth_los,
            None if self.fields is None else tuple(self.fields[int(k)] for k in np.asarray(index)),
        )

    def _los_at(self, pos_m: FloatArray) -> NDArray[np.bool_]:
        if self.truth_los == "snapshot":
            return self.los
        if self.truth_los == "always" or self.road.kind == "highway":
            return np.ones_like(self.los)
        b, n = self.los.shape
        hc_m, vc_m = self.road.corridors(pos_m)
        hc, vc = self.road.corridors(self.rx_pos_m.reshape(-1, 2))
        return Road.corridor_los((hc.reshape(b, n), vc.reshape(b, n)), (hc_m[:, None], vc_m[:, None]))

    def _shadow_at(self, pos_m: FloatArray) -> FloatArray:
        """[B, N] shadowing of the mover links with each mover at ``pos_m`` [B, 2] (the fields', where set)."""
        if self.fields is None:
            return self.shadow_db
        out = self.shadow_db.copy()
        for b, field in enumerate(self.fields):  # one row per copy that has a field
            if field is not None:
                out[b] = field.row_db(int(self.mover[b]), self.rx_pos_m[b], pos_m[b : b + 1])[0]
        return out

    def success(self, pos_m: FloatArray) -> FloatArray:
        """[B, N] expected success probability of the mover's packet at each receiver.

        Args:
            pos_m: [B, 2] mover positions (one per snapshot).

        Returns:
            P per receiver; 0 for non-targets (and for receivers below the sensitivity).
        """
        cfg = self.config
        s_dbm = mean_rx_dbm(
            cfg, self.road, pos_m[:, None, :], self.rx_pos_m, self._los_at(pos_m), self._shadow_at(pos_m)
        )
        s_mw = db_to_linear(s_dbm)
        noise_mw = float(db_to_linear(noise_power_dbm(cfg.radio.noise_dbm, cfg.radio.noise_figure_db)))
        if cfg.link.model == "rayleigh":
            theta = 10.0 ** (cfg.link.sinr_threshold_db / 10.0)
            log_p = -theta * noise_mw / s_mw - np.log1p(theta * self.interferer_mw / s_mw[..., None]).sum(axis=-1)
            p = np.exp(log_p)
        else:
            sinr_db = 10.0 * np.log10(s_mw / (self.interference_mw + noise_mw))
            if cfg.link.model == "per_table":
                p = link.load_per_curve(cfg.link.per_curve, cfg.link.per_interpolation).success(sinr_db)
            else:
                p = link.threshold_success(sinr_db, cfg.link.sinr_threshold_db)
        if cfg.radio.sensitivity_dbm is not None:
            p = np.where(s_dbm < cfg.radio.sensitivity_dbm, 0.0, p)
        return np.where(self.target, p, 0.0)
