"""Stage 2: the two-distance reception model (eq. 15-16), its fit, and its I/O."""

from cv2x_marl.regression.fit import MAX_NSV_CAP, FitData, FitError, fit_two_distance
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
