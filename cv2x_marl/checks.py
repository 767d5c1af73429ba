"""Type checks shared by every validated input (env arguments, training configs, baseline files)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def is_int(value: Any) -> bool:
    """An integer (numpy ones too), not a bool."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def as_real(value: Any) -> float | None:
    """``value`` as a float if it is a finite real number (numpy ones too) or a string that reads as
    one (YAML 1.1 reads ``3e-4`` as a string), else None; bools are not numbers."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int | float | np.integer | np.floating):
        x = float(value)
    elif isinstance(value, str):
        try:
            x = float(value)
        except ValueError:
            return None
    else:
        return None
    return x if math.isfinite(x) else None


def is_real(value: Any) -> bool:
    """A finite real number (numpy ones too), not a bool and not a string."""
    return not isinstance(value, str) and as_real(value) is not None
