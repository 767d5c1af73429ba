"""Env throughput: agent-steps per second at N = 21 in snapshot and traffic modes, next to MPE2's
``simple_spread`` measured in the same run (goal: snapshot >= 100k, traffic >= 20k, one core).

Actions are precomputed draws from the action spaces (every vehicle moves every step), so
the figure is the env's own cost. Long episodes measure ``step`` alone; the ``*_episodes100`` rows
include a ``reset`` every 100 steps (a new stage-1 snapshot each time), as in training. Best of 3.
The first call compiles the numba kernels (cached on disk afterwards); a warm-up step runs before
timing. Writes ``benchmarks/results/bench_env.json``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

from cv2x_marl.io import write_json  # noqa: E402


def agent_steps_per_s(env: Any, steps: int) -> float:
    env.reset(seed=0)
    for i, a in enumerate(env.possible_agents):
        env.action_space(a).seed(i)
    acts = [{a: env.action_space(a).sample() for a in env.possible_agents} for _ in range(64)]
    env.step(acts[0])  # warm-up (numba kernels load or compile)
    t0 = time.perf_counter()
    n = 0
    for k in range(steps):
        if not env.agents:
            env.reset(seed=k)
        env.step(acts[k % 64])
        n += len(env.possible_agents)
    return n / (time.perf_counter() - t0)


def reset_ms(env: Any, resets: int = 30) -> float:
    env.reset(seed=0)
    t0 = time.perf_counter()
    for s in range(resets):
        env.reset(seed=s)
    return (time.perf_counter() - t0) / resets * 1e3


def main() -> None:
    from mpe2 import simple_spread_v3

    from cv2x_marl.env import parallel_env

    rows: dict[str, float] = {}
    rows["snapshot_n21"] = max(agent_steps_per_s(parallel_env(max_cycles=10_000), 5000) for _ in range(3))
    rows["snapshot_n21_episodes100"] = max(agent_steps_per_s(parallel_env(max_cycles=100), 5000) for _ in range(3))
    rows["traffic_n21"] = max(
        agent_steps_per_s(parallel_env(mode="traffic", max_cycles=10_000), 2000) for _ in range(3)
    )
    rows["traffic_n21_episodes100"] = max(
        agent_steps_per_s(parallel_env(mode="traffic", max_cycles=100), 2000) for _ in range(3)
    )
    rows["snapshot_reset_ms"] = min(reset_ms(parallel_env()) for _ in range(3))
    rows["traffic_reset_ms"] = min(reset_ms(parallel_env(mode="traffic")) for _ in range(3))
    for n in (3, 21):
        mpe = simple_spread_v3.parallel_env(N=n, max_cycles=10_000, continuous_actions=True)
        rows[f"mpe2_simple_spread_n{n}"] = max(agent_steps_per_s(mpe, 3000) for _ in range(3))
    for k, v in rows.items():
        print(f"{k}: {v:.2f} ms" if k.endswith("_ms") else f"{k}: {v:,.0f} agent-steps/s")
    for mode in ("snapshot_n21", "traffic_n21"):
        for n in (3, 21):
            print(f"ratio {mode} / mpe2 simple_spread N={n}: {rows[mode] / rows[f'mpe2_simple_spread_n{n}']:.2f}")
    write_json(Path("benchmarks/results/bench_env.json"), rows)


if __name__ == "__main__":
    main()
