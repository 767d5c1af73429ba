"""How much of ``cv2x/Resource-v0``'s ceiling is coordination between vehicles that reselect in the same period
(docs/benchmark.md, "Why the resource learners stop near half of the ceiling").

On training-list episodes (``TRAIN_SEEDS[300:300+N]``, never a held-out one) it runs, from the same start:

    sps          the standard's choice (the gains' 0)
    optimum      the ceiling: the deciders' entries chosen together for the expected team objective
    independent  the same objective and knowledge, each decider choosing alone with the other deciders on the
                 resources the standard drew for them (``ResourceCeiling(joint=False)``)

and counts, at every step of the ``sps`` runs, how many vehicles decide. Writes ``coordination.csv`` (one row per
episode and method: the team's episode-mean utility and its gain against ``sps``), ``deciders.csv`` (steps by number
of deciders), ``summary.json`` and ``coordination.png`` to ``--out``.

    python benchmarks/resource_coordination.py [--episodes 48] [--out docs/benchmark/resource_coordination]
"""

from __future__ import annotations

import argparse
import copy
import csv
import sys
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.tasks import TRAIN_SEEDS
from cv2x_marl.io import write_json
from cv2x_marl.policies.resource import ResourceCeiling, make_resource_policy
from cv2x_marl.stats import bootstrap_ci, iqm

METHODS = ("sps", "optimum", "independent")
#: the training-list episodes this diagnostic uses (past the start pool's first 256 and the scripts' checks)
FIRST_SEED = 300


def run_episode(seed: int) -> tuple[dict[str, float], np.ndarray]:
    """Each method's team episode-mean utility on episode ``seed``, and the steps of the ``sps`` run by number of
    deciders ([10]; the last bin holds 9 or more)."""
    start = make_parallel_env("cv2x/Resource-v0")
    start.reset(seed=seed)
    out: dict[str, float] = {}
    counts = np.zeros(10, dtype=np.int64)
    for method in METHODS:
        env = copy.deepcopy(start)
        if method == "independent":
            policy: Any = ResourceCeiling(env, joint=False)
        else:
            policy = make_resource_policy(method, env)
        policy.reset(seed)
        obs = env.observations()
        while env.agents:
            if method == "sps":
                counts[min(int((env.pending.decides & env.mover_mask).sum()), 9)] += 1
            obs, *_ = env.step(policy.act(obs))
        out[method] = float(env.u_sum.mean() / env.t)
    return out, counts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--episodes", type=int, default=48, help="training-list episodes (1-512)")
    ap.add_argument("--out", type=Path, default=Path("docs/benchmark/resource_coordination"))
    args = ap.parse_args()
    if not 1 <= args.episodes <= 512:
        sys.exit(f"--episodes must be in [1, 512], got {args.episodes}")
    seeds = TRAIN_SEEDS[FIRST_SEED : FIRST_SEED + args.episodes]
    rows: list[dict[str, Any]] = []
    counts = np.zeros(10, dtype=np.int64)
    for k, seed in enumerate(seeds):
        utility, c = run_episode(seed)
        counts += c
        for method in METHODS:
            gain = (utility[method] - utility["sps"]) / abs(utility["sps"])
            rows.append({"seed": seed, "method": method, "utility": utility[method], "utility_gain": gain})
        print(f"episode {k + 1}/{len(seeds)}: " + ", ".join(f"{m} {utility[m]:.4f}" for m in METHODS), flush=True)
    summary: dict[str, Any] = {"episodes": len(seeds), "seeds": f"TRAIN_SEEDS[{FIRST_SEED}:{FIRST_SEED + len(seeds)}]"}
    for method in METHODS:
        g = np.array([r["utility_gain"] for r in rows if r["method"] == method])
        _, lo, hi = bootstrap_ci(g, np.random.default_rng(0))
        summary[method] = {"iqm_utility_gain": float(iqm(g)), "ci95": [float(lo), float(hi)], "mean": float(g.mean())}
    decisions = counts * np.arange(10)
    summary["steps_by_deciders"] = counts.tolist()
    summary["decisions_with_another_decider"] = float(decisions[2:].sum() / max(decisions.sum(), 1))
    args.out.mkdir(parents=True, exist_ok=True)
    with (args.out / "coordination.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    with (args.out / "deciders.csv").open("w", newline="") as f:
        f.write("deciders,steps\n" + "".join(f"{d}{'+' if d == 9 else ''},{n}\n" for d, n in enumerate(counts)))
    write_json(args.out / "summary.json", summary)
    figure(args.out / "coordination.png", summary, counts)
    for method in METHODS[1:]:
        s = summary[method]
        print(f"{method}: IQM gain {100 * s['iqm_utility_gain']:+.1f} % [{100 * s['ci95'][0]:+.1f}, "
              f"{100 * s['ci95'][1]:+.1f}]")  # fmt: skip
    print(f"decisions taken with another vehicle deciding in the same step: "
          f"{100 * summary['decisions_with_another_decider']:.1f} %")  # fmt: skip


def figure(path: Path, summary: dict[str, Any], counts: np.ndarray) -> None:
    """Two panels: each method's IQM gain with its interval, and the steps by number of deciders."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    names = list(METHODS[1:])
    vals = [100 * summary[m]["iqm_utility_gain"] for m in names]
    err = np.array(
        [[v - 100 * summary[m]["ci95"][0], 100 * summary[m]["ci95"][1] - v] for m, v in zip(names, vals, strict=True)]
    )
    a.bar(["ceiling\n(joint)", "each decider\nalone"], vals, yerr=err.T, color=["#4c72b0", "#dd8452"], capsize=4)
    a.axhline(0, color="k", lw=0.8)
    a.set_ylabel("team utility gain vs sps, IQM (%)")
    a.set_title("same knowledge, with and without coordination")
    b.bar(np.arange(10), counts, color="#55a868")
    b.set_xticks(np.arange(10), [str(d) if d < 9 else "9+" for d in range(10)])
    b.set_xlabel("vehicles deciding in the step")
    b.set_ylabel("steps")
    b.set_title(f"{100 * summary['decisions_with_another_decider']:.0f} % of decisions are concurrent")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
