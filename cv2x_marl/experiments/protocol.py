"""The benchmark protocol's statistics of evaluation rows (docs/benchmark.md): the team's gain per episode, the
per-episode means over the movers, the interquartile mean with its 95 % stratified bootstrap interval
(:mod:`cv2x_marl.stats`) over runs x episodes, and the summary as `cv2x-marl evaluate` prints it.
:mod:`cv2x_marl.experiments.evaluate` makes the rows and re-exports these names.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from cv2x_marl import stats

#: the summary keys the protocol adds (``seeds`` given or several runs)
PROTOCOL_KEYS = (
    "runs",
    "seeds",
    "iqm_utility_gain",
    "ci95_utility_gain",
    "iqm_prr_gain",
    "ci95_prr_gain",
    "iqm_share_of_optimum",
    "ci95_share_of_optimum",
    "bootstrap",
)
#: the seed of every bootstrap generator (a fresh ``default_rng(BOOTSTRAP_SEED)`` per statistic: the
#: same scores give the same interval in `evaluate` and `benchmark`)
BOOTSTRAP_SEED = 0


def team_gain(rows: Sequence[dict[str, Any]], start: str, end: str) -> np.ndarray:
    """[rows] the gain of the team in each row's episode (the same value on every row of it): eq. 17 of
    the mean over the episode's movers, ``(mean(end) - mean(start)) / |mean(start)|`` (NaN when the mean
    start is 0). With the utility per target receiver this is the gain of the Cooperative task's team
    objective J (:mod:`cv2x_marl.env.team_search`); with PRRs, of the network mean PRR."""
    groups: dict[tuple[int, int], list[int]] = {}
    for k, r in enumerate(rows):
        groups.setdefault((int(r.get("run", 0)), int(r["episode"])), []).append(k)
    out = np.full(len(rows), np.nan)
    for index in groups.values():
        j0 = float(np.mean([rows[k][start] for k in index]))
        j1 = float(np.mean([rows[k][end] for k in index]))
        if j0 != 0:
            out[index] = (j1 - j0) / abs(j0)
    return out


def episode_means(rows: Sequence[dict[str, Any]], key: str, runs: int, episodes: int) -> np.ndarray:
    """[runs, episodes] the mean of ``key`` over each episode's movers (NaN values left out; NaN when
    every mover's is). Rows without a ``run`` are run 0."""
    total = np.zeros((runs, episodes))
    count = np.zeros((runs, episodes))
    for r in rows:
        v = float(r[key])
        if np.isfinite(v):
            i, j = int(r.get("run", 0)), int(r["episode"])
            total[i, j] += v
            count[i, j] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def interval(scores: np.ndarray) -> tuple[float, list[float]]:
    """The protocol's IQM of ``scores`` [runs, episodes] and its 95 % stratified bootstrap interval
    (:func:`cv2x_marl.stats.bootstrap_ci`, 2000 resamples, generator ``default_rng(BOOTSTRAP_SEED)``)."""
    point, lo, hi = stats.bootstrap_ci(scores, np.random.default_rng(BOOTSTRAP_SEED))
    return point, [lo, hi]


def protocol_summary(
    rows: Sequence[dict[str, Any]], runs: int, episodes: int, vs_optimum: bool = False
) -> dict[str, Any]:
    """The protocol's statistics over runs x episodes: IQM and 95 % CI of the per-episode utility and
    PRR gains (each the mean over the episode's movers of eq. 17) and, with ``vs_optimum``, of the
    per-episode share of the optimum (the episode's gain over the optimum's gain on it)."""
    out: dict[str, Any] = {"runs": runs}
    ug = episode_means(rows, "utility_gain", runs, episodes)
    out["iqm_utility_gain"], out["ci95_utility_gain"] = interval(ug)
    out["iqm_prr_gain"], out["ci95_prr_gain"] = interval(episode_means(rows, "prr_gain", runs, episodes))
    if vs_optimum:
        og = episode_means(rows, "optimum_gain", runs, episodes)[:1]  # the same on every run
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.where(og != 0, ug / og, np.nan)
        out["iqm_share_of_optimum"], out["ci95_share_of_optimum"] = interval(share)
    out["bootstrap"] = {
        "statistic": "iqm",
        "resamples": stats.N_RESAMPLES,
        "level": stats.LEVEL,
        "seed": BOOTSTRAP_SEED,
        "resampled": "runs and episodes (crossed), docs/benchmark.md",
    }
    return out


def format_summary(summary: dict[str, Any], label: str | None = None) -> str:
    """The summary as `cv2x-marl evaluate` prints it (``label``: the policy as given; default the summary's)."""
    policy = summary["policy"]
    label = label or (", ".join(policy) if isinstance(policy, list) else str(policy))
    share = f", {summary['share_of_optimum']:.1%} of the optimum's gain" if "share_of_optimum" in summary else ""
    text = (
        f"{label} on {summary['env']}, {summary['episodes']} episodes x "
        f"{summary['movers_per_episode']} movers: "
        f"utility gain {summary['mean_utility_gain']:+.1%}, PRR gain {summary['mean_prr_gain']:+.1%}, "
        f"effectiveness {summary['effectiveness']:.1%}, Jain {summary['jain_fairness']:.3f}, "
        f"return {summary['mean_return']:.1f}{share}"
    )
    if "iqm_utility_gain" in summary:
        parts = [
            ("utility gain", "utility_gain"),
            ("PRR gain", "prr_gain"),
            ("share of the optimum", "share_of_optimum"),
        ]
        sign = {"share_of_optimum": ""}
        shown = []
        for name, key in parts:
            if "iqm_" + key in summary:
                f = "{:" + sign.get(key, "+") + ".1%}"
                lo, hi = summary["ci95_" + key]
                shown.append(f"{name} {f.format(summary['iqm_' + key])} [{f.format(lo)}, {f.format(hi)}]")
        text += f"\nIQM over {summary['runs']} run(s) x {summary['episodes']} episodes (95% CI): " + ", ".join(shown)
    return text
