"""Fitting the two-distance model per NSV (Sec. 6.2, Tables 2-3) with a held-out split.

Inputs are arrays over samples: signal distance ``d_m``, main-interference distance ``l_m``,
``nsv``, the target (by default the link's expected success probability), and a group label for
the split (the run, so the test set holds whole independent runs and no link is on both sides).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from sklearn.linear_model import LinearRegression, LogisticRegression

from cv2x_marl.regression.model import KINDS, ModelError, TwoDistanceModel

FloatArray = NDArray[np.float64]


class FitError(ValueError):
    """The data cannot support the requested fit."""


#: the largest ``nsv_cap``: NSV values from 0 to the cap each get their own coefficients (the paper: 6);
#: aggregated datasets count NSV up to 255, and a cap above that only repeats fallback rows
MAX_NSV_CAP = 255


@dataclass(frozen=True)
class FitData:
    """Samples for the fit (arrays of one length S).

    Attributes:
        d_m: signal distance, metres.
        l_m: main-interference distance, metres (th_I when NSV = 0).
        nsv: co-channel vehicles within th_I of the receiver.
        target: what P should predict, in [0, 1].
        group: split label (run id, or link id when there is one run).
    """

    d_m: FloatArray
    l_m: FloatArray
    nsv: NDArray[np.int64]
    target: FloatArray
    group: NDArray[np.int64]

    def __post_init__(self) -> None:
        n = self.d_m.shape[0]
        for name in ("l_m", "nsv", "target", "group"):
            if getattr(self, name).shape != (n,):
                raise FitError(f"{name} has shape {getattr(self, name).shape}, expected ({n},)")
        if n and not (np.all(self.d_m > 0) and np.all(self.l_m > 0)):  # NaN fails the test too
            raise FitError("distances must be > 0 m (log10 of metres), not NaN")
        if n and not (np.all(np.isfinite(self.d_m)) and np.all(np.isfinite(self.l_m))):
            raise FitError("distances must be finite")
        if n and (np.any(self.target < 0) or np.any(self.target > 1) or np.any(~np.isfinite(self.target))):
            raise FitError("targets must lie in [0, 1]")


def holdout_mask(group: NDArray[np.int64], test_fraction: float, seed: int) -> NDArray[np.bool_]:
    """Hold out whole groups, about ``test_fraction`` of them (at least one when there are two or more)."""
    groups = np.unique(group)
    if groups.size < 2 or test_fraction <= 0:
        return np.zeros(group.shape[0], dtype=bool)
    n_test = min(groups.size - 1, max(1, round(test_fraction * groups.size)))
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5E1]))
    held = rng.choice(groups, size=n_test, replace=False)
    return np.isin(group, held)


def r2_score(y: FloatArray, p: FloatArray) -> float:
    """Coefficient of determination; NaN for fewer than two samples or a constant target."""
    if y.size < 2:
        return float("nan")
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    if ss_tot == 0.0:
        return float("nan")
    return 1.0 - float(np.sum((y - p) ** 2)) / ss_tot


def brier(y: FloatArray, p: FloatArray) -> float:
    """Mean squared error of probabilities (targets may be fractional)."""
    return float(np.mean((p - y) ** 2)) if y.size else float("nan")


def log_loss(y: FloatArray, p: FloatArray, eps: float = 1e-6) -> float:
    """Cross-entropy with soft targets, probabilities clipped to ``[eps, 1 - eps]``."""
    if not y.size:
        return float("nan")
    q = np.clip(p, eps, 1.0 - eps)
    return float(-np.mean(y * np.log(q) + (1.0 - y) * np.log1p(-q)))


def _features(d_m: FloatArray, l_m: FloatArray) -> FloatArray:
    return np.column_stack([np.log10(d_m), np.log10(l_m)])


def _fit_one(kind: str, x: FloatArray, y: FloatArray) -> tuple[float, float, float]:
    """(alpha, beta, gamma) for one NSV. Constant columns (l = th_I at NSV 0) get coefficient 0."""
    varying = np.ptp(x, axis=0) > 1e-9
    coef = np.zeros(2)
    if kind == "linear":
        reg = LinearRegression().fit(x[:, varying], y) if varying.any() else None
        intercept = float(reg.intercept_) if reg is not None else float(y.mean())
        if reg is not None:
            coef[varying] = reg.coef_
    else:
        # soft labels: maximum likelihood with each row as a weighted positive and negative
        xv = x[:, varying]
        xx = np.vstack([xv, xv])
        yy = np.r_[np.ones(y.size), np.zeros(y.size)]
        ww = np.r_[y, 1.0 - y]
        if varying.any():
            clf = LogisticRegression(C=np.inf, max_iter=1000, tol=1e-10).fit(xx, yy, sample_weight=ww)
            coef[varying] = clf.coef_[0]
            intercept = float(clf.intercept_[0])
        else:
            m = float(np.clip(y.mean(), 1e-9, 1 - 1e-9))
            intercept = math.log(m / (1 - m))
    return float(coef[0]), float(coef[1]), intercept


def fit_two_distance(
    data: FitData,
    kind: str = "linear",
    nsv_cap: int = 6,
    test_fraction: float = 0.2,
    seed: int = 0,
    min_samples: int = 30,
    p_min: float = 1e-3,
) -> TwoDistanceModel:
    """Fit eq. 15 (or its logistic version) for NSV = 0..nsv_cap, NSV above the cap pooled into it.

    An NSV with fewer than ``min_samples`` training samples borrows the coefficients of the
    nearest NSV that has enough (lower first); its stats say ``fallback_from``.

    Returns:
        The model, with per-NSV ``instances``, ``n_train``, ``n_test``, ``r2`` (train),
        ``r2_test``, ``brier_test``, ``log_loss_test`` and ``fallback_from`` in ``stats``.
    """
    if kind not in KINDS:
        raise ModelError(f"unknown model kind {kind!r}; kinds: {', '.join(KINDS)}")
    if not 0 <= nsv_cap <= MAX_NSV_CAP:
        raise FitError(f"nsv_cap must be an integer in [0, {MAX_NSV_CAP}], got {nsv_cap}")
    k_all = np.minimum(data.nsv, nsv_cap)
    test = holdout_mask(data.group, test_fraction, seed)
    x_all = _features(data.d_m, data.l_m)
    coefs: list[tuple[float, float, float] | None] = []
    for k in range(nsv_cap + 1):
        tr = (k_all == k) & ~test
        coefs.append(_fit_one(kind, x_all[tr], data.target[tr]) if tr.sum() >= min_samples else None)
    fitted = [k for k, c in enumerate(coefs) if c is not None]
    if not fitted:
        raise FitError(f"no NSV value has {min_samples} training samples (of {int((~test).sum())} in all)")
    fallback: dict[int, int] = {}
    for k, c in enumerate(coefs):
        if c is None:
            src = min(fitted, key=lambda j: (abs(j - k), j > k))
            fallback[k] = src
            coefs[k] = coefs[src]
    alpha, beta, gamma = (np.array([c[i] for c in coefs if c is not None]) for i in range(3))
    model = TwoDistanceModel(kind, alpha, beta, gamma, p_min=p_min)
    pred = model.predict(data.d_m, data.l_m, k_all)
    stats: list[dict[str, Any]] = []
    for k in range(nsv_cap + 1):
        rows = k_all == k
        tr, te = rows & ~test, rows & test
        stats.append(
            {
                "nsv": k,
                "instances": int(rows.sum()),
                "n_train": int(tr.sum()),
                "n_test": int(te.sum()),
                "r2": r2_score(data.target[tr], pred[tr]),
                "r2_test": r2_score(data.target[te], pred[te]),
                "brier_test": brier(data.target[te], pred[te]),
                "log_loss_test": log_loss(data.target[te], pred[te]),
                "fallback_from": fallback.get(k),
            }
        )
    model.stats = stats
    model.provenance = {
        "n_samples": int(data.d_m.shape[0]),
        "n_train": int((~test).sum()),
        "n_test": int(test.sum()),
        "test_fraction": test_fraction,
        "split": "whole groups (runs) held out",
        "seed": seed,
        "min_samples": min_samples,
        "overall_test": {
            "r2": r2_score(data.target[test], pred[test]),
            "brier": brier(data.target[test], pred[test]),
            "log_loss": log_loss(data.target[test], pred[test]),
        },
    }
    return model
