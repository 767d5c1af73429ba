"""Figures (matplotlib, headless Agg backend). Kept out of ``cv2x_marl.sim``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from cv2x_marl.io import atomic_write

CAUSE_LABELS = {
    "half_duplex": "half duplex",
    "sensitivity": "below sensitivity",
    "propagation": "propagation",
    "collision": "collision",
}


def plot_prr_vs_distance(summary: dict[str, Any], path: str | Path, title: str = "") -> Path:
    """PRR vs distance (sampled and expected) over the stacked shares of each loss cause."""
    rows = summary["prr_vs_distance"]
    loss = summary["loss_causes"]
    d = [r["distance_m"] for r in rows]
    fig, ax = plt.subplots(figsize=(7.5, 4.5), constrained_layout=True)
    bottom = [r["prr"] for r in rows]
    width = (d[1] - d[0]) if len(d) > 1 else 10.0
    colors = {"half_duplex": "#b07aa1", "sensitivity": "#9c755f", "propagation": "#f28e2b", "collision": "#e15759"}
    for cause, label in CAUSE_LABELS.items():
        share = [r[cause] for r in loss]
        if max(share, default=0.0) <= 0.0:
            continue
        ax.bar(d, share, width=width, bottom=bottom, color=colors[cause], alpha=0.45, label=f"lost: {label}")
        bottom = [b + s for b, s in zip(bottom, share, strict=True)]
    ax.plot(d, [r["prr"] for r in rows], "k-", lw=2, label="PRR (decoded)")
    ax.plot(d, [r["prr_expected"] for r in rows], "b--", lw=1.2, label="PRR (expected)")
    ax.set_xlabel("Tx-Rx distance (m)")
    ax.set_ylabel("packet reception ratio / share of packets")
    ax.set_ylim(0, 1.02)
    ax.set_xlim(0, max(d, default=1.0) + width)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(title or f"PRR vs distance (mean per-node PRR {summary['prr_mean']:.3f})")

    def save(tmp: Path) -> None:
        fig.savefig(tmp, format="png", dpi=120)

    try:
        return atomic_write(path, save)
    finally:
        plt.close(fig)


def _save(fig: Any, path: str | Path) -> Path:
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))
    finally:
        plt.close(fig)


def plot_surface(model: Any, path: str | Path, nsv_values: tuple[int, ...] = (1, 3, 5)) -> Path:
    """The paper's Fig. 2: P(d, l) surfaces of the two-distance model for a few NSV values."""
    import numpy as np

    d = np.linspace(10.0, 400.0, 60)
    lgrid = np.linspace(10.0, 200.0, 60)
    dd, ll = np.meshgrid(d, lgrid)
    fig = plt.figure(figsize=(4.2 * len(nsv_values), 4.0), constrained_layout=True)
    for i, k in enumerate(nsv_values):
        ax = fig.add_subplot(1, len(nsv_values), i + 1, projection="3d")
        p = model.predict(dd, ll, np.full(dd.shape, k))
        ax.plot_surface(dd, ll, p, cmap="viridis", vmin=0, vmax=1, linewidth=0, antialiased=True)
        ax.set_xlabel("signal distance d (m)")
        ax.set_ylabel("interferer distance l (m)")
        ax.set_zlabel("P")
        ax.set_zlim(0, 1)
        cap = "+" if k >= model.nsv_cap else ""
        ax.set_title(f"NSV = {min(k, model.nsv_cap)}{cap} ({model.kind})")
        ax.view_init(elev=25, azim=-125)
    return _save(fig, path)


def plot_fit_quality(model: Any, path: str | Path) -> Path:
    """R^2 (train and held out) and instances per NSV (the paper's Table 3 as a figure)."""
    import numpy as np

    ks = np.array([s["nsv"] for s in model.stats])
    r2 = np.array([np.nan if s["r2"] is None else s["r2"] for s in model.stats], dtype=float)
    r2t = np.array([np.nan if s["r2_test"] is None else s["r2_test"] for s in model.stats], dtype=float)
    inst = np.array([s["instances"] for s in model.stats])
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    ax.bar(ks - 0.2, r2, width=0.4, label="R^2 train", color="#4e79a7")
    ax.bar(ks + 0.2, r2t, width=0.4, label="R^2 held out", color="#f28e2b")
    ax.set_xlabel("NSV (last bar: cap and above)")
    ax.set_ylabel("R^2")
    ax.set_ylim(min(0.0, float(np.nanmin(np.r_[r2, r2t, 0.0]))), 1.0)
    ax.set_xticks(ks)
    ax2 = ax.twinx()
    ax2.plot(ks, inst, "k.-", label="instances")
    ax2.set_ylabel("instances")
    ax2.set_yscale("log")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    ax.set_title(f"Two-distance model fit per NSV ({model.kind})")
    return _save(fig, path)
