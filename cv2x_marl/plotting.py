"""Figures (matplotlib, headless Agg backend). Kept out of ``cv2x_marl.sim``.

Figures are built as :class:`matplotlib.figure.Figure` objects, without ``pyplot``: no global figure
registry to close, safe in threads and workers, and a lighter import.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from cv2x_marl.io import atomic_write

CAUSE_LABELS = {
    "half_duplex": "half duplex",
    "sensitivity": "below sensitivity",
    "propagation": "propagation",
    "collision": "collision",
}


def _subplots(nrows: int = 1, ncols: int = 1, **kw: Any) -> tuple[Figure, Any]:
    """``pyplot.subplots`` without pyplot: a new :class:`Figure` (``figsize``, ``constrained_layout``, ...)
    and its axes (one, or an array as ``subplots`` returns); ``sharex`` / ``sharey`` go to the axes."""
    share = {k: kw.pop(k) for k in ("sharex", "sharey") if k in kw}
    fig = Figure(**kw)
    return fig, fig.subplots(nrows, ncols, **share)


def plot_prr_vs_distance(summary: dict[str, Any], path: str | Path, title: str = "") -> Path:
    """PRR vs distance (sampled and expected) over the stacked shares of each loss cause (one filled
    step outline per cause over the distance bins: the bars of each bin, drawn as one patch)."""
    rows = summary["prr_vs_distance"]
    loss = summary["loss_causes"]
    d = [r["distance_m"] for r in rows]
    fig = Figure(figsize=(7.5, 4.5))
    ax = fig.add_subplot()
    bottom = [r["prr"] for r in rows]
    width = (d[1] - d[0]) if len(d) > 1 else 10.0
    edges = [x - width / 2 for x in d] + [d[-1] + width / 2] if d else [0.0, width]
    colors = {"half_duplex": "#b07aa1", "sensitivity": "#9c755f", "propagation": "#f28e2b", "collision": "#e15759"}
    for cause, label in CAUSE_LABELS.items():
        share = [r[cause] for r in loss]
        if max(share, default=0.0) <= 0.0:
            continue
        top = [b + s for b, s in zip(bottom, share, strict=True)]
        ax.stairs(top, edges, baseline=bottom, fill=True, color=colors[cause], alpha=0.45, label=f"lost: {label}")
        bottom = top
    ax.plot(d, [r["prr"] for r in rows], "k-", lw=2, label="PRR (decoded)")
    ax.plot(d, [r["prr_expected"] for r in rows], "b--", lw=1.2, label="PRR (expected)")
    ax.set_xlabel("Tx-Rx distance (m)")
    ax.set_ylabel("packet reception ratio / share of packets")
    ax.set_ylim(0, 1.02)
    ax.set_xlim(0, max(d, default=1.0) + width)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title(title or f"PRR vs distance (mean per-node PRR {summary['prr_mean']:.3f})")
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.11, top=0.93)  # fixed margins: no layout solver
    return _save(fig, path)


def _save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as a PNG (120 dpi) to ``path``, atomically (temporary file, then rename)."""
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))


def plot_surface(model: Any, path: str | Path, nsv_values: tuple[int, ...] = (1, 3, 5)) -> Path:
    """The paper's Fig. 2: P(d, l) surfaces of the two-distance model for a few NSV values."""
    import numpy as np

    d = np.linspace(10.0, 400.0, 60)
    lgrid = np.linspace(10.0, 200.0, 60)
    dd, ll = np.meshgrid(d, lgrid)
    fig = Figure(figsize=(4.2 * len(nsv_values), 4.0), constrained_layout=True)
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
    fig, ax = _subplots(figsize=(7, 4), constrained_layout=True)
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


METHOD_STYLE = {
    "gbmu": ("#e15759", "GBMU"),
    "greedy": ("#4e79a7", "greedy (eq. 9)"),
    "oracle": ("#59a14f", "oracle"),
    "planner": ("#b07aa1", "planner (model's best reachable)"),
    "optimum": ("#7f7f7f", "optimum (best reachable)"),
    "gbmu-logistic": ("#f28e2b", "GBMU, logistic model"),
    "gbmu-schedule": ("#ff9da7", "GBMU, backtracking step"),
    "gbmu-logistic-schedule": ("#9c755f", "GBMU, logistic + backtracking"),
    "planner-logistic": ("#76b7b2", "planner, logistic model"),
}


def plot_trajectories(
    snapshot: Any, mover: int, target: Any, runs: dict[str, Any], path: str | Path, case: str, judge: str = "simulator"
) -> Path:
    """Fig. 5 / Fig. 7: the network and each method's path for the mover."""
    import numpy as np

    pos = snapshot.positions_m
    res = snapshot.slot * snapshot.n_subchannels + snapshot.subchannel
    co = (res == res[mover]) & (np.arange(pos.shape[0]) != mover)
    fig, ax = _subplots(figsize=(6.5, 6.0), constrained_layout=True)
    ax.scatter(pos[target, 0], pos[target, 1], s=45, c="#4e79a7", label="target receivers", zorder=3)
    others = ~target & ~co
    others[mover] = False
    if others.any():
        ax.scatter(pos[others, 0], pos[others, 1], s=30, c="#bab0ac", label="half duplex (same subframe)", zorder=3)
    if co.any():
        ax.scatter(pos[co, 0], pos[co, 1], s=60, marker="^", c="#f28e2b", label="co-channel interferers", zorder=3)
    for j in np.flatnonzero(target | co):
        ax.annotate(f"UE{j}", pos[j], textcoords="offset points", xytext=(4, 4), fontsize=7)
    for name, r in runs.items():
        color, label = METHOD_STYLE[name]
        tr = r.climb.trajectory_m[:, 0, :]
        ax.plot(tr[:, 0], tr[:, 1], "-", color=color, lw=1.8, label=f"{label}: {r.utility_gain[0]:+.1%} utility")
        ax.plot(*tr[-1], "o", color=color, ms=7, mfc="white", mew=2, zorder=4)
    ax.plot(*pos[mover], "*", color="k", ms=16, label=f"UE{mover} start", zorder=5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    scored = "true" if judge == "simulator" else "model-judged"
    ax.set_title(f"{case}: moving update of UE{mover} ({scored} eq. 12 utility gain)")
    return _save(fig, path)


def plot_gain_curves(runs: dict[str, Any], path: str | Path, case: str, judge: str = "simulator") -> Path:
    """Fig. 6 / Fig. 8: normalised utility gain (eq. 17, scored by the judge) against the iteration."""
    fig, ax = _subplots(figsize=(7, 4), constrained_layout=True)
    for name, r in runs.items():
        color, label = METHOD_STYLE[name]
        u = r.utility_curve[:, 0]
        gain = (u - u[0]) / abs(u[0])
        ax.plot(r.climb.recorded_iterations, 100 * gain, color=color, lw=1.8, label=label)
    ax.set_xlabel("iteration k")
    ax.set_ylabel("utility gain (eq. 17), %")
    ax.grid(alpha=0.3)
    ax.legend()
    scored = "ground truth from the link model" if judge == "simulator" else "judged by the regression model"
    ax.set_title(f"{case}: gain convergence ({scored})")
    return _save(fig, path)


def plot_realization_gains(runs: dict[str, Any], path: str | Path, judge: str = "simulator") -> Path:
    """Fig. 9 and 10: per-realisation utility and PRR gains, sorted by GBMU's gain."""
    import numpy as np

    first = runs.get("gbmu", next(iter(runs.values())))
    order = np.argsort(first.utility_gain)
    fig, axes = _subplots(2, 1, figsize=(9, 6.5), sharex=True, constrained_layout=True)
    x = np.arange(order.size)
    for ax, attr, title in ((axes[0], "utility_gain", "utility (eq. 12)"), (axes[1], "prr_gain", "PRR")):
        for name, r in runs.items():
            color, label = METHOD_STYLE[name]
            vals = 100 * getattr(r, attr)[order]
            if name == "gbmu":
                ax.bar(x, vals, color=color, alpha=0.7, label=f"{label} (mean {np.nanmean(vals):+.1f} %)")
            else:
                ax.plot(x, vals, ".", color=color, ms=4, label=f"{label} (mean {np.nanmean(vals):+.1f} %)")
        ax.axhline(0, color="k", lw=0.8)
        ax.set_ylabel(f"normalised gain in {title}, %")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[1].set_xlabel("realisation (sorted by GBMU utility gain)")
    scored = "" if judge == "simulator" else ", judged by the regression model"
    axes[0].set_title(f"Gains at convergence over {order.size} realisations (Fig. 9 and 10{scored})")
    return _save(fig, path)


def plot_method_comparison(table: list[dict[str, Any]], path: str | Path, title: str) -> Path:
    """Mean utility gain, effectiveness and PRR gain per method; error bars = spread over seeds."""
    import numpy as np

    names = [r["method"] for r in table]
    fig, axes = _subplots(1, 3, figsize=(12, 3.8), constrained_layout=True)
    for ax, key, label in (
        (axes[0], "mean_utility_gain", "mean utility gain (eq. 17), %"),
        (axes[1], "effectiveness", "effectiveness (utility up), %"),
        (axes[2], "mean_prr_gain", "mean PRR gain, %"),
    ):
        vals = np.array([100 * r[key] for r in table])
        err = np.array([100 * r.get(key + "_std", 0.0) for r in table])
        colors = ["#e15759" if n.startswith("ppo") else "#4e79a7" for n in names]
        ax.bar(range(len(names)), vals, yerr=err, color=colors, capsize=4)
        ax.set_xticks(range(len(names)))
        ax.set_xticklabels(names, rotation=30, ha="right")
        ax.set_ylabel(label)
        ax.axhline(0, color="k", lw=0.8)
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(title)
    return _save(fig, path)


def plot_learning_curves(curves: dict[str, list[dict[str, float]]], path: str | Path, title: str) -> Path:
    """The learner's evaluation utility gain during training (one line per seed) against GBMU's: the rows of
    each run's ``eval.csv`` (PPO's ``ppo_mean_utility_gain`` or MAPPO's ``mappo_mean_utility_gain``)."""
    fig, ax = _subplots(figsize=(7, 4), constrained_layout=True)
    gbmu = None
    for name, rows in sorted(curves.items()):
        t = [r["timesteps"] for r in rows]
        key = "ppo_mean_utility_gain" if "ppo_mean_utility_gain" in rows[0] else "mappo_mean_utility_gain"
        ax.plot(t, [100 * r[key] for r in rows], "-o", ms=3, lw=1.2, label=name)
        gbmu = rows[0]["gbmu_mean_utility_gain"]
    if gbmu is not None:
        ax.axhline(100 * gbmu, color="k", ls="--", lw=1.2, label="GBMU (same evaluation episodes)")
    ax.set_xlabel("training agent-steps")
    ax.set_ylabel("evaluation utility gain (eq. 17), %")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(title)
    return _save(fig, path)


def plot_return_vs_cpu(rows: list[dict[str, Any]], path: str | Path, title: str) -> Path:
    """The mean training-episode return against the process CPU seconds of training: the rows of a
    ``curve.csv`` (``cpu_s``, ``train_mean_return``; rows without a return yet are left out)."""
    fig, ax = _subplots(figsize=(7, 4), constrained_layout=True)
    kept = [r for r in rows if r["train_mean_return"] == r["train_mean_return"]]  # NaN before the first episode
    ax.plot([r["cpu_s"] for r in kept], [r["train_mean_return"] for r in kept], "-", lw=1.2)
    ax.set_xlabel("process CPU seconds (start-up, collection and updates)")
    ax.set_ylabel("mean training-episode return")
    ax.grid(alpha=0.3)
    ax.set_title(title)
    return _save(fig, path)


def plot_gain_vs_cpu(curves: dict[str, list[dict[str, Any]]], path: str | Path, title: str) -> Path:
    """The utility gain of a run's evaluations during training against its process CPU seconds, one line per
    run: ``curves`` maps a run's name to the rows of its ``curve.csv`` (``cpu_s``, ``eval_utility_gain``; rows
    without an evaluation, an empty value, are left out)."""
    fig, ax = _subplots(figsize=(7, 4), constrained_layout=True)
    for name, rows in curves.items():
        kept = [r for r in rows if r["eval_utility_gain"] not in ("", None)]
        cpu_s = [float(r["cpu_s"]) for r in kept]
        ax.plot(cpu_s, [100 * float(r["eval_utility_gain"]) for r in kept], "o-", ms=3, label=name)
    ax.set_xlabel("process CPU seconds (collection, fitting and these evaluations)")
    ax.set_ylabel("utility gain, training-list episodes (%)")
    ax.grid(alpha=0.3)
    if len(curves) > 1:
        ax.legend(fontsize=8)
    ax.set_title(title)
    return _save(fig, path)


def plot_sweep(result: dict[str, Any], path: str | Path) -> Path:
    """Held-out utility gain per grid point of a sweep: mean +- std bar, one dot per training seed."""
    points = result["points"]
    fig, ax = _subplots(figsize=(max(5.0, 1.2 * len(points) + 2.5), 4.0), constrained_layout=True)
    for i, p in enumerate(points):
        gains = [  # failed trials (no metrics, or None) have no dot
            100 * t["mean_utility_gain"]
            for t in result["trials"]
            if t["config"] == p["config"] and t["status"] == "TERMINATED" and t.get("mean_utility_gain") is not None
        ]
        if p.get("mean_utility_gain") is not None:
            sd = 100 * (p.get("std_utility_gain") or 0.0)
            ax.bar(i, 100 * p["mean_utility_gain"], yerr=sd, color="#4e79a7", alpha=0.6, capsize=4)
        if gains:
            ax.plot([i] * len(gains), gains, "ko", ms=4)
    ax.set_xticks(range(len(points)), [p["label"] for p in points], rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("held-out mean utility gain (%)")
    ax.set_title(
        f"sweep: {len(result['seeds'])} seed(s) x {len(points)} point(s), {result['timesteps']} steps, "
        f"{result['eval_episodes']} episodes (seed {result['eval_seed']})",
        fontsize=9,
    )
    ax.axhline(0, color="k", lw=0.8)
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def plot_benchmark(summary: dict[str, Any], path: str | Path) -> Path:
    """`cv2x-marl benchmark`: per task (one panel each) every method's IQM utility gain on the held-out
    episodes with its 95 % bootstrap interval; the ceiling's IQM a dashed line (its interval shaded)."""
    tasks = summary["tasks"]
    import math

    fig = Figure(figsize=(4.5 * len(tasks) + 0.5, 4.0), constrained_layout=True)
    axes = fig.subplots(1, len(tasks), squeeze=False)
    for ax, (name, task) in zip(axes[0], tasks.items(), strict=True):
        rows = [(m, r) for m, r in task["methods"].items() if m != task["ceiling"]]
        for i, (_, r) in enumerate(rows):
            lo, hi = r["ci95_utility_gain"]
            mid = r["iqm_utility_gain"]
            ax.errorbar(
                i, 100 * mid, yerr=[[100 * (mid - lo)], [100 * (hi - mid)]], fmt="o", color="#4e79a7", capsize=4
            )
        ceil = task["methods"].get(task["ceiling"])
        if ceil is not None and all(math.isfinite(v) for v in (ceil["iqm_utility_gain"], *ceil["ci95_utility_gain"])):
            ax.axhline(100 * ceil["iqm_utility_gain"], color="#e15759", ls="--", label=f"ceiling ({task['ceiling']})")
            ax.axhspan(*(100 * v for v in ceil["ci95_utility_gain"]), color="#e15759", alpha=0.12)
            ax.legend(fontsize=8, loc="lower right")
        ax.set_xticks(range(len(rows)), [m for m, _ in rows], rotation=20, ha="right", fontsize=8)
        ax.set_xlim(-0.6, len(rows) - 0.4)
        ax.set_title(f"{name} ({task['env_id']}), {task['episodes']} held-out episodes", fontsize=9)
        ax.set_ylabel("IQM utility gain (%), 95% CI")
        ax.axhline(0, color="k", lw=0.8)
        ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)
