"""Vector-env throughput: ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`` next to
``SyncVectorEnv`` over the same single-agent envs, in the same run (issue 11).

Env-steps per second (one env-step = one copy's step: the mover's agent-step) for K copies of
``cv2x/SingleMover-v2`` with the options of the shipped single-mover config (plan residual, utility
reward, episodes of 100 steps), random actions drawn up front. Two settings: ``steps`` (autoreset
disabled, the resets between episodes left out of the timed window: the step alone) and
``episodes100`` (autoresets included, as in training: each reset runs a stage-1 simulation and the
sensing plan). Best of
``--repeats``; a warm-up step compiles or loads the numba kernels first. One thread.
Writes ``benchmarks/results/bench_vector.json``.

    python benchmarks/bench_vector.py [--copies 1 8 32] [--steps 400] [--repeats 3]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from cv2x_marl.io import write_json  # noqa: E402

ENV_ID = "cv2x/SingleMover-v2"
OPTIONS = {"action_mode": "plan_residual", "reward_form": "utility"}


def env_steps_per_s(mode: str, copies: int, steps: int, with_resets: bool) -> float:
    import gymnasium

    autoreset = "NextStep" if with_resets else "Disabled"
    kwargs: dict[str, Any] = {"max_cycles": 100, **OPTIONS}
    if mode == "sync":
        kwargs["vector_kwargs"] = {"autoreset_mode": autoreset}
    else:
        kwargs["autoreset_mode"] = autoreset
    envs: Any = gymnasium.make_vec(ENV_ID, num_envs=copies, vectorization_mode=mode, **kwargs)
    acts = np.random.default_rng(0).uniform(-1, 1, (64, copies, 2)).astype(np.float32)
    envs.reset(seed=0)
    envs.step(acts[0])  # warm-up: kernels compiled or loaded from the cache
    elapsed = 0.0
    t0 = time.perf_counter()
    for k in range(1, steps + 1):
        if not with_resets and k % 100 == 0:  # every copy's episode ended: reset outside the clock
            elapsed += time.perf_counter() - t0
            envs.reset()
            t0 = time.perf_counter()
        envs.step(acts[k % 64])
    elapsed += time.perf_counter() - t0
    envs.close()
    return steps * copies / elapsed


def main() -> None:
    import gymnasium

    import cv2x_marl  # noqa: F401 - registers the ids

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, nargs="+", default=[1, 8, 32])
    ap.add_argument("--steps", type=int, default=400, help="vector steps timed per run")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rows: dict[str, Any] = {
        "env_id": ENV_ID,
        "options": OPTIONS,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs",
        "gymnasium": gymnasium.__version__,
    }
    for setting, with_resets in (("steps", False), ("episodes100", True)):
        for k in args.copies:
            for mode in ("sync", "vector_entry_point"):
                rows[f"{setting}_k{k}_{mode}"] = max(
                    env_steps_per_s(mode, k, args.steps, with_resets) for _ in range(args.repeats)
                )
            ratio = rows[f"{setting}_k{k}_vector_entry_point"] / rows[f"{setting}_k{k}_sync"]
            rows[f"{setting}_k{k}_speedup"] = ratio
            print(
                f"{setting:12s} K={k:3d}  sync {rows[f'{setting}_k{k}_sync']:>10,.0f}  "
                f"vector_entry_point {rows[f'{setting}_k{k}_vector_entry_point']:>10,.0f} env-steps/s  "
                f"({ratio:.1f}x)",
                flush=True,
            )
    write_json(Path("benchmarks/results/bench_vector.json"), rows)


if __name__ == "__main__":
    main()
