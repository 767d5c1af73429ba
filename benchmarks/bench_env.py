"""Env throughput: agent-steps per second at N = 21 in snapshot and traffic modes, next to MPE2's
``simple_spread`` measured in the same run (goal: snapshot >= 100k, traffic >= 20k, one core).

Actions are precomputed (zeros), so the figure is the env's own cost. Writes
``results/bench_env.json``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402


def agent_steps_per_s(env: Any, steps: int) -> float:
    env.reset(seed=0)
    acts = {a: np.zeros(env.action_space(a).shape, dtype=np.float32) for a in env.agents}
    t0 = time.perf_counter()
    n = 0
    for _ in range(steps):
        if not env.agents:
            env.reset(seed=n)
        env.step({a: acts[a] for a in env.agents})
        n += len(acts)
    return n / (time.perf_counter() - t0)


def main() -> None:
    from mpe2 import simple_spread_v3

    from cv2x_marl.env import parallel_env

    rows: dict[str, float] = {}
    rows["snapshot_n21"] = max(agent_steps_per_s(parallel_env(max_cycles=10_000), 3000) for _ in range(3))
    rows["traffic_n21"] = max(
        agent_steps_per_s(parallel_env(mode="traffic", max_cycles=10_000), 1000) for _ in range(3)
    )
    for n in (3, 21):
        mpe = simple_spread_v3.parallel_env(N=n, max_cycles=10_000, continuous_actions=True)
        rows[f"mpe2_simple_spread_n{n}"] = max(agent_steps_per_s(mpe, 3000) for _ in range(3))
    for k, v in rows.items():
        print(f"{k}: {v:,.0f} agent-steps/s")
    for mode in ("snapshot_n21", "traffic_n21"):
        for n in (3, 21):
            print(f"ratio {mode} / mpe2 simple_spread N={n}: {rows[mode] / rows[f'mpe2_simple_spread_n{n}']:.2f}")
    out = Path("results/bench_env.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
