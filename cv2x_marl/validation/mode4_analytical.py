"""Analytical model of the PDR of C-V2X (LTE-V2X) sidelink Mode 4 on a highway.

An independent Python implementation of

    M. Gonzalez-Martin, M. Sepulcre, R. Molina-Masegosa, J. Gozalvez, "Analytical Models of the
    Performance of C-V2X Mode 4 Vehicular Communications", IEEE Trans. Veh. Technol. 68(2),
    pp. 1155-1166, Feb. 2019, DOI 10.1109/TVT.2018.2888704, arXiv:1807.06508.

Equation numbers below are the paper's, as the authors' reference MATLAB code
(github.com/msepulcre/C-V2X) labels them. That code was read to pin the discretisation (0.1 dB
grids, 1 m sensing grid, interferers up to 1000 m, noise over the data resource blocks) so that
the numbers can be compared; nothing here is a transliteration of it, and this module imports
nothing from :mod:`cv2x_marl.sim`, so it is an independent check of the simulator.

The model. Vehicles lie on a line with ``beta`` vehicles per metre, each transmitting ``lambda``
packets per second on one sub-channel of ``S`` per subframe. A packet sent by ``v_t`` to ``v_r``
at distance ``d`` is lost for one of four reasons, checked in this order (eq. 6):

* half duplex, ``delta_HD = lambda / 1000`` (eq. 7): ``v_r`` transmits in the same subframe;
* below the sensing power threshold ``P_SEN``,
  ``delta_SEN(d) = 1/2 (1 - erf((P_t - PL(d) - P_SEN) / (sigma sqrt 2)))`` (eq. 10), with
  log-normal shadowing of standard deviation ``sigma``;
* propagation, ``delta_PRO(d) = int BLER(gamma) f_SNR(gamma | P_r >= P_SEN) d gamma`` (eq. 13);
* collision, ``delta_COL(d) = 1 - prod_i (1 - p_SIM(i) p_INT(i, d))`` over the interferers ``i``
  (eqs. 14, 15), with ``p_INT = (p_SINR - delta_PRO) / (1 - delta_PRO)`` (eqs. 17, 18) and the
  probability ``p_SIM`` that ``i`` uses the same resource from the overlap of the candidate sets
  of ``v_t`` and ``i`` (eqs. 23-33): Step 2 of the SPS selection alone (eq. 23) or Step 3 (its
  threshold raised until 20 % of the resources are candidates, eq. 31), weighted by the
  channel busy ratio (eqs. 21, 22, 34).

Every term is a probability conditional on the previous ones not having happened; the
unconditional shares of eqs. 6.1-6.5 are

    delta_HD, delta_SEN (1 - delta_HD), delta_PRO (1 - delta_HD)(1 - delta_SEN),
    delta_COL (1 - delta_HD)(1 - delta_SEN)(1 - delta_PRO),

and ``PDR = 1 - (sum of them) = (1 - delta_HD)(1 - delta_SEN)(1 - delta_PRO)(1 - delta_COL)``.

Example:
    >>> out = analytical_pdr([0.0, 100.0, 300.0], 100.0, 10.0, 20.0, 4, 190)
    >>> bool(out["pdr"][0] <= 1.0 - 10.0 / 1000.0)
    True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.signal import fftconvolve
from scipy.special import erf, erfc

__all__ = [
    "BLER_190B_R05",
    "BLER_190B_R07",
    "BlerCurve",
    "alpha_weight",
    "analytical_pdr",
    "excluded_resources",
    "noise_power_dbm",
    "path_loss_db",
]

FloatArray = NDArray[np.float64]

#: speed of light as the reference code takes it for the WINNER+ B1 breakpoint, m/s
_C_MPS = 3e8
#: the power axis of the SNR/SINR densities spans [-200, 200] dB(m), as in the reference code
_POWER_AXIS_HALF_SPAN_DB = 200.0
#: mean power of the "interferer" that makes the interference-free SNR density (reference code)
_NO_INTERFERENCE_DBM = -180.0
#: interferer rows convolved at once in :func:`_mean_bler`
_ROWS_PER_BATCH = 64


@dataclass(frozen=True)
class BlerCurve:
    """A BLER(SINR) curve: linear interpolation between points, constant outside.

    Attributes:
        name: a label.
        sinr_db: ascending SINR points, dB.
        bler: block error rate at each point, in [0, 1].
    """

    name: str
    sinr_db: tuple[float, ...]
    bler: tuple[float, ...]

    def __post_init__(self) -> None:
        s = np.asarray(self.sinr_db, dtype=np.float64)
        b = np.asarray(self.bler, dtype=np.float64)
        if s.ndim != 1 or s.shape != b.shape or s.size < 2:
            raise ValueError("BlerCurve: sinr_db and bler must be 1-D of the same length >= 2")
        if np.any(np.diff(s) <= 0.0):
            raise ValueError("BlerCurve: sinr_db must increase strictly")
        if np.any(b < 0.0) or np.any(b > 1.0):
            raise ValueError("BlerCurve: bler must lie in [0, 1]")

    def __call__(self, sinr_db: ArrayLike) -> FloatArray:
        """BLER at ``sinr_db`` (any shape); the first value below the table, the last above it."""
        s = np.asarray(self.sinr_db, dtype=np.float64)
        b = np.asarray(self.bler, dtype=np.float64)
        return np.interp(np.asarray(sinr_db, dtype=np.float64), s, b, left=b[0], right=b[-1])


#: 190-byte packet, QPSK, code rate 0.7, relative speed 280 km/h (3GPP R1-160284), as the paper
#: uses it for S = 4 sub-channels: BLER 1 up to 0 dB, 1e-3 from 16 dB to 20 dB, 1e-4 above 20 dB
BLER_190B_R07 = BlerCurve(
    "190B-QPSK-r0.7-280kmh",
    (0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 20.0 + 1e-6),
    (1.0, 0.9, 0.7, 0.4, 0.13, 0.045, 0.017, 0.007, 1e-3, 1e-3, 1e-3, 1e-4),
)
#: 190-byte packet, QPSK, code rate 0.5, 280 km/h (3GPP R1-160284), for S = 2 sub-channels
BLER_190B_R05 = BlerCurve(
    "190B-QPSK-r0.5-280kmh",
    (-2.0, 0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 20.0 + 1e-6),
    (1.0, 0.9, 0.7, 0.3, 0.09, 0.02, 0.002, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-4),
)

#: (packet bytes, sub-channels) -> (resource blocks of the data field, BLER curve) of the paper
PAPER_FORMATS: dict[tuple[int, int], tuple[int, BlerCurve]] = {
    (190, 4): (10, BLER_190B_R07),
    (190, 2): (12, BLER_190B_R05),
}


def _check_range(name: str, value: float, lo: float, hi: float, lo_open: bool = False) -> float:
    """``value`` as a float, or a ValueError naming ``name`` and the allowed range."""
    v = float(value)
    bad_lo = v <= lo if lo_open else v < lo
    if not math.isfinite(v) or bad_lo or v > hi:
        left = "(" if lo_open else "["
        raise ValueError(f"{name} must be in {left}{lo:g}, {hi:g}], got {value!r}")
    return v


def noise_power_dbm(data_rbs: int, total_rbs: int = 50, channel_noise_dbm: float = -95.0) -> float:
    """Noise over the data field of a packet: the 10 MHz channel's noise scaled to its RBs.

    ``-95 dBm`` is ``-174 dBm/Hz + 10 log10(10 MHz) + 9 dB`` noise figure over the 50 RBs of 10 MHz.

    Args:
        data_rbs: resource blocks of the packet's data field, in [1, total_rbs].
        total_rbs: resource blocks of the channel.
        channel_noise_dbm: noise power over the whole channel, noise figure included.

    Returns:
        ``channel_noise_dbm - 10 log10(total_rbs / data_rbs)``.
    """
    if not 1 <= int(total_rbs) <= 1000 or int(total_rbs) != total_rbs:
        raise ValueError(f"total_rbs must be an integer in [1, 1000], got {total_rbs!r}")
    if not 1 <= int(data_rbs) <= total_rbs or int(data_rbs) != data_rbs:
        raise ValueError(f"data_rbs must be an integer in [1, total_rbs={total_rbs}], got {data_rbs!r}")
    return float(channel_noise_dbm - 10.0 * math.log10(total_rbs / data_rbs))


def path_loss_db(
    distance_m: ArrayLike,
    carrier_hz: float = 5.91e9,
    antenna_height_m: float = 1.5,
    shadowing_std_db: float = 3.0,
    min_distance_m: float = 3.0,
) -> tuple[FloatArray, FloatArray]:
    """WINNER+ B1 LOS path loss with the free-space floor (3GPP TR 36.885 Table A.1.4-1), the
    paper's propagation model, and the shadowing standard deviation.

    ``PL = 22.7 log10 d + 27 + 20 log10 f_GHz`` below the breakpoint ``d_BP = 4 h h f / c``,
    ``40 log10 d + 7.56 - 2 * 17.3 log10 h + 2.7 log10 f_GHz`` beyond it, and at least
    ``20 log10 d + 46.4 + 20 log10(f_GHz / 5)``; distances below ``min_distance_m`` are clipped.

    Args:
        distance_m: distances (any shape, the sign is ignored), m.
        carrier_hz: carrier frequency, Hz.
        antenna_height_m: effective antenna height of both ends, m.
        shadowing_std_db: log-normal shadowing standard deviation, dB.
        min_distance_m: clipping distance, m.

    Returns:
        (path loss in dB, shadowing standard deviation in dB), both of the shape of ``distance_m``.
    """
    d = np.maximum(np.abs(np.asarray(distance_m, dtype=np.float64)), min_distance_m)
    f_ghz = carrier_hz / 1e9
    h = antenna_height_m
    d_bp_m = 4.0 * h * h * carrier_hz / _C_MPS
    near = 22.7 * np.log10(d) + 27.0 + 20.0 * np.log10(f_ghz)
    far = 40.0 * np.log10(d) + 7.56 - 2.0 * 17.3 * np.log10(h) + 2.7 * np.log10(f_ghz)
    free = 20.0 * np.log10(d) + 46.4 + 20.0 * np.log10(f_ghz / 5.0)
    pl = np.maximum(np.where(d < d_bp_m, near, far), free)
    return pl, np.full_like(pl, shadowing_std_db)


def excluded_resources(sensed_vehicles: float, n_resources: float) -> float:
    """Expected number of resources excluded in Step 2 (eq. 29) or Step 3 (eq. 33).

    ``N_e = S/2 + sum_{k=1}^{floor(S/2)} max(1 - k / (N - S/2), 0)`` with ``S`` the expected number
    of vehicles whose reservations are sensed (eq. 29.1 or 32.1) and ``N`` the resources (eq. 28).

    Args:
        sensed_vehicles: ``S_PSR``, >= 0.
        n_resources: ``N``; must exceed ``S_PSR / 2``.

    Returns:
        ``N_e``.
    """
    half = sensed_vehicles / 2.0
    if sensed_vehicles < 0.0 or not half < n_resources:
        raise ValueError(
            f"eq. 29 needs 0 <= S_PSR / 2 < N; got S_PSR = {sensed_vehicles:g} sensed vehicles and N = "
            f"{n_resources:g} resources: lower density_veh_per_km or raise n_subchannels"
        )
    k = np.arange(1, math.floor(half + 1e-9) + 1, dtype=np.float64)
    return float(half + np.maximum(1.0 - k / (n_resources - half), 0.0).sum())


def alpha_weight(cbr: float) -> float:
    """Weight of the Step 2 collision probability (eq. 22): 0 below CBR 0.2, ``2 CBR - 0.4`` up to
    0.7, then 1."""
    if cbr < 0.2:
        return 0.0
    if cbr <= 0.7:
        return 2.0 * cbr - 0.4
    return 1.0


def _psr(distance_m: FloatArray, tx_power_dbm: float, threshold_dbm: float, **pl_kw: float) -> FloatArray:
    """Packet sensing ratio (eq. 11): the probability that a packet from ``distance_m`` arrives
    above ``threshold_dbm`` under log-normal shadowing."""
    pl, std = path_loss_db(distance_m, **pl_kw)
    return np.asarray(0.5 * (1.0 + erf((tx_power_dbm - pl - threshold_dbm) / (std * math.sqrt(2.0)))))


def _normalised(log_density: FloatArray, step_db: float) -> FloatArray:
    """Rows of ``exp(log_density)`` scaled so that each sums to 1 / step (a density on the grid)."""
    with np.errstate(invalid="ignore"):
        top = np.max(log_density, axis=-1, keepdims=True)
        dens = np.exp(log_density - top)
    dens = np.where(np.isfinite(dens), dens, 0.0)
    return np.asarray(dens / (dens.sum(axis=-1, keepdims=True) * step_db))


def _signal_density(
    mean_dbm: FloatArray, std_db: FloatArray, axis_dbm: FloatArray, threshold_dbm: float, step_db: float
) -> FloatArray:
    """[D, X] density of the received power in dBm, Gaussian (shadowing) truncated below the
    sensing threshold: the packets of eq. 13 and eq. 17 arrive above ``P_SEN``."""
    z = (axis_dbm[None, :] - mean_dbm[:, None]) / std_db[:, None]
    logd = -0.5 * z * z
    logd = np.where(axis_dbm[None, :] < threshold_dbm - 1e-9, -np.inf, logd)
    return _normalised(logd, step_db)


def _interference_plus_noise_density(
    mean_dbm: FloatArray, std_db: FloatArray, axis_dbm: FloatArray, noise_dbm: float, step_db: float
) -> FloatArray:
    """[I, X] density of ``10 log10(I + N)`` in dBm, ``I`` log-normal (mean ``mean_dbm`` in dB),
    ``N`` the noise power: the change of variables ``y = 10 log10(10^(i/10) + N)``, zero at and
    below the noise."""
    above = axis_dbm > noise_dbm + 1e-9
    y = axis_dbm[above]
    lin = 10.0 ** (y / 10.0)
    excess = lin - 10.0 ** (noise_dbm / 10.0)
    i_dbm = 10.0 * np.log10(excess)
    z = (i_dbm[None, :] - mean_dbm[:, None]) / std_db[:, None]
    logd = np.full((mean_dbm.shape[0], axis_dbm.shape[0]), -np.inf)
    logd[:, above] = (np.log(lin) - np.log(excess))[None, :] - np.log(std_db)[:, None] - 0.5 * z * z
    return _normalised(logd, step_db)


def _mean_bler(
    signal_density: FloatArray, in_density: FloatArray, curve: BlerCurve, axis_dbm: FloatArray, step_db: float
) -> FloatArray:
    """[D, I] mean BLER over the SINR ``x - y`` of the received power ``x`` (density per row of
    ``signal_density``) and interference plus noise ``y`` (per row of ``in_density``), eq. 13 and
    eq. 17: ``sum_x sum_y f_S(x) f_IN(y) BLER(x - y) step^2``.

    The double sum is done as one convolution per interferer row,
    ``g(x) = sum_y f_IN(y) BLER(x - y) step``, then one matrix product over ``x``.
    """
    n = axis_dbm.shape[0]
    lag_db = step_db * np.arange(-(n - 1), n)
    bler_of_lag = curve(lag_db)
    out = np.empty((signal_density.shape[0], in_density.shape[0]))
    for lo in range(0, in_density.shape[0], _ROWS_PER_BATCH):  # bounded memory: a batch of FFTs at a time
        rows = in_density[lo : lo + _ROWS_PER_BATCH]
        g = fftconvolve(rows, bler_of_lag[None, :], mode="full", axes=1)[:, n - 1 : 2 * n - 1] * step_db
        out[:, lo : lo + rows.shape[0]] = (signal_density * step_db) @ g.T
    return out


def _collision_probability(
    p_int: FloatArray,
    distance_m: FloatArray,
    interferer_m: FloatArray,
    common_candidates: FloatArray,
    n_candidates: float,
    packets_per_s: float,
    tx_power_dbm: float,
    threshold_dbm: float,
    pl_kw: dict[str, float],
) -> FloatArray:
    """[D] ``delta_COL`` of eq. 14 for one step of the selection (Step 2: eq. 23, Step 3: eq. 31).

    ``p_SIM(i) = p_s(i) C_c(|x_i + d|) / N_c^2`` with ``p_s = 1 - (1 - 1/tau) PSR(x_i + d)`` (eq. 24,
    ``tau = lambda`` as in the reference code), ``C_c`` read at the distance rounded to the metre.
    """
    to_tx_m = interferer_m[None, :] + distance_m[:, None]
    p_sensed = _psr(to_tx_m, tx_power_dbm, threshold_dbm, **pl_kw)
    p_s = 1.0 - (1.0 - 1.0 / packets_per_s) * p_sensed
    lag = np.floor(np.abs(to_tx_m) + 0.5).astype(np.int64)
    p_sim = p_s * common_candidates[lag] / (n_candidates * n_candidates)
    p_col = p_sim * p_int
    return np.asarray(1.0 - np.prod(1.0 - p_col, axis=1))


def analytical_pdr(
    distance_m: ArrayLike,
    density_veh_per_km: float,
    packets_per_s: float,
    tx_power_dbm: float,
    n_subchannels: int,
    packet_bytes: int,
    *,
    sensing_threshold_dbm: float = -90.5,
    bler_curve: BlerCurve | None = None,
    data_rbs: int | None = None,
    noise_dbm: float | None = None,
    carrier_hz: float = 5.91e9,
    antenna_height_m: float = 1.5,
    shadowing_std_db: float = 3.0,
    grid_step_db: float = 0.1,
    interferer_range_m: float = 1000.0,
    sensing_range_m: float = 1500.0,
    candidate_fraction: float = 0.2,
) -> dict[str, FloatArray]:
    """PDR(d) and the four loss probabilities of C-V2X Mode 4 (Gonzalez-Martin et al. 2019).

    Args:
        distance_m: transmitter-receiver distances, m, each in [0, 1500].
        density_veh_per_km: vehicles per km of highway ``1000 beta``, in (0, 1000].
        packets_per_s: packet rate ``lambda`` (the reservation interval is ``1000 / lambda`` ms),
            in [1, 100].
        tx_power_dbm: transmit power ``P_t`` (no antenna gains), in [-30, 46] dBm.
        n_subchannels: sub-channels per subframe ``S``, in [1, 50].
        packet_bytes: packet size ``B``; with ``bler_curve`` None, ``(B, S)`` must be one of the
            paper's formats, (190, 4) or (190, 2), which fix the BLER curve and the data RBs.
        sensing_threshold_dbm: ``P_SEN`` (received power over the packet), dBm.
        bler_curve: the link-level curve; None: the paper's for ``(B, S)``.
        data_rbs: resource blocks of the data field (sets the noise); None: the paper's.
        noise_dbm: noise power over the data field, noise figure included; None:
            :func:`noise_power_dbm` of ``data_rbs``.
        carrier_hz, antenna_height_m, shadowing_std_db: propagation (:func:`path_loss_db`).
        grid_step_db: step of the power and SINR grids of eqs. 13 and 17, in (0, 1] dB.
        interferer_range_m: interferers every ``1 / beta`` up to this distance from the receiver.
        sensing_range_m: half-width of the 1 m grid of the sensing integrals (eqs. 29.1, 30.2).
        candidate_fraction: share of the resources that must remain candidates (3GPP: 0.2).

    Returns:
        A dict of float arrays. Per distance ([D]): ``distance_m``, ``pdr`` (eq. 6) and the
        unconditional loss shares ``delta_hd``, ``delta_sen``, ``delta_pro``, ``delta_col``
        (eqs. 6.1-6.5; ``pdr`` plus the four is 1); the conditional probabilities ``p_hd`` (eq. 7),
        ``p_sen`` (eq. 10), ``p_pro`` (eq. 13), ``p_col`` (eq. 21), ``p_col_step2`` and
        ``p_col_step3`` (eq. 14 with eqs. 23 and 31), so that ``pdr = (1 - p_hd)(1 - p_sen)
        (1 - p_pro)(1 - p_col)``. Scalars (0-d): ``cbr`` (eq. 34), ``alpha`` (eq. 22),
        ``n_resources`` (eq. 28), ``n_excluded_step2`` (eq. 29), ``n_excluded_step3`` (eq. 33),
        ``threshold_step3_dbm``, ``noise_dbm``.

    Raises:
        ValueError: an argument out of its range (named, with the range), or a density at which
            eq. 29 does not hold (more sensed vehicles than twice the resources).
    """
    d, density, lam, pt, s, psen, step, int_range, sen_range, frac = _checked_arguments(
        distance_m, density_veh_per_km, packets_per_s, tx_power_dbm, n_subchannels, packet_bytes,
        sensing_threshold_dbm, grid_step_db, carrier_hz, antenna_height_m, shadowing_std_db,
        interferer_range_m, sensing_range_m, candidate_fraction,
    )  # fmt: skip
    curve, noise = _link_curve_and_noise(packet_bytes, s, bler_curve, data_rbs, noise_dbm)
    beta = density / 1000.0  # veh/m
    pl_kw = {"carrier_hz": float(carrier_hz), "antenna_height_m": float(antenna_height_m)}
    pl_kw["shadowing_std_db"] = float(shadowing_std_db)

    # --- half duplex (eq. 7), sensing (eq. 10), propagation (eq. 13)
    p_hd = np.full(d.shape, lam / 1000.0)
    pl_d, std_d = path_loss_db(d, **pl_kw)
    p_sen = 0.5 * erfc((pt - pl_d - psen) / (std_d * math.sqrt(2.0)))
    half = round(_POWER_AXIS_HALF_SPAN_DB / step)
    axis_dbm = step * np.arange(-half, half + 1, dtype=np.float64)
    f_signal = _signal_density(pt - pl_d, std_d, axis_dbm, psen, step)
    f_noise = _interference_plus_noise_density(
        np.array([_NO_INTERFERENCE_DBM]), np.array([shadowing_std_db]), axis_dbm, noise, step
    )
    p_pro = _mean_bler(f_signal, f_noise, curve, axis_dbm, step)[:, 0]
    interferer_m, p_int = _interference_on_links(
        d.size, int_range, beta, pt, f_signal, p_pro, curve, axis_dbm, noise, step, pl_kw
    )

    # --- resources (eq. 28) and Step 2: sensing ratio, excluded and common resources (eqs. 26-30, 34)
    n_res = s * 1000.0 / lam
    n_cand = frac * n_res
    grid_m = np.arange(-round(sen_range), round(sen_range) + 1, dtype=np.float64)
    psr = _psr(grid_m, pt, psen, **pl_kw)
    s_psr = beta * float(psr.sum())  # eq. 29.1
    ne2 = excluded_resources(s_psr, n_res)  # eq. 29
    na2 = n_res - ne2
    cbr = ne2 / n_res  # eq. 34
    r_psr = np.correlate(psr, psr, mode="full")[psr.size - 1 :]  # eq. 30.2, lags 0, 1, ... m
    r0 = float(r_psr[0])  # eq. 40

    def common_candidates(ne: float, na: float) -> FloatArray:
        ce = (r_psr / r0) * (beta * ne * r0 / s_psr - ne * ne / n_res) + ne * ne / n_res  # eq. 30
        ca = n_res - 2.0 * ne + ce  # eq. 27
        return np.asarray(ca * (n_cand / na) ** 2)  # eq. 26

    if interferer_m.size and s_psr > 0.0:
        p_col2 = _collision_probability(
            p_int, d, interferer_m, common_candidates(ne2, na2), n_cand, lam, pt, psen, pl_kw
        )
    else:
        p_col2 = np.zeros(d.shape)
    alpha = alpha_weight(cbr)

    # --- Step 3: raise the threshold until N_a >= N_c (eqs. 32, 33), then eq. 31
    th3, ne3 = _step3_threshold(grid_m, beta, pt, psen, step, n_res, n_cand, pl_kw)
    na3 = n_res - ne3
    if alpha < 1.0 and interferer_m.size and s_psr > 0.0:
        p_col3 = _collision_probability(
            p_int, d, interferer_m, common_candidates(ne3, na3), n_cand, lam, pt, th3, pl_kw
        )
    else:
        p_col3 = np.zeros(d.shape)
    p_col = alpha * p_col2 + (1.0 - alpha) * p_col3  # eq. 21
    scalars = {"cbr": cbr, "alpha": alpha, "n_resources": n_res, "n_excluded_step2": ne2, "n_excluded_step3": ne3}
    scalars |= {"threshold_step3_dbm": th3, "noise_dbm": noise}
    return _pdr_and_shares(d, p_hd, p_sen, p_pro, p_col, p_col2, p_col3, scalars)


def _checked_arguments(
    distance_m: ArrayLike,
    density_veh_per_km: float,
    packets_per_s: float,
    tx_power_dbm: float,
    n_subchannels: int,
    packet_bytes: int,
    sensing_threshold_dbm: float,
    grid_step_db: float,
    carrier_hz: float,
    antenna_height_m: float,
    shadowing_std_db: float,
    interferer_range_m: float,
    sensing_range_m: float,
    candidate_fraction: float,
) -> tuple[FloatArray, float, float, float, int, float, float, float, float, float]:
    """:func:`analytical_pdr`'s arguments checked in its order (ValueError naming one out of its range): ``(d,
    density, packets per s, P_t, S, P_SEN, grid step, interferer range, sensing range, candidate fraction)``."""
    d = np.atleast_1d(np.asarray(distance_m, dtype=np.float64))
    if d.ndim != 1 or d.size == 0:
        raise ValueError(f"distance_m must be a scalar or a non-empty 1-D array, got shape {d.shape}")
    if not np.all(np.isfinite(d)) or np.any(d < 0.0) or np.any(d > 1500.0):
        raise ValueError("distance_m must be in [0, 1500] m (finite)")
    density = _check_range("density_veh_per_km", density_veh_per_km, 0.0, 1000.0, lo_open=True)
    lam = _check_range("packets_per_s", packets_per_s, 1.0, 100.0)
    pt = _check_range("tx_power_dbm", tx_power_dbm, -30.0, 46.0)
    if int(n_subchannels) != n_subchannels or not 1 <= int(n_subchannels) <= 50:
        raise ValueError(f"n_subchannels must be an integer in [1, 50], got {n_subchannels!r}")
    if int(packet_bytes) != packet_bytes or not 1 <= int(packet_bytes) <= 10000:
        raise ValueError(f"packet_bytes must be an integer in [1, 10000], got {packet_bytes!r}")
    psen = _check_range("sensing_threshold_dbm", sensing_threshold_dbm, -150.0, 0.0)
    step = _check_range("grid_step_db", grid_step_db, 0.0, 1.0, lo_open=True)
    _check_range("carrier_hz", carrier_hz, 1e8, 1e11)
    _check_range("antenna_height_m", antenna_height_m, 0.1, 10.0)
    _check_range("shadowing_std_db", shadowing_std_db, 0.0, 20.0, lo_open=True)
    int_range = _check_range("interferer_range_m", interferer_range_m, 0.0, 5000.0)
    sen_range = _check_range("sensing_range_m", sensing_range_m, 10.0, 5000.0)
    frac = _check_range("candidate_fraction", candidate_fraction, 0.0, 1.0, lo_open=True)
    if int_range + float(d.max()) > 2.0 * sen_range:
        raise ValueError(
            f"interferer_range_m + max(distance_m) must not exceed 2 * sensing_range_m ({2.0 * sen_range:g} m)"
        )
    return d, density, lam, pt, int(n_subchannels), psen, step, int_range, sen_range, frac


def _link_curve_and_noise(
    packet_bytes: int, s: int, bler_curve: BlerCurve | None, data_rbs: int | None, noise_dbm: float | None
) -> tuple[BlerCurve, float]:
    """The BLER curve and the noise power (dBm) of :func:`analytical_pdr`: those given, else the paper's format
    ``(packet_bytes, s)``'s (ValueError: not one of the paper's formats, or ``noise_dbm`` out of its range)."""
    fmt = PAPER_FORMATS.get((int(packet_bytes), s))
    if bler_curve is None or (data_rbs is None and noise_dbm is None):
        if fmt is None:
            raise ValueError(
                f"packet_bytes={packet_bytes} with n_subchannels={s} is not one of the paper's formats "
                f"{sorted(PAPER_FORMATS)}; pass bler_curve and data_rbs (or noise_dbm)"
            )
    curve = bler_curve if bler_curve is not None else PAPER_FORMATS[(int(packet_bytes), s)][1]
    if noise_dbm is None:
        rbs = data_rbs if data_rbs is not None else PAPER_FORMATS[(int(packet_bytes), s)][0]
        noise = noise_power_dbm(rbs)
    else:
        noise = _check_range("noise_dbm", noise_dbm, -200.0, 0.0)
    return curve, noise


def _interference_on_links(
    n_links: int,
    int_range: float,
    beta: float,
    pt: float,
    f_signal: FloatArray,
    p_pro: FloatArray,
    curve: BlerCurve,
    axis_dbm: FloatArray,
    noise: float,
    step: float,
    pl_kw: dict[str, float],
) -> tuple[FloatArray, FloatArray]:
    """The interferers' distances from the receiver (every ``1 / beta`` up to ``int_range``, the receiver
    excluded) and ``p_INT`` [links, interferers], the loss each one alone causes on each link (eqs. 17, 18)."""
    k_int = round(int_range * beta)
    ks = np.arange(-k_int, k_int + 1)
    interferer_m = ks[ks != 0] / beta  # every 1/beta from the receiver, the receiver excluded
    if interferer_m.size:
        pl_i, std_i = path_loss_db(interferer_m, **pl_kw)
        f_in = _interference_plus_noise_density(pt - pl_i, std_i, axis_dbm, noise, step)
        p_sinr = _mean_bler(f_signal, f_in, curve, axis_dbm, step)
        with np.errstate(invalid="ignore", divide="ignore"):
            p_int = (p_sinr - p_pro[:, None]) / (1.0 - p_pro[:, None])
        p_int = np.where(p_pro[:, None] == 1.0, 0.0, p_int)
    else:
        p_int = np.zeros((n_links, 0))
    return interferer_m, p_int


def _step3_threshold(
    grid_m: FloatArray,
    beta: float,
    pt: float,
    psen: float,
    step: float,
    n_res: float,
    n_cand: float,
    pl_kw: dict[str, float],
) -> tuple[float, float]:
    """Step 3's threshold, raised from ``psen`` in ``step`` dB until N_a >= N_c (eqs. 32, 33), and the resources
    it excludes (ValueError: the search did not end, a guard, not a model step)."""
    th3 = psen
    while True:
        s_psr3 = 2.0 * beta * float(_psr(grid_m, pt, th3, **pl_kw).sum())  # eq. 32.1
        ne3 = excluded_resources(s_psr3, n_res) if s_psr3 / 2.0 < n_res else n_res  # eq. 33
        if n_res - ne3 >= n_cand:
            break
        th3 += step
        if th3 > pt + 100.0:  # PSR is 0 long before; a guard, not a model step
            raise ValueError("Step 3 threshold search did not end; check density_veh_per_km and n_subchannels")
    return th3, ne3


def _pdr_and_shares(
    d: FloatArray,
    p_hd: FloatArray,
    p_sen: FloatArray,
    p_pro: FloatArray,
    p_col: FloatArray,
    p_col2: FloatArray,
    p_col3: FloatArray,
    scalars: dict[str, float],
) -> dict[str, FloatArray]:
    """:func:`analytical_pdr`'s result: the unconditional shares (eqs. 6.1-6.5) and the PDR (eq. 6) from the
    conditional probabilities, then ``scalars`` as 0-d arrays."""
    delta_hd = p_hd
    delta_sen = p_sen * (1.0 - p_hd)
    delta_pro = p_pro * (1.0 - p_hd) * (1.0 - p_sen)
    delta_col = p_col * (1.0 - p_hd) * (1.0 - p_sen) * (1.0 - p_pro)
    pdr = 1.0 - delta_hd - delta_sen - delta_pro - delta_col
    return {
        "distance_m": d,
        "pdr": pdr,
        "delta_hd": delta_hd,
        "delta_sen": delta_sen,
        "delta_pro": delta_pro,
        "delta_col": delta_col,
        "p_hd": p_hd,
        "p_sen": p_sen,
        "p_pro": p_pro,
        "p_col": p_col,
        "p_col_step2": p_col2,
        "p_col_step3": p_col3,
        **{k: np.asarray(float(v), dtype=np.float64) for k, v in scalars.items()},
    }
