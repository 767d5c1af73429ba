"""Unit conversions. Names carry units: ``_db``, ``_dbm``, ``_mw``, ``_m``, ``_hz``, ``_mps``."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

SPEED_OF_LIGHT_MPS = 299_792_458.0
BOLTZMANN_DBM_PER_HZ = -173.975  # 10 log10(k T0 / 1 mW) at T0 = 290 K


def db_to_linear(x_db: ArrayLike) -> NDArray[np.float64]:
    """10^(x/10)."""
    return np.power(10.0, np.asarray(x_db, dtype=np.float64) / 10.0)


def linear_to_db(x: ArrayLike) -> NDArray[np.float64]:
    """10 log10(x); zero maps to -inf."""
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(np.asarray(x, dtype=np.float64))


dbm_to_mw = db_to_linear
mw_to_dbm = linear_to_db


def thermal_noise_dbm(bandwidth_hz: float) -> float:
    """kT0B in dBm (T0 = 290 K). Ten LTE resource blocks (1.8 MHz) give -111.42 dBm."""
    return float(BOLTZMANN_DBM_PER_HZ + 10.0 * np.log10(bandwidth_hz))


def noise_power_dbm(noise_dbm: float, noise_figure_db: float) -> float:
    """Receiver noise power: noise over the band plus the noise figure (dB add).

    Paper Table 1: -112.45 dBm + 9 dB = -103.45 dBm per subchannel.
    """
    return float(noise_dbm + noise_figure_db)
