"""Compile the numba kernels once, ahead of the first use (``make install`` runs ``python -m
cv2x_marl.experiments.warm``).

numba compiles a kernel on its first call in a process and caches the machine code on disk (``cache=True``);
a process that finds the cache loads it instead. Without this step the first process after an install pays
the compilation (measured: 13.5 s to the first step of ``cv2x/SingleMover-v3`` with an empty cache, 0.6 s with
a warm one, 2-core machine). This module calls every path a user's first commands take: every registered env id
(reset and a few steps, single and batched), the simulator on the ``paper`` and ``highway`` presets, and the
policies of the benchmark's tasks.
"""

from __future__ import annotations

import sys
import time
import warnings

import numpy as np

from cv2x_marl.config import apply_overrides, preset
from cv2x_marl.env.registry import ENV_IDS, make_parallel_env
from cv2x_marl.env.tasks import TASKS
from cv2x_marl.policies.registry import make_policy
from cv2x_marl.sim.simulator import Simulator


def warm(verbose: bool = True) -> float:
    """Run the package's compiled paths once; returns the seconds it took."""
    import gymnasium

    t0 = time.perf_counter()

    def say(what: str) -> None:
        if verbose:
            print(f"  {time.perf_counter() - t0:5.1f} s  {what}", file=sys.stderr, flush=True)

    for name in ("paper", "highway"):
        sim = Simulator(apply_overrides(preset(name), ["sim.warmup_subframes=0"]))
        sim.reset(0)
        sim.run(200, record=False)
        say(f"simulator ({name})")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the older ids' deprecation notices
        for env_id in ENV_IDS:
            env = make_parallel_env(env_id, max_cycles=3)
            env.reset(seed=0)
            while env.agents:
                env.step(dict.fromkeys(env.agents, env.dynamics.null_action))
            env.close()
            spec = gymnasium.spec(env_id) if env_id in gymnasium.registry else None
            if spec is not None and spec.vector_entry_point is not None:
                vec = gymnasium.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point", max_cycles=3)
                vec.reset(seed=0)
                vec.step(np.zeros(vec.action_space.shape, np.float32))
                vec.close()
            say(env_id)
        for task in TASKS.values():
            env = make_parallel_env(task.env_id, max_cycles=2)
            for method in (*task.methods, task.ceiling):
                env.reset(seed=0)
                policy = make_policy(method, env)
                policy.reset(0)
                obs = env.reset(seed=0)[0]
                policy.act(obs)
            env.close()
            say(f"{task.name}: {', '.join((*task.methods, task.ceiling))}")
    return time.perf_counter() - t0


def main() -> int:
    print("compiling the numba kernels once (cached on disk for every later process) ...", file=sys.stderr)
    took = warm()
    print(f"numba kernels compiled and cached in {took:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
