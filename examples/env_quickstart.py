"""The benchmark's envs from their registered ids, a scripted expert through the public API, and the scripted movers
against the ceiling on the task's held-out episodes.

    python examples/env_quickstart.py [--episodes 8] [--quick]

Creates ``cv2x/SingleMover-v3`` (Gymnasium) and runs one episode with GBMU acting on the Gymnasium env's parallel
env (``env.unwrapped.par``), one random episode of ``cv2x/Cooperative-v0`` (PettingZoo, every vehicle moves), then
compares GBMU, the sensing planner and the ceiling (``optimum``) on the single-mover task's first held-out episodes
with :func:`cv2x_marl.experiments.evaluate.evaluate` (share of the ceiling's gain).
"""

from __future__ import annotations

import argparse

import gymnasium
import numpy as np
import pettingzoo

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env.tasks import TASKS
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.policies.registry import make_policy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="short episodes and a short warm-up (for tests)")
    args = ap.parse_args()
    kw = {"max_cycles": 10, "overrides": ["sim.warmup_subframes=200"]} if args.quick else {}
    episodes = 2 if args.quick else args.episodes

    single = gymnasium.make("cv2x/SingleMover-v3", **kw)
    obs, info = single.reset(seed=0)
    par = single.unwrapped.par  # the parallel env behind the Gymnasium one: what the scripted movers act in
    expert = make_policy("gbmu", par)
    expert.reset(seed=0)
    done = False
    while not done:
        action = expert.act({"vehicle_0": obs})["vehicle_0"]
        obs, _, terminated, truncated, info = single.step(action)
        done = terminated or truncated
    print(f"SingleMover-v3, one GBMU episode: utility {info['utility_start']:.2f} -> {info['utility']:.2f}")

    team = pettingzoo.make("parallel", "cv2x/Cooperative-v0", **kw)
    team.reset(seed=0)
    rng = np.random.default_rng(0)
    infos: dict = {}
    while team.agents:
        _, _, _, _, infos = team.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in team.agents})
    prr = np.mean([i["prr"] for i in infos.values()])
    print(f"Cooperative-v0, one random episode: {len(infos)} agents, mean PRR {prr:.3f}")

    seeds = TASKS["singlemover"].heldout_seeds[:episodes]
    for policy in ("gbmu", "sensing", "optimum"):
        res = evaluate(
            "cv2x/SingleMover-v3", policy, episodes, 0, env_kwargs=kw, progress=False, vs_optimum=True, seeds=seeds
        )
        print(
            f"{policy:8s} utility gain {res['mean_utility_gain']:+.1%}  "
            f"share of the ceiling {res['share_of_optimum']:.0%}  effectiveness {res['effectiveness']:.0%}"
        )


if __name__ == "__main__":
    main()
