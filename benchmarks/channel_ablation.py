"""What the coordination channel of ``cv2x/Cooperative-v1`` buys a script: the same sequential script with and
without the announcements, on the first held-out episodes of the cooperative task.

A :mod:`cv2x_marl.policies.sequential` script re-plans at its subframe's turn with the earlier subframes' vehicles
at their announced moves; with ``hear=False`` it plans with every vehicle where it is (simultaneous decisions, the
same search, the same re-plans). The gains are eq. 17 of the team objective J (the benchmark's ``utility_gain``),
shares over the ceiling's gain on the same episode read from a benchmark.csv's ``optimum`` rows (the ceiling does
not depend on the order of decisions).

    python benchmarks/channel_ablation.py [--policy sequential-best-response] [--episodes 8] \
        [--hear both | with | without] [--rows docs/benchmark/benchmark.csv]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.tasks import TASKS
from cv2x_marl.env.team_search import team_objective
from cv2x_marl.policies.sequential import SequentialBestResponsePolicy, SequentialSensingPolicy, SequentialTeamPolicy

POLICIES = {p.name: p for p in (SequentialBestResponsePolicy, SequentialSensingPolicy, SequentialTeamPolicy)}


def gain(env, policy, seed: int) -> float:
    """eq. 17 of J over one episode of ``policy`` (reset here)."""
    obs, _ = env.reset(seed=seed)
    policy.reset(seed)
    j0 = team_objective(env.links, env.positions_m, env.p_min)
    while env.agents:
        obs, *_ = env.step(policy.act(obs))
    return (team_objective(env.links, env.positions_m, env.p_min) - j0) / abs(j0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", default="sequential-best-response", choices=sorted(POLICIES))
    p.add_argument("--episodes", type=int, default=8, help="the first N held-out episodes (1 .. 48)")
    p.add_argument("--hear", default="both", choices=("both", "with", "without"), help="the variants run")
    p.add_argument("--rows", default="docs/benchmark/benchmark.csv", help="a benchmark.csv with the optimum rows")
    args = p.parse_args(argv)
    if not 1 <= args.episodes <= 48:
        raise SystemExit(f"--episodes {args.episodes}: allowed 1 .. 48")
    import csv

    task = TASKS["cooperative"]
    seeds = [int(s) for s in task.heldout_seeds[: args.episodes]]
    with open(args.rows, newline="") as fh:
        ceiling = {
            int(r["seed"]): float(r["utility_gain"])
            for r in csv.DictReader(fh)
            if r["task"] == "cooperative" and r["method"] == "optimum" and r["run"] == "0"
        }
    env = make_parallel_env("cv2x/Cooperative-v1", **task.options)
    kinds = {"both": (True, False), "with": (True,), "without": (False,)}[args.hear]
    t0 = time.perf_counter()
    out: dict[bool, list[float]] = {h: [] for h in kinds}
    for seed in seeds:
        for hear in kinds:
            out[hear].append(gain(env, POLICIES[args.policy](env, hear=hear), seed))
        text = ", ".join(f"{'with' if h else 'without'} the channel {100 * out[h][-1]:+.2f} %" for h in kinds)
        print(
            f"seed {seed}: {text}, ceiling {100 * ceiling[seed]:+.2f} % ({time.perf_counter() - t0:.0f} s)", flush=True
        )
    c = np.array([ceiling[s] for s in seeds])
    for hear in kinds:
        g = np.array(out[hear])
        print(
            f"{args.policy} {'with' if hear else 'without'} the channel: mean gain {100 * g.mean():+.2f} %, "
            f"mean share {100 * np.mean(g / c):.1f} %, share of the summed gains {100 * g.sum() / c.sum():.1f} %"
        )
    if len(kinds) == 2:
        d = np.array(out[True]) - np.array(out[False])
        print(
            f"difference (with - without): mean {100 * d.mean():+.2f} points of gain, {int(np.sum(d > 0))}/{len(d)} > 0"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
