"""Ground truth for a moved transmitter: its links' success probability from the link model.

Given stage-1 snapshots and one mover per snapshot, :class:`MoverLinks` answers "if the mover
stood at position x, what would be the success probability of its packet at every receiver?"
with the simulator's own link model: path loss from x to each receiver (the snapshot's shadowing
and, by default, its LOS state per link), interference at each receiver from the other vehicles
transmitting on the mover's resource (fixed: they do not move), noise, then the PER table / Rayleigh
closed form / threshold. Expected values (no fading draw). Batched over snapshots: arrays are
``[B, N]`` for B snapshots of N vehicles.

``truth_los``: ``snapshot`` keeps each link's LOS/NLOS state from the snapshot (the mover is
taken to stay in its street system), ``geometry`` recomputes it from x with the corridor rule,
``always`` forces LOS.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ScenarioConfig
from cv2x_marl.sim import channel, link
from cv2x_marl.sim.road import Road
from cv2x_marl.sim.simulator import Snapshot
from cv2x_marl.units import SPEED_OF_LIGHT_MPS, db_to_linear, noise_power_dbm

FloatArray = NDArray[np.float64]
TRUTH_LOS = ("snapshot", "geometry", "always")


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


def _power_at_all(config: ScenarioConfig, road: Road, snap: Snapshot, tx: NDArray[np.int64]) -> FloatArray:
    """[N, T] mean power of transmitters ``tx`` at every vehicle of the snapshot (0 at themselves and
    beyond ``link.max_range_m``)."""
    pos = snap.positions_m
    p = db_to_linear(mean_rx_dbm(config, road, pos[tx][None], pos[:, None], snap.los[:, tx], snap.shadowing_db[:, tx]))
    if config.link.max_range_m is not None:
        d = np.hypot(*(pos[:, None, :] - pos[tx][None, :, :]).transpose(2, 0, 1))
        p = np.where(d <= config.link.max_range_m, p, 0.0)
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

    @classmethod
    def from_snapshots(
        cls,
        config: ScenarioConfig,
        snapshots: Sequence[Snapshot],
        movers: Sequence[int],
        truth_los: str = "snapshot",
        neighbourhood_m: float | None = None,
    ) -> MoverLinks:
        """Collect the mover links of each snapshot (all with the same vehicle count)."""
        if truth_los not in TRUTH_LOS:
            raise ValueError(f"truth_los must be one of {', '.join(TRUTH_LOS)}, got {truth_los!r}")
        road = Road.from_config(config.road)
        n = snapshots[0].positions_m.shape[0]
        b = len(snapshots)
        rx_pos = np.zeros((b, n, 2))
        target = np.zeros((b, n), dtype=bool)
        los = np.zeros((b, n), dtype=bool)
        shadow = np.zeros((b, n))
        interf = np.zeros((b, n))
        terms: list[FloatArray] = []
        for k, (snap, i) in enumerate(zip(snapshots, movers, strict=True)):
            if snap.positions_m.shape[0] != n:
                raise ValueError("all snapshots must hold the same number of vehicles")
            pos = snap.positions_m
            res = snap.slot * snap.n_subchannels + snap.subchannel
            rx_pos[k] = pos
            los[k] = snap.los[i]
            shadow[k] = snap.shadowing_db[i]
            tgt = snap.slot != snap.slot[i]
            dist = np.hypot(*(pos - pos[i]).T)
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
        c_max = max((t.shape[1] for t in terms), default=0)
        interferer = np.zeros((b, n, c_max))
        for k, t in enumerate(terms):
            interferer[k, :, : t.shape[1]] = t
        start = rx_pos[np.arange(b), np.asarray(movers)]
        return cls(config, road, rx_pos, target, los, shadow, interf, interferer, start, np.asarray(movers), truth_los)

    def _los_at(self, pos_m: FloatArray) -> NDArray[np.bool_]:
        if self.truth_los == "snapshot":
            return self.los
        if self.truth_los == "always" or self.road.kind == "highway":
            return np.ones_like(self.los)
        b, n = self.los.shape
        hc_m, vc_m = self.road.corridors(pos_m)
        hc, vc = self.road.corridors(self.rx_pos_m.reshape(-1, 2))
        hc, vc = hc.reshape(b, n), vc.reshape(b, n)
        return ((hc == hc_m[:, None]) & (hc >= 0)) | ((vc == vc_m[:, None]) & (vc >= 0))

    def success(self, pos_m: FloatArray) -> FloatArray:
        """[B, N] expected success probability of the mover's packet at each receiver.

        Args:
            pos_m: [B, 2] mover positions (one per snapshot).

        Returns:
            P per receiver; 0 for non-targets (and for receivers below the sensitivity).
        """
        cfg = self.config
        s_dbm = mean_rx_dbm(cfg, self.road, pos_m[:, None, :], self.rx_pos_m, self._los_at(pos_m), self.shadow_db)
        s_mw = db_to_linear(s_dbm)
        noise_mw = float(db_to_linear(noise_power_dbm(cfg.radio.noise_dbm, cfg.radio.noise_figure_db)))
        if cfg.link.model == "rayleigh":
            theta = 10.0 ** (cfg.link.sinr_threshold_db / 10.0)
            log_p = -theta * noise_mw / s_mw - np.log1p(theta * self.interferer_mw / s_mw[..., None]).sum(axis=-1)
            p = np.exp(log_p)
        else:
            sinr_db = 10.0 * np.log10(s_mw / (self.interference_mw + noise_mw))
            if cfg.link.model == "per_table":
                p = link.load_per_curve(cfg.link.per_curve).success(sinr_db)
            else:
                p = link.threshold_success(sinr_db, cfg.link.sinr_threshold_db)
        if cfg.radio.sensitivity_dbm is not None:
            p = np.where(s_dbm < cfg.radio.sensitivity_dbm, 0.0, p)
        return np.where(self.target, p, 0.0)


class SnapshotLinks:
    """Expected success of every link of a snapshot when any vehicles move (the env's reward).

    Resources, shadowing and (with ``truth_los="snapshot"``) LOS states stay those of the
    snapshot; positions are free. ``success(positions)`` returns ``P[tx, rx]`` for all N x N
    links: the signal from the moved transmitter, interference from the moved co-channel
    transmitters, half duplex, the link model. One call is array code over the N(N-1)/2 pairs.
    """

    def __init__(self, config: ScenarioConfig, snapshot: Snapshot, truth_los: str = "snapshot") -> None:
        if truth_los not in TRUTH_LOS:
            raise ValueError(f"truth_los must be one of {', '.join(TRUTH_LOS)}, got {truth_los!r}")
        if config.link.model == "rayleigh":
            raise ValueError("SnapshotLinks supports link.model per_table and threshold")
        self.config = config
        self.road = Road.from_config(config.road)
        self.snapshot = snapshot
        self.truth_los = truth_los
        n = snapshot.positions_m.shape[0]
        self.n = n
        self.iu, self.ju = np.triu_indices(n, 1)
        self.shadow_u = snapshot.shadowing_db[self.iu, self.ju]
        self.los_u = snapshot.los[self.iu, self.ju] if truth_los == "snapshot" else np.ones(self.iu.size, bool)
        res = snapshot.slot * snapshot.n_subchannels + snapshot.subchannel
        uniq, self.res_idx = np.unique(res, return_inverse=True)
        self.onehot = (self.res_idx[:, None] == np.arange(uniq.size)[None, :]).astype(np.float64)  # [N, R']
        self.same_res = self.res_idx[:, None] == self.res_idx[None, :]
        slot = snapshot.slot
        self.target = slot[:, None] != slot[None, :]  # [tx, rx]: half duplex excluded (and the diagonal)
        self.same_slot_other = (slot[:, None] == slot[None, :]) & ~self.same_res
        radio = config.radio
        self.eirp_dbm = radio.tx_power_dbm + radio.tx_antenna_gain_dbi + radio.rx_antenna_gain_dbi
        self.noise_mw = float(db_to_linear(noise_power_dbm(radio.noise_dbm, radio.noise_figure_db)))
        self.curve = link.load_per_curve(config.link.per_curve)
        self.ibe = (
            None if config.link.inband_emission_db is None else float(db_to_linear(config.link.inband_emission_db))
        )
        self._fast = (
            config.channel.pathloss == "winner_b1" and truth_los != "geometry" and not config.road.wrap_distances
        )
        if self._fast:
            fc_ghz = radio.carrier_hz / 1e9
            h = config.channel.effective_height_m
            self._d_bp = 4.0 * h * h * radio.carrier_hz / SPEED_OF_LIGHT_MPS
            self._c_near = 41.0 + 20.0 * np.log10(fc_ghz / 5.0)
            self._c_far = 9.45 - 34.6 * np.log10(h) + 2.7 * np.log10(fc_ghz / 5.0)
            self._c_nlos = 20.0 + 3.0 * np.log10(fc_ghz / 5.0)
            self._c_free = 46.4 + 20.0 * np.log10(fc_ghz / 5.0)
            self._nlos_idx = np.flatnonzero(~self.los_u)
            self._gain_u = self.eirp_dbm - self.shadow_u

    def _winner_fast_db(self, pos: FloatArray) -> FloatArray:
        """WINNER+ B1 loss of the unordered pairs with the snapshot's LOS states (same formulas as
        :func:`cv2x_marl.sim.channel.winner_b1_db`, fused; NLOS only on the NLOS pairs)."""
        dmin = self.config.channel.min_distance_m
        dx = pos[self.iu, 0] - pos[self.ju, 0]
        dy = pos[self.iu, 1] - pos[self.ju, 1]
        ld = 0.5 * np.log10(np.maximum(dx * dx + dy * dy, dmin * dmin))
        d = 10.0**ld
        pl = np.where(d < self._d_bp, 22.7 * ld + self._c_near, 40.0 * ld + self._c_far)
        k = self._nlos_idx
        if k.size:
            ax = np.maximum(np.abs(dx[k]), dmin)
            ay = np.maximum(np.abs(dy[k]), dmin)
            lx, ly = np.log10(ax), np.log10(ay)
            nx = np.maximum(2.8 - 0.0024 * ax, 1.84)
            ny = np.maximum(2.8 - 0.0024 * ay, 1.84)
            los_x = np.where(ax < self._d_bp, 22.7 * lx + self._c_near, 40.0 * lx + self._c_far)
            los_y = np.where(ay < self._d_bp, 22.7 * ly + self._c_near, 40.0 * ly + self._c_far)
            n1 = los_x + self._c_nlos - 12.5 * nx + 10.0 * nx * ly
            n2 = los_y + self._c_nlos - 12.5 * ny + 10.0 * ny * lx
            pl[k] = np.minimum(n1, n2)
        return np.maximum(pl, 20.0 * ld + self._c_free)

    def power_mw(self, positions_m: FloatArray) -> FloatArray:
        """[N, N] mean received power (symmetric; zero on the diagonal and beyond the cut-off)."""
        pos = positions_m
        a, b = self.iu, self.ju
        if self._fast and self.config.link.max_range_m is None:
            mw = 10.0 ** ((self._gain_u - self._winner_fast_db(pos)) / 10.0)
            m = np.zeros((self.n, self.n))
            m[a, b] = mw
            m[b, a] = mw
            return m
        if self.truth_los == "geometry" and self.road.kind == "grid":
            hc, vc = self.road.corridors(pos)
            los = ((hc[a] == hc[b]) & (hc[a] >= 0)) | ((vc[a] == vc[b]) & (vc[a] >= 0))
        else:
            los = self.los_u
        dbm = mean_rx_dbm(self.config, self.road, pos[a], pos[b], los, self.shadow_u)
        mw = db_to_linear(dbm)
        rng = self.config.link.max_range_m
        if rng is not None:
            mw = np.where(np.hypot(*(pos[a] - pos[b]).T) <= rng, mw, 0.0)
        m = np.zeros((self.n, self.n))
        m[a, b] = mw
        m[b, a] = mw
        return m

    def success(self, positions_m: FloatArray) -> FloatArray:
        """[N(tx), N(rx)] expected success probability; 0 where rx is not a target of tx."""
        m = self.power_mw(positions_m)  # m[c, j]: power of c at j
        per_res = m.T @ self.onehot  # [rx, R'] total power on each resource at each receiver
        interference = per_res[:, self.res_idx].T - m  # [tx, rx]
        if self.ibe is not None:
            # leakage from the other subchannels of the transmitter's subframe: sum_c S[tx, c] m[c, rx]
            interference = interference + self.ibe * (self.same_slot_other.astype(np.float64) @ m)
        sinr_db = 10.0 * np.log10(np.maximum(m, 1e-300) / (np.maximum(interference, 0.0) + self.noise_mw))
        if self.config.link.model == "per_table":
            p = self.curve.success(sinr_db)
        else:
            p = link.threshold_success(sinr_db, self.config.link.sinr_threshold_db)
        sens = self.config.radio.sensitivity_dbm
        if sens is not None:
            p = np.where(10.0 * np.log10(np.maximum(m, 1e-300)) < sens, 0.0, p)
        return np.where(self.target, p, 0.0)
