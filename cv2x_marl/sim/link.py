"""Link abstraction: SINR (eq. 8) -> probability of decoding.

Three models, all vectorised over links:

* ``per_table``: ``P = 1 - PER(SINR)`` with PER interpolated from a link-level curve shipped as
  package data (``cv2x_marl/sim/data/*.csv``, source in the file header); PER = 1 below the first
  table point and the last PER above the last one. Between points (``link.per_interpolation``):
  ``linear``, PER linear in SINR (dB) (the paper presets', as ``interp1(..., 'linear')``
  in the reference code the points come from); ``log`` (the default), ``log PER`` linear in SINR (dB), i.e. PER
  geometric between points, which follows a waterfall curve (PER falls about exponentially with
  SINR in dB) instead of over-estimating it between points: at 7 dB on the r = 0.5 curve (6 dB:
  0.09, 8 dB: 0.02) linear gives 0.055 and log ``sqrt(0.09 * 0.02) = 0.0424``.
* ``rayleigh``: the closed form of ``Pr[SINR >= theta]`` when the signal and every interferer
  undergo independent Rayleigh fading around their mean powers ``S`` and ``I_c``:
  ``P = exp(-theta N / S) prod_c 1 / (1 + theta I_c / S)``.
* ``threshold``: ``P = 1[SINR >= theta]``.

The SCI (PSCCH) has its own curve (:class:`PscchCurve`, ``sps.sci_decoding=sinr``): the probability
that a receiver decodes the SCI, and hence learns the reservation the sensing of TS 36.213 14.1.1.6
uses, from the PSCCH SINR.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cv2x_marl.config import PER_CURVES, PER_INTERPOLATIONS
from cv2x_marl.sim import kernels

FloatArray = NDArray[np.float64]

#: the shipped PSCCH (SCI) BLER curve (``cv2x_marl/sim/data/<name>.csv``, source in its header)
PSCCH_CURVE = "nist-pscch-awgn-siso"


@dataclass(frozen=True)
class PerCurve:
    """A PER(SINR) table: ``sinr_db`` ascending [K], ``per`` [K], where it comes from, and how it
    is interpolated between its points (:data:`cv2x_marl.config.PER_INTERPOLATIONS`)."""

    name: str
    sinr_db: FloatArray
    per: FloatArray
    source: str
    interpolation: str

    def success(self, sinr_db: ArrayLike) -> FloatArray:
        """``1 - PER`` at ``sinr_db`` (any shape): PER 1 below the table, the last PER above it.

        ``linear``: PER linear in SINR (dB) between points (``np.interp``); ``log``: ``ln PER``
        linear in SINR (dB), ``PER = PER_j^(1 - t) PER_{j+1}^t`` with ``t`` the position between
        points ``j`` and ``j + 1``. Both agree at the table points.
        """
        x = np.asarray(sinr_db, dtype=np.float64)
        if self.interpolation == "log":
            per = np.exp(np.interp(x, self.sinr_db, np.log(self.per), left=0.0, right=float(np.log(self.per[-1]))))
        else:
            per = np.interp(x, self.sinr_db, self.per, left=1.0, right=self.per[-1])
        return 1.0 - per

    @property
    def kernel_model(self) -> int:
        """The ``model`` code of the compiled kernels for this curve's interpolation
        (:data:`cv2x_marl.sim.kernels.MODEL_PER_TABLE` or ``MODEL_PER_TABLE_LOG``)."""
        return kernels.MODEL_PER_TABLE_LOG if self.interpolation == "log" else kernels.MODEL_PER_TABLE


def _read_curve(name: str, what: str) -> tuple[FloatArray, str]:
    """A curve of package data (``cv2x_marl/sim/data/<name>.csv``: ``#`` comment lines, one of them
    ``# source: ...``, a header row, then ``sinr_db, value`` rows): the [K, 2] table, SINR strictly
    increasing, and its source line."""
    text = resources.files("cv2x_marl.sim").joinpath("data", f"{name}.csv").read_text()
    comments = [ln[1:].strip() for ln in text.splitlines() if ln.startswith("#")]
    rows = [ln for ln in text.splitlines() if ln and not ln.startswith("#")][1:]
    table = np.array([[float(v) for v in ln.split(",")] for ln in rows])
    source = next((c.split(":", 1)[1].strip() for c in comments if c.startswith("source:")), "")
    if np.any(np.diff(table[:, 0]) <= 0):
        raise ValueError(f"{what} curve {name}: SINR points must increase")
    return table, source


@functools.cache
def load_per_curve(name: str, interpolation: str) -> PerCurve:
    """Read a shipped PER curve by name (see :data:`cv2x_marl.config.PER_CURVES`).

    Args:
        name: the curve (file ``cv2x_marl/sim/data/<name>.csv``).
        interpolation: between table points, ``linear`` (PER) or ``log`` (``ln PER``); see
            :data:`cv2x_marl.config.PER_INTERPOLATIONS` and the module docstring. No default: the
            configuration's (``link.per_interpolation``, ``log``) is not the paper presets' (``linear``),
            so every caller says which.
    """
    if name not in PER_CURVES:
        raise ValueError(f"unknown PER curve {name!r}; available: {', '.join(PER_CURVES)}")
    if interpolation not in PER_INTERPOLATIONS:
        raise ValueError(f"unknown PER interpolation {interpolation!r}; available: {', '.join(PER_INTERPOLATIONS)}")
    table, source = _read_curve(name, "PER")
    if np.any(table[:, 1] <= 0.0) or np.any(table[:, 1] > 1.0):
        raise ValueError(f"PER curve {name}: PER values must lie in (0, 1] (log interpolation needs PER > 0)")
    return PerCurve(name, table[:, 0].copy(), table[:, 1].copy(), source, interpolation)


@dataclass(frozen=True)
class PscchCurve:
    """The PSCCH (SCI) BLER as a function of SINR: ``sinr_db`` ascending [K], ``bler`` [K] in [0, 1].

    Interpolated as its source does (NIST's ns-3 sidelink error model, ``GetBlerValue``): BLER linear
    in the *linear* SINR between points, 1 below the first point and the last value (0 for the
    shipped curve) above the last one.
    """

    name: str
    sinr_db: FloatArray
    bler: FloatArray
    source: str

    def decoding_probability(self, sinr_db: ArrayLike) -> FloatArray:
        """``1 - BLER`` at ``sinr_db`` (any shape, dB): the probability that the SCI is decoded.

        Args:
            sinr_db: the PSCCH SINR, dB (``-inf`` and NaN decode with probability 0).

        Returns:
            Probabilities in [0, 1], the shape of ``sinr_db``.
        """
        x = np.asarray(sinr_db, dtype=np.float64)
        with np.errstate(over="ignore"):
            lin = np.power(10.0, x / 10.0)
        bler = np.interp(lin, np.power(10.0, self.sinr_db / 10.0), self.bler, left=1.0, right=float(self.bler[-1]))
        return np.where(np.isnan(x), 0.0, 1.0 - bler)


@functools.cache
def load_pscch_curve(name: str = PSCCH_CURVE) -> PscchCurve:
    """Read the shipped PSCCH BLER curve (file ``cv2x_marl/sim/data/<name>.csv``, columns
    ``sinr_db, bler``; its ``# source:`` header line names where the values come from)."""
    if name != PSCCH_CURVE:
        raise ValueError(f"unknown PSCCH curve {name!r}; available: {PSCCH_CURVE}")
    table, source = _read_curve(name, "PSCCH")
    if np.any(table[:, 1] < 0.0) or np.any(table[:, 1] > 1.0) or np.any(np.diff(table[:, 1]) > 0):
        raise ValueError(f"PSCCH curve {name}: BLER values must lie in [0, 1] and not increase with SINR")
    return PscchCurve(name, table[:, 0].copy(), table[:, 1].copy(), source)


def rayleigh_success(
    signal_mw: FloatArray,
    noise_mw: float,
    interferer_mw: FloatArray,
    link_of_interferer: NDArray[np.int64],
    theta_db: float,
) -> FloatArray:
    """Closed-form success probability under Rayleigh fading of signal and interferers.

    ``P_l = exp(-theta N / S_l) * prod_{c in I(l)} 1 / (1 + theta I_c / S_l)``.

    Args:
        signal_mw: [L] mean received signal power of each link, mW.
        noise_mw: noise power (noise figure included), mW.
        interferer_mw: [K] mean received power of each (link, interferer) term, mW.
        link_of_interferer: [K] index in ``[0, L)`` of the link each term belongs to.
        theta_db: decoding threshold.

    Returns:
        [L] success probabilities.
    """
    theta = 10.0 ** (theta_db / 10.0)
    log_p = -theta * noise_mw / signal_mw
    if interferer_mw.size:
        terms = np.log1p(theta * interferer_mw / signal_mw[link_of_interferer])
        log_p = log_p - np.bincount(link_of_interferer, weights=terms, minlength=signal_mw.shape[0])
    return np.exp(log_p)


def threshold_success(sinr_db: ArrayLike, theta_db: float) -> FloatArray:
    """``1[SINR >= theta]`` as floats."""
    return (np.asarray(sinr_db, dtype=np.float64) >= theta_db).astype(np.float64)
