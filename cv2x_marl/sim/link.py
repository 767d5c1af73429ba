"""Link abstraction: SINR (eq. 8) -> probability of decoding.

Three models, all vectorised over links:

* ``per_table``: ``P = 1 - PER(SINR)`` with PER linearly interpolated in dB from a link-level
  curve shipped as package data (``cv2x_marl/sim/data/*.csv``, source in the file header);
  PER = 1 below the first table point and the last PER above the last one.
* ``rayleigh``: the closed form of ``Pr[SINR >= theta]`` when the signal and every interferer
  undergo independent Rayleigh fading around their mean powers ``S`` and ``I_c``:
  ``P = exp(-theta N / S) prod_c 1 / (1 + theta I_c / S)``.
* ``threshold``: ``P = 1[SINR >= theta]``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

PER_CURVES: tuple[str, ...] = ("r1-160284-190b-r0.5", "r1-160284-190b-r0.7")


@dataclass(frozen=True)
class PerCurve:
    """A PER(SINR) table: ``sinr_db`` ascending [K], ``per`` [K], and where it comes from."""

    name: str
    sinr_db: FloatArray
    per: FloatArray
    source: str

    def success(self, sinr_db: ArrayLike) -> FloatArray:
        """``1 - PER`` interpolated at ``sinr_db`` (any shape)."""
        per = np.interp(np.asarray(sinr_db, dtype=np.float64), self.sinr_db, self.per, left=1.0, right=self.per[-1])
        return 1.0 - per


@functools.cache
def load_per_curve(name: str) -> PerCurve:
    """Read a shipped PER curve by name (see :data:`PER_CURVES`)."""
    if name not in PER_CURVES:
        raise ValueError(f"unknown PER curve {name!r}; available: {', '.join(PER_CURVES)}")
    text = resources.files("cv2x_marl.sim").joinpath("data", f"{name}.csv").read_text()
    comments = [ln[1:].strip() for ln in text.splitlines() if ln.startswith("#")]
    rows = [ln for ln in text.splitlines() if ln and not ln.startswith("#")][1:]
    table = np.array([[float(v) for v in ln.split(",")] for ln in rows])
    source = next((c.split(":", 1)[1].strip() for c in comments if c.startswith("source:")), "")
    if np.any(np.diff(table[:, 0]) <= 0):
        raise ValueError(f"PER curve {name}: SINR points must increase")
    return PerCurve(name, table[:, 0].copy(), table[:, 1].copy(), source)


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
