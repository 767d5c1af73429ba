"""Strict JSON: NaN and infinities are written as null, numpy values as plain numbers."""

import json
import math
from pathlib import Path

import numpy as np

from cv2x_marl.io import dumps_json, strict, write_json


def _reject(token: str) -> None:
    raise ValueError(f"non-standard JSON token {token}")


def test_nan_and_infinities_become_null(tmp_path: Path) -> None:
    data = {"a": float("nan"), "b": [1.0, float("inf"), -math.inf], "c": np.float32("nan"), "d": np.arange(2)}
    path = write_json(tmp_path / "x.json", data)
    loaded = json.loads(path.read_text(), parse_constant=_reject)  # a strict parser accepts it
    assert loaded == {"a": None, "b": [1.0, None, None], "c": None, "d": [0, 1]}
    assert json.loads(dumps_json({"k": np.float64(2.5)}), parse_constant=_reject) == {"k": 2.5}
    assert strict({"s": "nan", "n": 3}) == {"s": "nan", "n": 3}  # strings are left alone
