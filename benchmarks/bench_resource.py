"""Throughput of ``cv2x/Resource-v0`` as users get it: agent-steps per second of the PettingZoo parallel env
(21 agents, the task's scenario), one thread, episodes of 100 steps, actions drawn up front (list entries
0 .. 19 uniformly: an entry past a vehicle's list keeps the standard's draw, as a policy's choice would cost the
same), three settings:

- ``steps``: the step alone (resets outside the clock);
- ``resets``: a fresh episode seed every 100 steps, its ``reset()`` inside the clock (the simulator's 1,000-subframe
  warm-up each time);
- ``pool64``: ``start_pool=64`` after one warm pass over the pool's 64 starts, resets inside the clock (a reset
  copies a kept start).

Also the milliseconds per ``reset()`` (fresh / from the warm pool). Best of ``--repeats``. Writes
``benchmarks/results/bench_resource.json``; docs/performance.md quotes it next to the target (>= 20k agent-steps/s
with resets, one core).

    python benchmarks/bench_resource.py [--repeats 3] [--steps 1000]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from cv2x_marl.env.registry import make_parallel_env  # noqa: E402
from cv2x_marl.io import write_json  # noqa: E402

ENV_ID = "cv2x/Resource-v0"
EPISODE = 100
POOL = 64
TARGET = 20_000.0


def throughput(steps: int, setting: str) -> float:
    """Agent-steps/s of the parallel env in ``setting`` (module docstring)."""
    pool = POOL if setting == "pool64" else 0
    env = make_parallel_env(ENV_ID, max_cycles=EPISODE, start_pool=pool)
    rng = np.random.default_rng(0)
    table = rng.integers(0, 20, (64, env.n))
    acts = [{a: np.int64(table[k, i]) for i, a in enumerate(env.possible_agents)} for k in range(64)]
    if pool:  # one warm pass: every start of the pool kept
        env.reset(seed=0)
        for _ in range(4 * POOL):
            env.reset()
    fresh = iter(range(10**6, 2 * 10**6))
    env.reset(seed=next(fresh) if not pool else None)
    elapsed = 0.0
    t0 = time.perf_counter()
    for k in range(steps):
        if not env.agents:
            if setting == "steps":
                elapsed += time.perf_counter() - t0
                env.reset(seed=next(fresh))
                t0 = time.perf_counter()
            else:
                env.reset(seed=None if pool else next(fresh))
        env.step(acts[k % 64])
    elapsed += time.perf_counter() - t0
    return steps * env.n / elapsed


def reset_ms(pool: int, count: int) -> float:
    """Mean ms per ``reset()`` (fresh seeds, or from the warm pool)."""
    env = make_parallel_env(ENV_ID, max_cycles=EPISODE, start_pool=pool)
    env.reset(seed=1)
    if pool:
        for _ in range(4 * POOL):
            env.reset()
    seeds = iter(range(3 * 10**6, 4 * 10**6))
    t0 = time.perf_counter()
    for _ in range(count):
        env.reset(seed=None if pool else next(seeds))
    return (time.perf_counter() - t0) / count * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="runs per setting (best of)")
    ap.add_argument("--steps", type=int, default=1000, help="env steps timed per run")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/bench_resource.json"))
    args = ap.parse_args()
    make_parallel_env(ENV_ID, max_cycles=3).reset(seed=0)  # compile / load the kernels outside the clock
    rows: dict[str, float] = {}
    for setting in ("steps", "resets", "pool64"):
        runs = [throughput(args.steps, setting) for _ in range(args.repeats)]
        rows[setting] = max(runs)
        print(f"Resource-v0 {setting:7s} {rows[setting]:>10,.0f} agent-steps/s (runs: "
              f"{', '.join(f'{r:,.0f}' for r in runs)})", flush=True)  # fmt: skip
    rows["reset_ms_fresh"] = min(reset_ms(0, 20) for _ in range(args.repeats))
    rows["reset_ms_pool"] = min(reset_ms(POOL, 200) for _ in range(args.repeats))
    print(f"reset: {rows['reset_ms_fresh']:.2f} ms fresh, {rows['reset_ms_pool']:.2f} ms from the pool")
    met = rows["pool64"] >= TARGET
    print(f"target >= {TARGET:,.0f} agent-steps/s with resets (start pool): {'met' if met else 'NOT met'}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(
        args.out,
        {"env_id": ENV_ID, "agents": 21, "episode": EPISODE, "results": rows, "target": TARGET,
         "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()}},
    )  # fmt: skip


if __name__ == "__main__":
    main()
