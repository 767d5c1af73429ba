"""The two-distance reception model of eq. 15, and a logistic refinement.

Per NSV value ``k`` (pooled at ``nsv_cap``), a linear predictor in the log10 of the two
distances in metres (READING.md settles the base and unit):

    eta_k(d, l) = alpha_k log10 d + beta_k log10 l + gamma_k

* ``linear`` (the paper's eq. 15): ``P = clip(eta, p_min, 1)``.
* ``logistic`` (beyond the paper): ``P = clip(sigmoid(eta), p_min, 1)``. Same inputs, same
  number of parameters, but bounded by construction and fitted by maximum likelihood, so it does
  not need the clip to stay a probability and its gradient fades where P saturates.

``grad_d`` is eq. 16's ``dP/dd`` of the unclipped model, analytic:
``alpha / (d ln 10)`` (linear) and ``P (1 - P) alpha / (d ln 10)`` (logistic). GBMU's step is
``G = grad_d / P`` (eq. 16: ``G = alpha / (d P)`` up to the ``ln 10`` of the log base).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cv2x_marl.config import show_value
from cv2x_marl.io import InputFileError, read_text_limited, strict, write_json
from cv2x_marl.yamlcore import load_json

FloatArray = NDArray[np.float64]
SCHEMA_VERSION = 1
KINDS: tuple[str, ...] = ("linear", "logistic")
LN10 = math.log(10.0)


class ModelError(ValueError):
    """A model file is missing, corrupt, of another schema, or of an unknown kind."""


#: the largest magnitude of a coefficient (eq. 15 on log10 of metres: fitted values are of order 1; the
#: paper's Table 2 lies within +-1.8); larger ones would overflow the gradients GBMU steps along
MAX_ABS_COEFFICIENT = 1e6
#: the largest model file read, in bytes
MAX_MODEL_BYTES = 10 * 2**20


# The paper's Table 2 (NSV 0..6), log10 of metres.
PAPER_TABLE2: dict[str, list[float]] = {
    "alpha": [-0.83, -0.71, -0.61, -0.67, -0.72, -0.76, -0.74],
    "beta": [0.52, 0.19, 0.12, 0.09, 0.06, -0.02, 0.25],
    "gamma": [1.00, 1.42, 1.26, 1.44, 1.54, 1.73, 1.25],
}


@dataclass
class TwoDistanceModel:
    """Per-NSV coefficients of eq. 15 (``kind="linear"``) or its logistic version.

    Attributes:
        kind: ``linear`` or ``logistic``.
        alpha, beta, gamma: [nsv_cap + 1] coefficients; row k serves NSV = k (k = cap: NSV >= cap).
        p_min: lower clip of P (eq. 12's log needs P > 0).
        stats: per-NSV fit statistics (instances, R^2, ...), as written by the fit.
        provenance: where the fit's data came from.
    """

    kind: str
    alpha: FloatArray
    beta: FloatArray
    gamma: FloatArray
    p_min: float = 1e-3
    stats: list[dict[str, Any]] = field(default_factory=list)
    provenance: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ModelError(f"unknown model kind {show_value(self.kind)}; kinds: {', '.join(KINDS)}")
        self.alpha = np.asarray(self.alpha, dtype=np.float64)
        self.beta = np.asarray(self.beta, dtype=np.float64)
        self.gamma = np.asarray(self.gamma, dtype=np.float64)
        if not (self.alpha.shape == self.beta.shape == self.gamma.shape) or self.alpha.ndim != 1 or not self.alpha.size:
            raise ModelError("alpha, beta and gamma must be equal-length, non-empty 1-D arrays")
        for name in ("alpha", "beta", "gamma"):
            values = getattr(self, name)
            bad = np.flatnonzero(~(np.abs(values) <= MAX_ABS_COEFFICIENT))  # NaN fails the test too
            if bad.size:
                k = int(bad[0])
                raise ModelError(
                    f"{name} of NSV {k} is {values[k]:g}: model coefficients must be finite numbers within "
                    f"+-{MAX_ABS_COEFFICIENT:g}"
                )
        if not 0.0 < self.p_min < 1.0:
            raise ModelError(f"p_min must lie in (0, 1), got {self.p_min}")

    @property
    def nsv_cap(self) -> int:
        """Largest NSV with its own coefficients; larger NSV use this row."""
        return int(self.alpha.shape[0] - 1)

    @classmethod
    def paper_table2(cls, p_min: float = 1e-3) -> TwoDistanceModel:
        """The authors' own coefficients (Table 2), for running GBMU as published."""
        return cls(
            "linear",
            np.array(PAPER_TABLE2["alpha"]),
            np.array(PAPER_TABLE2["beta"]),
            np.array(PAPER_TABLE2["gamma"]),
            p_min=p_min,
            provenance={"source": "paper Table 2 (Men and Hou)"},
        )

    def _rows(self, nsv: ArrayLike) -> NDArray[np.int64]:
        k = np.asarray(nsv)
        if np.any(k < 0):
            raise ValueError("nsv must be >= 0")
        return np.minimum(k.astype(np.int64), self.nsv_cap)

    def eta(self, d_m: ArrayLike, l_m: ArrayLike, nsv: ArrayLike) -> FloatArray:
        """Linear predictor ``alpha log10 d + beta log10 l + gamma`` (broadcast shapes)."""
        k = self._rows(nsv)
        return self.alpha[k] * np.log10(d_m) + self.beta[k] * np.log10(l_m) + self.gamma[k]

    def predict_unclipped(self, d_m: ArrayLike, l_m: ArrayLike, nsv: ArrayLike) -> FloatArray:
        """P before the [p_min, 1] clip."""
        e = self.eta(d_m, l_m, nsv)
        return e if self.kind == "linear" else 1.0 / (1.0 + np.exp(-e))

    def predict(self, d_m: ArrayLike, l_m: ArrayLike, nsv: ArrayLike) -> FloatArray:
        """Success probability, clipped to ``[p_min, 1]``.

        Args:
            d_m: signal distance(s), metres (> 0).
            l_m: main-interference distance(s), metres (> 0; th_I when NSV = 0).
            nsv: number of surrounding co-channel vehicles (>= 0, pooled at the cap).
        """
        return np.clip(self.predict_unclipped(d_m, l_m, nsv), self.p_min, 1.0)

    def _grad(self, coef: FloatArray, x_m: ArrayLike, d_m: ArrayLike, l_m: ArrayLike, nsv: ArrayLike) -> FloatArray:
        """``dP/dx`` for ``x`` = d (``coef`` = alpha) or l (``coef`` = beta): ``coef / (x ln 10)`` times the
        link function's slope (1 for linear, ``P (1 - P)`` for logistic)."""
        base = coef[self._rows(nsv)] / (np.asarray(x_m, dtype=np.float64) * LN10)
        shape = np.broadcast_shapes(np.shape(base), np.shape(d_m), np.shape(l_m))
        if self.kind == "linear":
            return np.broadcast_to(base, shape).astype(np.float64)
        p = self.predict_unclipped(d_m, l_m, nsv)
        return p * (1.0 - p) * base

    def grad_d(self, d_m: ArrayLike, l_m: ArrayLike, nsv: ArrayLike) -> FloatArray:
        """``dP/dd`` of the unclipped model (eq. 16), per metre."""
        return self._grad(self.alpha, d_m, d_m, l_m, nsv)

    def grad_l(self, d_m: ArrayLike, l_m: ArrayLike, nsv: ArrayLike) -> FloatArray:
        """``dP/dl`` of the unclipped model, per metre."""
        return self._grad(self.beta, l_m, d_m, l_m, nsv)

    # ----------------------------------------------------------------- JSON
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready representation (schema ``SCHEMA_VERSION``)."""
        per_nsv = []
        for k in range(self.nsv_cap + 1):
            row: dict[str, Any] = {
                "nsv": k,
                "alpha": float(self.alpha[k]),
                "beta": float(self.beta[k]),
                "gamma": float(self.gamma[k]),
            }
            if k < len(self.stats):
                row.update({key: v for key, v in self.stats[k].items() if key != "nsv"})
            per_nsv.append(row)
        return {
            "schema_version": SCHEMA_VERSION,
            "kind": self.kind,
            "log_base": 10,
            "distance_unit": "m",
            "p_min": self.p_min,
            "nsv_cap": self.nsv_cap,
            "per_nsv": per_nsv,
            "provenance": self.provenance,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "model") -> TwoDistanceModel:
        """Inverse of :meth:`to_dict`; raises :class:`ModelError` naming ``source`` on bad input."""
        if not isinstance(data, dict):
            raise ModelError(f"{source}: expected a JSON object")
        version = data.get("schema_version")
        if version != SCHEMA_VERSION:
            raise ModelError(
                f"{source}: schema_version {show_value(version)} is not supported (expected {SCHEMA_VERSION})"
            )
        try:
            rows = sorted(data["per_nsv"], key=lambda r: int(r["nsv"]))
            if [int(r["nsv"]) for r in rows] != list(range(len(rows))):
                raise ModelError("per_nsv must list NSV 0, 1, ... without gaps")
            coef = {c: np.array([_number(r[c], f"per_nsv[{i}].{c}") for i, r in enumerate(rows)]) for c in _COEFS}
            stats = [{k: v for k, v in r.items() if k not in _COEFS} for r in rows]
            return cls(
                str(data["kind"]),
                coef["alpha"],
                coef["beta"],
                coef["gamma"],
                p_min=_number(data.get("p_min", 1e-3), "p_min"),
                stats=stats,
                provenance=dict(data.get("provenance", {})),
            )
        except ModelError as exc:
            raise ModelError(f"{source}: {exc}") from exc
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise ModelError(f"{source}: malformed model ({type(exc).__name__}: {exc})") from exc

    def save(self, path: str | Path) -> Path:
        """Write the model as JSON (atomically), with the SHA-256 of its content (checked by :meth:`load`)."""
        payload = strict(self.to_dict())
        return write_json(path, {**payload, "sha256": _digest(payload)})

    @classmethod
    def load(cls, path: str | Path) -> TwoDistanceModel:
        """Read a model file written by :meth:`save` (or ``cv2x-marl fit``)."""
        path = Path(path)
        try:
            data = load_json(read_text_limited(path, MAX_MODEL_BYTES, "model file"))
        except FileNotFoundError as exc:
            raise ModelError(f"model file {path} does not exist") from exc
        except InputFileError as exc:
            raise ModelError(str(exc)) from exc
        except ValueError as exc:  # json.JSONDecodeError, too deep a document
            raise ModelError(f"model file {path} is not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise ModelError(f"model file {path}: expected a JSON object, got a JSON {type(data).__name__}")
        where = _non_finite(data)
        if where is not None:  # json reads NaN, Infinity and 1e999; no model written by save holds one
            raise ModelError(f"model file {path}: {where} is not a finite number (NaN or infinite)")
        if not isinstance(data.get("sha256"), str):
            raise ModelError(
                f"model file {path} has no sha256 key (the SHA-256 of its content that `cv2x-marl fit` writes): "
                "the file was edited or is not a model written by this package; refit it"
            )
        payload = {k: v for k, v in data.items() if k != "sha256"}
        if _digest(payload) != data["sha256"]:
            raise ModelError(
                f"model file {path} does not match its SHA-256: the file was edited or corrupted; refit it"
            )
        return cls.from_dict(payload, source=f"model file {path}")


#: the model file of a fit folder (``cv2x-marl fit --out DIR`` writes ``DIR/model.json``)
MODEL_FILE = "model.json"
#: the paper's Table 2 coefficients, as a model name (:meth:`TwoDistanceModel.paper_table2`)
PAPER_MODEL = "paper-table2"
#: two-distance models shipped as package data (``cv2x_marl/regression/data/NAME.json``)
SHIPPED_MODELS = ("linear-fit", "logistic-fit")


def resolve_model(model: str) -> str:
    """A model name as :func:`load_model` reads it: a shipped model's name (:data:`SHIPPED_MODELS`)
    becomes its package-data path; anything else is returned as is."""
    if model not in SHIPPED_MODELS:
        return model
    return str(resources.files("cv2x_marl.regression") / "data" / f"{model}.json")


def load_model(path: Path | str) -> TwoDistanceModel:
    """Load a model: ``paper-table2`` (the preset), a fit folder (its ``model.json``) or a model file."""
    if str(path) == PAPER_MODEL:
        return TwoDistanceModel.paper_table2()
    path = Path(path)
    if path.is_dir():
        path = path / MODEL_FILE
    return TwoDistanceModel.load(path)


def load_shipped_model(name: str) -> TwoDistanceModel:
    """The shipped :class:`TwoDistanceModel` ``name`` (:data:`SHIPPED_MODELS`)."""
    if name not in SHIPPED_MODELS:
        raise ValueError(f"unknown shipped model {name!r}; shipped models: {', '.join(SHIPPED_MODELS)}")
    return TwoDistanceModel.load(resolve_model(name))


_COEFS = ("alpha", "beta", "gamma")


def _number(value: Any, key: str) -> float:
    """``value`` as a float; a ModelError naming ``key`` for anything but a JSON number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ModelError(f"{key}: expected a number, got {type(value).__name__}")
    try:
        return float(value)
    except OverflowError:
        raise ModelError(f"{key}: an integer beyond the range of a float") from None


def _non_finite(data: Any, where: str = "") -> str | None:
    """The key path (``per_nsv[2].alpha``) of the first NaN or infinite number in ``data``, else None."""
    stack: list[tuple[Any, str]] = [(data, where)]
    while stack:
        value, at = stack.pop()
        if isinstance(value, float) and not math.isfinite(value):
            return at or "the value"
        if isinstance(value, dict):
            stack.extend((v, f"{at}.{k}" if at else str(k)) for k, v in reversed(value.items()))
        elif isinstance(value, list):
            stack.extend((v, f"{at}[{i}]") for i, v in reversed(list(enumerate(value))))
    return None


def _digest(payload: Any) -> str:
    """SHA-256 of the canonical JSON of a model's content (sorted keys, no spaces)."""
    import hashlib

    text = json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()
