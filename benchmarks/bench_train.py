"""End-to-end training throughput: SB3 PPO on ``cv2x/SingleMover-*`` next to Gymnasium's Pendulum-v1.

Both runs use the PPO settings and the number of env copies of the shipped single-mover config
(``agents/configs/ppo_single_v2_residual.yaml`` unless ``--config``), one torch thread, no callbacks, and
are measured in the same process in interleaved pairs (ours, Pendulum, ours, ...), so each ratio
compares the two on the same machine state; reported: the best of each and the median of the
per-pair ratios (goal of issue 10: ours >= 0.7x Pendulum). Ours goes through the
:class:`~cv2x_marl.rl.sb3_vec_env.AgentsVecEnv` that ``cv2x-marl train`` uses (one-mover fast path);
Pendulum through SB3's ``DummyVecEnv``. Also timed alone: the env part of ours (random actions
through the same VecEnv, resets included). Best of ``--repeats``. Writes ``benchmarks/results/bench_train.json``.

    python benchmarks/bench_train.py [--timesteps 32768] [--repeats 2] [--env cv2x/SingleMover-v2] [--start-pool N]

With ``--start-pool N`` our training episodes start from N episode seeds whose starts are cached
(``TrainConfig.start_pool``); each timed run starts with an empty cache, so it pays for the pool.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from cv2x_marl.io import write_json  # noqa: E402


def ppo_steps_per_s(vec: Any, cfg: Any, timesteps: int, seed: int) -> float:
    from cv2x_marl.env.starts import START_CACHE as _START_CACHE
    from cv2x_marl.rl.train import make_ppo

    _START_CACHE.clear()  # every timed run pays for its own start pool (with --start-pool)
    model = make_ppo(vec, cfg.ppo, seed)
    t0 = time.perf_counter()
    model.learn(timesteps)
    return model.num_timesteps / (time.perf_counter() - t0)


def env_steps_per_s(vec: Any, steps: int) -> float:
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (64, vec.num_envs, 2)).astype(np.float32)
    vec.seed(0)
    vec.reset()
    t0 = time.perf_counter()
    for k in range(steps):
        vec.step(acts[k % 64])
    return steps * vec.num_envs / (time.perf_counter() - t0)


def main() -> None:
    import gymnasium
    import torch
    from stable_baselines3.common.env_util import make_vec_env

    from cv2x_marl.rl.train import load_train_config
    from cv2x_marl.rl.train import make_vec_env as make_ours

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="agents/configs/ppo_single_v2_residual.yaml")
    ap.add_argument("--env", default=None, help="override the config's env id")
    ap.add_argument("--timesteps", type=int, default=32_768)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--start-pool", type=int, default=None, help="train from N cached episode starts")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = load_train_config(Path(args.config), env_id=args.env)
    if args.start_pool is not None:
        import dataclasses

        cfg = dataclasses.replace(cfg, start_pool=args.start_pool)
    ours = make_ours(cfg)
    ours.seed(0)
    pend = make_vec_env("Pendulum-v1", n_envs=cfg.copies, seed=0)
    rows: dict[str, Any] = {
        "env_id": cfg.env_id,
        "config": args.config,
        "copies": cfg.copies,
        "start_pool": cfg.start_pool,
        "timesteps": args.timesteps,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs",
        "gymnasium": gymnasium.__version__,
        "torch": torch.__version__,
    }
    rows["ours_env_only_steps_per_s"] = max(env_steps_per_s(ours, 2_000) for _ in range(args.repeats))
    ours_runs, pend_runs = [], []
    for _ in range(args.repeats):  # interleaved pairs: a drift of the machine's speed hits both alike
        ours_runs.append(ppo_steps_per_s(ours, cfg, args.timesteps, 0))
        pend_runs.append(ppo_steps_per_s(pend, cfg, args.timesteps, 0))
    ratios = [a / b for a, b in zip(ours_runs, pend_runs, strict=True)]
    rows["ours_ppo_steps_per_s_runs"] = ours_runs
    rows["pendulum_ppo_steps_per_s_runs"] = pend_runs
    rows["ratio_runs"] = ratios
    rows["ours_ppo_steps_per_s"] = max(ours_runs)
    rows["pendulum_ppo_steps_per_s"] = max(pend_runs)
    rows["ratio_ours_to_pendulum"] = rows["ours_ppo_steps_per_s"] / rows["pendulum_ppo_steps_per_s"]
    rows["ratio_median_of_pairs"] = float(np.median(ratios))
    for k, v in rows.items():
        if isinstance(v, list):
            print(f"{k}: " + ", ".join(f"{x:,.2f}" for x in v))
        else:
            print(f"{k}: {v:,.2f}" if isinstance(v, float) else f"{k}: {v}")
    suffix = "" if cfg.start_pool is None else f"_pool{cfg.start_pool}"
    write_json(Path(f"benchmarks/results/bench_train{suffix}.json"), rows)


if __name__ == "__main__":
    main()
