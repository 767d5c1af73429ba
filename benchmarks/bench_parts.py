"""One fixed env workload per process, for paired before / after timings of the env's structure (whole
processes: start-up, imports, numba's cache load, resets and steps). Prints the workload's own step rate too.

    python benchmarks/bench_parts.py {mobility,traffic,single,vector} [--seed 0]

``mobility``: cv2x/Mobility-v3, every vehicle moves, 30 episodes of 100 steps; ``traffic``: cv2x/Traffic-v1
through PettingZoo, 20 episodes of 100 steps; ``single``: gymnasium cv2x/SingleMover-v3 (the one-mover path),
60 episodes of 100 steps; ``vector``: ``gymnasium.make_vec`` of cv2x/SingleMover-v3 with 16 copies (the batched
kernels), 3,000 vector steps with autoreset. Actions are drawn from the action spaces with fixed seeds.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402


def parallel(env_id: str, episodes: int, seed: int) -> tuple[int, float]:
    from cv2x_marl.env.registry import make_parallel_env

    env = make_parallel_env(env_id, max_cycles=100)
    rng = np.random.default_rng(seed)
    steps, t0 = 0, time.perf_counter()
    for e in range(episodes):
        env.reset(seed=seed + e)
        while env.agents:
            env.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents})
            steps += len(env.possible_agents)
    return steps, time.perf_counter() - t0


def single(episodes: int, seed: int) -> tuple[int, float]:
    import gymnasium

    import cv2x_marl  # noqa: F401  (registers the ids)

    env = gymnasium.make("cv2x/SingleMover-v3")
    env.action_space.seed(seed)
    steps, t0 = 0, time.perf_counter()
    for e in range(episodes):
        env.reset(seed=seed + e)
        done = False
        while not done:
            _, _, term, trunc, _ = env.step(env.action_space.sample())
            done = term or trunc
            steps += 1
    return steps, time.perf_counter() - t0


def vector(copies: int, vector_steps: int, seed: int) -> tuple[int, float]:
    import gymnasium

    import cv2x_marl  # noqa: F401

    env = gymnasium.make_vec("cv2x/SingleMover-v3", num_envs=copies, vectorization_mode="vector_entry_point")
    env.action_space.seed(seed)
    env.reset(seed=seed)
    t0 = time.perf_counter()
    for _ in range(vector_steps):
        env.step(env.action_space.sample())
    return copies * vector_steps, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workload", choices=("mobility", "traffic", "single", "vector"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    if args.workload == "mobility":
        steps, dt = parallel("cv2x/Mobility-v3", 30, args.seed)
    elif args.workload == "traffic":
        steps, dt = parallel("cv2x/Traffic-v1", 20, args.seed)
    elif args.workload == "single":
        steps, dt = single(60, args.seed)
    else:
        steps, dt = vector(16, 3000, args.seed)
    print(f"{args.workload}: {steps} agent-steps in {dt:.2f} s (resets included): {steps / dt:,.0f} per s")


if __name__ == "__main__":
    main()
