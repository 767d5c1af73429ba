"""Stage 2: the two-distance reception model (eq. 15-16), its fit, and its I/O.

The fit's names (:mod:`cv2x_marl.regression.fit`) are imported on first use: the fit needs scikit-learn
(about 0.7 s to import), which loading a model (the env's observation versions 1 and 2) does not.
"""

from typing import Any

from cv2x_marl.regression.model import (
    KINDS,
    PAPER_TABLE2,
    SHIPPED_MODELS,
    ModelError,
    TwoDistanceModel,
    load_model,
    load_shipped_model,
    resolve_model,
)

_FIT_NAMES = ("MAX_NSV_CAP", "FitData", "FitError", "fit_two_distance")


def __getattr__(name: str) -> Any:
    if name in _FIT_NAMES:
        from cv2x_marl.regression import fit  # scikit-learn: imported when a fit is asked for

        return getattr(fit, name)
    raise AttributeError(f"module 'cv2x_marl.regression' has no attribute {name!r}")


__all__ = [
    "KINDS",
    "MAX_NSV_CAP",
    "PAPER_TABLE2",
    "SHIPPED_MODELS",
    "FitData",
    "FitError",
    "ModelError",
    "TwoDistanceModel",
    "fit_two_distance",
    "load_model",
    "load_shipped_model",
    "resolve_model",
]
