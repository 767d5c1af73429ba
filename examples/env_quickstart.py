"""Both envs from their registered ids, and the scripted movers on the same episodes.

    python examples/env_quickstart.py [--episodes 8] [--quick]

Creates ``cv2x/SingleMover-v2`` (Gymnasium) and ``cv2x/Mobility-v2`` (PettingZoo), runs one episode
of each by hand, then compares GBMU, the sensing planner and the optimum on the same held-out
episodes with :func:`cv2x_marl.experiments.evaluate.evaluate` (share of the optimum's gain).
"""

from __future__ import annotations

import argparse

import gymnasium
import numpy as np
import pettingzoo

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.experiments.evaluate import evaluate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="short episodes and a short warm-up (for tests)")
    args = ap.parse_args()
    kw = {"max_cycles": 10, "overrides": ["sim.warmup_subframes=200"]} if args.quick else {}
    episodes = 2 if args.quick else args.episodes

    single = gymnasium.make("cv2x/SingleMover-v2", **kw)
    obs, info = single.reset(seed=0)
    layout = single.unwrapped.par.layout
    done = False
    while not done:  # drive straight along the observed plan (the sensing planner by hand)
        plan = layout.own_v1(obs)[6:8] * layout.scale_m / 5.0  # plan offset (m) over max_step_m
        obs, _, terminated, truncated, info = single.step(np.clip(plan, -1, 1).astype(np.float32))
        done = terminated or truncated
    print(f"SingleMover-v2, one episode: utility {info['utility_start']:.2f} -> {info['utility']:.2f}")

    multi = pettingzoo.make("parallel", "cv2x/Mobility-v2", **kw)
    multi.reset(seed=0)
    rng = np.random.default_rng(0)
    infos: dict = {}
    while multi.agents:
        _, _, _, _, infos = multi.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in multi.agents})
    prr = np.mean([i["prr"] for i in infos.values()])
    print(f"Mobility-v2, one random episode: {len(infos)} agents, mean PRR {prr:.3f}")

    for policy in ("gbmu", "sensing", "optimum"):
        res = evaluate("cv2x/SingleMover-v2", policy, episodes, 2026, env_kwargs=kw, progress=False, vs_optimum=True)
        print(
            f"{policy:8s} utility gain {res['mean_utility_gain']:+.1%}  "
            f"share of the optimum {res['share_of_optimum']:.0%}  effectiveness {res['effectiveness']:.0%}"
        )


if __name__ == "__main__":
    main()
