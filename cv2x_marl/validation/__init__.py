"""Independent checkers of the simulator against published references.

* :mod:`cv2x_marl.validation.mode4_analytical`: the closed-form analytical model of C-V2X Mode 4 of
  Gonzalez-Martin et al., IEEE TVT 68(2), 2019 (numpy/scipy only; imports nothing from
  :mod:`cv2x_marl.sim`, so it checks the simulator rather than restating it).
* :mod:`cv2x_marl.validation.compare`: runs the simulator on the analytical model's highway and
  writes PDR(d) and loss causes of both (``cv2x-marl validate --out DIR``).
"""

from cv2x_marl.validation.mode4_analytical import (
    BLER_190B_R05,
    BLER_190B_R07,
    BlerCurve,
    alpha_weight,
    analytical_pdr,
    excluded_resources,
    noise_power_dbm,
    path_loss_db,
)

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
