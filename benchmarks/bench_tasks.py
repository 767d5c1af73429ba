"""Throughput of the issue-27 tasks as users get them, resets included (issue 27, "Fast resets everywhere").

Agent-steps per second (steps x agents: one per copy for ``cv2x/SingleMover-v3``, 21 per step for
``cv2x/Cooperative-v0``), one thread, N = 21 (the ``paper`` preset), episodes of 100 steps, random
actions drawn up front:

- ``cv2x/SingleMover-v3``: ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``, K copies
  (default 16);
- ``cv2x/Cooperative-v0``: the PettingZoo parallel env (``cv2x_marl.env.registry.make_parallel_env``).

Three settings each: ``steps`` (resets outside the clock: the step alone), ``resets`` (``start_pool=0``:
every episode a fresh stage-1 run, inside the clock: ``SameStep`` autoreset for the vector env, a
``reset()`` every 100 steps for the parallel env) and ``pool64`` (``start_pool=64``, after one warm pass
over the pool's 64 starts, so resets reuse the kept starts; for the vector env also its kept rows, filled by
pooled resets of a warm-up vector env). Also the milliseconds per ``reset()`` of one
env (fresh seeds / from the warm pool). Best of ``--repeats`` (the machine may be shared: best-of-N is the
least disturbed run). Writes ``benchmarks/results/bench_tasks.json``; ``docs/performance.md``
("Benchmark tasks (issue 27)") quotes it next to the targets (SingleMover-v3 K = 16 >= 50k agent-steps/s
with resets, Cooperative-v0 >= 30k).

Also a ``cold`` run as a user's script gets it: a new process imports the package, makes the K-copy vector
env with ``start_pool=64``, resets it and steps ``--cold-steps`` vector steps (the pool's starts are made the
first time each is drawn), timed over the whole process and over the loop.

    python benchmarks/bench_tasks.py [--copies 16] [--repeats 3] [--steps 300] [--coop-steps 500] [--cold-steps 2000]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from cv2x_marl.io import write_json  # noqa: E402

EPISODE = 100
POOL = 64
TARGETS = {"cv2x/SingleMover-v3": 50_000.0, "cv2x/Cooperative-v0": 30_000.0}


def cpu_model() -> str:
    """``lscpu``'s model name (or Python's guess)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return platform.processor() or platform.machine()
    for line in out.splitlines():
        if line.startswith("Model name:"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def warm_pool(env_id: str, copies: int = 16) -> None:
    """One reset per seed of the start pool: their starts are kept (process-wide cache). For
    ``SingleMover-v3`` also pooled resets of a K-copy vector env until every pool seed came once, so that
    the vector env's kept starts (``cv2x_marl.env.vector.KEPT_STARTS``, process-wide) hold them all."""
    import gymnasium

    from cv2x_marl.env.registry import make_parallel_env
    from cv2x_marl.env.seeds import training_pool
    from cv2x_marl.env.vector import KEPT_STARTS

    env = make_parallel_env(env_id, max_cycles=EPISODE, start_pool=POOL)
    for seed in training_pool(POOL):
        env.reset(seed=int(seed))
    if env_id != "cv2x/SingleMover-v3":
        return
    envs: Any = gymnasium.make_vec(
        env_id, num_envs=copies, vectorization_mode="vector_entry_point", max_cycles=EPISODE, start_pool=POOL
    )
    envs.reset(seed=0)
    for _ in range(200):  # 16 draws each from 64 seeds: all of them long before 200 rounds
        envs.reset()
        if len(KEPT_STARTS) >= POOL:
            break
    envs.close()


def single_mover(copies: int, steps: int, setting: str) -> float:
    """Agent-steps/s of K ``SingleMover-v3`` copies (vector entry point) in ``setting``."""
    import gymnasium

    pool = POOL if setting == "pool64" else 0
    autoreset = "Disabled" if setting == "steps" else "SameStep"
    envs: Any = gymnasium.make_vec(
        "cv2x/SingleMover-v3", num_envs=copies, vectorization_mode="vector_entry_point", max_cycles=EPISODE,
        start_pool=pool, autoreset_mode=autoreset,
    )  # fmt: skip
    acts = np.random.default_rng(0).uniform(-1, 1, (64, copies, 2)).astype(np.float32)
    envs.reset(seed=None if pool else 0)
    envs.step(acts[0])  # warm-up: kernels compiled or loaded from the cache
    elapsed = 0.0
    t0 = time.perf_counter()
    for k in range(1, steps + 1):
        if setting == "steps" and k % EPISODE == 0:  # every copy's episode ended: reset outside the clock
            elapsed += time.perf_counter() - t0
            envs.reset()
            t0 = time.perf_counter()
        envs.step(acts[k % 64])
    elapsed += time.perf_counter() - t0
    envs.close()
    return steps * copies / elapsed


def cooperative(steps: int, setting: str) -> float:
    """Agent-steps/s of ``Cooperative-v0`` (parallel env, 21 agents) in ``setting``."""
    from cv2x_marl.env.registry import make_parallel_env

    pool = POOL if setting == "pool64" else 0
    env = make_parallel_env("cv2x/Cooperative-v0", max_cycles=EPISODE, start_pool=pool)
    rng = np.random.default_rng(0)
    table = rng.uniform(-1, 1, (64, env.n, 2)).astype(np.float32)
    acts = [dict(zip(env.possible_agents, table[k], strict=True)) for k in range(64)]
    env.reset(seed=None if pool else 0)
    env.step(acts[0])
    env.reset()
    elapsed = 0.0
    t0 = time.perf_counter()
    for k in range(steps):
        if not env.agents:
            if setting == "steps":
                elapsed += time.perf_counter() - t0
                env.reset()
                t0 = time.perf_counter()
            else:
                env.reset()
        env.step(acts[k % 64])
    elapsed += time.perf_counter() - t0
    return steps * env.n / elapsed


COLD_RUN = """
import sys, time
t0 = time.perf_counter()
import gymnasium, numpy as np
import cv2x_marl.env
copies, steps = int(sys.argv[1]), int(sys.argv[2])
envs = gymnasium.make_vec("cv2x/SingleMover-v3", num_envs=copies, vectorization_mode="vector_entry_point",
                          max_cycles=100, start_pool=64)
envs.reset(seed=0)
acts = np.random.default_rng(0).uniform(-1, 1, (64, copies, 2)).astype(np.float32)
t1 = time.perf_counter()
for k in range(steps):
    envs.step(acts[k % 64])
t2 = time.perf_counter()
print(steps * copies / (t2 - t0), steps * copies / (t2 - t1))
"""


def cold_single_mover(copies: int, steps: int) -> tuple[float, float]:
    """A user's run in a new process: import, ``make_vec(..., start_pool=64)``, ``reset(seed=0)``, ``steps``
    vector steps with SameStep autoreset (every pool start drawn the first time is a fresh stage-1 run).
    Returns agent-steps/s over the whole process (start-up included) and over the stepping loop."""
    import sys

    out = subprocess.run(
        [sys.executable, "-c", COLD_RUN, str(copies), str(steps)], capture_output=True, text=True, check=True
    ).stdout.split()
    return float(out[0]), float(out[1])


def reset_ms(env_id: str, pool: int, count: int) -> float:
    """Mean ms per ``reset()`` of one parallel env (fresh seeds, or from the warm pool)."""
    from cv2x_marl.env.registry import make_parallel_env

    env = make_parallel_env(env_id, max_cycles=EPISODE, start_pool=pool)
    env.reset(seed=1)
    t0 = time.perf_counter()
    for _ in range(count):
        env.reset()
    return (time.perf_counter() - t0) / count * 1e3


def main() -> None:
    import cv2x_marl  # noqa: F401 - registers the ids

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=16)
    ap.add_argument("--steps", type=int, default=300, help="vector steps timed per SingleMover run")
    ap.add_argument("--coop-steps", type=int, default=500, help="Cooperative steps timed per run")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--cold-steps", type=int, default=2000, help="vector steps of the cold-process SingleMover run (0: skip)"
    )
    args = ap.parse_args()
    rows: dict[str, Any] = {
        "machine": f"{cpu_model()}, {os.cpu_count()} logical CPUs (one thread used)",
        "n_vehicles": 21,
        "episode_steps": EPISODE,
        "copies": args.copies,
        "repeats": args.repeats,
        "statistic": "best of repeats",
        "targets_agent_steps_per_s_with_resets": TARGETS,
    }
    for env_id in TARGETS:
        warm_pool(env_id, args.copies)
    for setting in ("steps", "resets", "pool64"):
        key = f"single_mover_v3_k{args.copies}_{setting}"
        rows[key] = max(single_mover(args.copies, args.steps, setting) for _ in range(args.repeats))
        print(f"SingleMover-v3 K={args.copies} {setting:7s} {rows[key]:>10,.0f} agent-steps/s", flush=True)
        key = f"cooperative_v0_{setting}"
        rows[key] = max(cooperative(args.coop_steps, setting) for _ in range(args.repeats))
        print(f"Cooperative-v0      {setting:7s} {rows[key]:>10,.0f} agent-steps/s", flush=True)
    for env_id, name in (("cv2x/SingleMover-v3", "single_mover_v3"), ("cv2x/Cooperative-v0", "cooperative_v0")):
        for pool, label, count in ((0, "fresh", 8), (POOL, "pool64", 32)):
            key = f"{name}_reset_ms_{label}"
            rows[key] = min(reset_ms(env_id, pool, count) for _ in range(args.repeats))
            print(f"{env_id} reset ({label}): {rows[key]:.2f} ms", flush=True)
    if args.cold_steps:
        runs = [cold_single_mover(args.copies, args.cold_steps) for _ in range(args.repeats)]
        whole, loop = max(r[0] for r in runs), max(r[1] for r in runs)
        key = f"single_mover_v3_k{args.copies}_cold_{args.cold_steps * args.copies}"
        rows[f"{key}_whole_process"], rows[f"{key}_loop"] = whole, loop
        print(
            f"SingleMover-v3 K={args.copies} cold process, {args.cold_steps * args.copies:,} agent-steps: "
            f"{whole:,.0f} agent-steps/s whole process, {loop:,.0f} in the loop",
            flush=True,
        )
    for env_id, name in (
        ("cv2x/SingleMover-v3", f"single_mover_v3_k{args.copies}"),
        ("cv2x/Cooperative-v0", "cooperative_v0"),
    ):
        best = max(rows[f"{name}_resets"], rows[f"{name}_pool64"])
        rows[f"{name}_target_met_with_resets"] = bool(best >= TARGETS[env_id])
    write_json(Path("benchmarks/results/bench_tasks.json"), rows)


if __name__ == "__main__":
    main()
