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
