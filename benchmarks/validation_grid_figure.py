"""The figure of docs/validation.md (issue 29): the study grid's mean |PDR difference| to the model per
configuration, from docs/validation/grid_{simplified,standard}.csv (`cv2x-marl validate --study`).

    .venv/bin/python benchmarks/validation_grid_figure.py
"""

import csv

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

rows = {v: list(csv.DictReader(open(f"docs/validation/grid_{v}.csv"))) for v in ("simplified", "standard")}
lab = [
    f"S={int(r['n_subchannels'])}\n{float(r['packets_per_s']):g} Hz {float(r['tx_power_dbm']):g} dBm\n"
    f"{float(r['density_veh_per_m']):g} veh/m"
    for r in rows["simplified"]
]
x = np.arange(len(lab))
w = 0.27
fig, ax = plt.subplots(figsize=(12, 4.2))
for i, v in enumerate(("simplified", "standard")):
    m = [float(r["mad_pdr_pct_vs_analytical"]) for r in rows[v]]
    se = [float(r["se_pct_mean"]) for r in rows[v]]
    ax.bar(x + (i - 1) * w, m, w, yerr=se, capsize=2, label=f"simulator ({v} procedures) vs model")
ax.bar(
    x + w,
    [float(r["mad_pdr_pct_analytical_vs_veins"]) for r in rows["simplified"]],
    w,
    color="0.6",
    label="model vs the authors' Veins",
)
ax.axhline(1.5, ls="--", c="k", lw=1, label="target 1.5 points")
ax.set_xticks(x, lab, fontsize=7)
ax.set_ylabel("mean |PDR difference| 0-500 m (points)")
ax.set_title(
    "cv2x-marl validate --study: 8 seeds x 4000 subframes (error bars: standard error of the curve, mean over bins)",
    fontsize=9,
)
ax.legend(fontsize=8)
fig.tight_layout()
fig.savefig("docs/validation/grid_mad.png", dpi=110)
