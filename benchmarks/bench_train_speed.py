"""Training agent-steps per CPU-second: SB3 PPO next to ``ppo.backend: torchrl`` (:mod:`cv2x_marl.rl.fast_ppo`).

Both train the same configuration (``agents/configs/ppo_single_v3_deepsets.yaml`` unless ``--config``: the same
env id and options, the same copies, network, ``n_steps``, ``batch_size`` and ``n_epochs``) for the same number
of agent-steps, each in a fresh process (so each pays its own imports' start, env construction and the stage-1
runs of the pool starts it meets), with torch on 1 and on 2 threads. Measured with ``time.process_time`` (the
process's CPU time, every thread counted):

* ``cpu_s``: from the start of the process's work (after the imports) to the end of training: building the env
  copies and the model, resets, collection and updates;
* ``collect_cpu_s``: the rollouts alone (SB3: from ``_on_rollout_start`` to ``_on_rollout_end``; torchrl: the
  collection and GAE), the remainder being the updates and start-up;
* ``phases``: the steady state (the env option ``start_pool: 8``, after a warm-up of 6 iterations, so every reset
  is a kept start), CPU milliseconds per iteration of ``n_steps`` x copies agent-steps over 20 iterations, split
  into the collection (SB3: the rollout; torchrl: the collection and GAE) and the rest (the update), torch on
  one thread; ``--phases-only`` measures this alone;
* ``step_only``: the env alone through each trainer's adapter (SB3: :class:`~cv2x_marl.rl.sb3_vec_env.AgentsVecEnv`;
  torchrl: :class:`~cv2x_marl.env.vector.SingleMoverVectorEnv`), random actions, resets included, the same
  agent-steps, also in a fresh process.

    python benchmarks/bench_train_speed.py [--timesteps 20480] [--threads 1 2] [--config FILE] [--phases-only]

Writes ``benchmarks/results/bench_train_speed_<config stem>.json``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from cv2x_marl.io import write_json  # noqa: E402


def _config(path: str, backend: str) -> Any:
    from cv2x_marl.rl.train_config import load_train_config

    cfg = load_train_config(Path(path))
    return dataclasses.replace(cfg, ppo=dataclasses.replace(cfg.ppo, backend=backend))


def run_sb3(path: str, timesteps: int, seed: int) -> dict[str, Any]:
    """SB3 PPO as ``cv2x-marl train`` builds it (no callbacks but the timer)."""
    from stable_baselines3.common.callbacks import BaseCallback

    from cv2x_marl.rl.train import make_ppo, make_vec_env

    cpu0 = time.process_time()
    cfg = _config(path, "sb3")
    vec = make_vec_env(cfg)
    model = make_ppo(vec, cfg.ppo, seed, layout=vec.envs[0].layout)
    collect = [0.0]

    class Timer(BaseCallback):
        def _on_rollout_start(self) -> None:
            self.t = time.process_time()

        def _on_rollout_end(self) -> None:
            collect[0] += time.process_time() - self.t

        def _on_step(self) -> bool:
            return True

    model.learn(timesteps, callback=Timer())
    return {"agent_steps": int(model.num_timesteps), "cpu_s": time.process_time() - cpu0, "collect_cpu_s": collect[0]}


def run_torchrl(path: str, timesteps: int, seed: int) -> dict[str, Any]:
    """The ``ppo.backend: torchrl`` loop (what ``cv2x-marl train`` runs, without its evaluations and files)."""
    from cv2x_marl.rl.fast_ppo import FastPpo

    cpu0 = time.process_time()
    run = FastPpo(_config(path, "torchrl"), seed)
    collect = 0.0
    while run.agent_steps < timesteps:
        t = time.process_time()
        data = run.advantages(run.collect())
        collect += time.process_time() - t
        run.update(data)
    return {"agent_steps": run.agent_steps, "cpu_s": time.process_time() - cpu0, "collect_cpu_s": collect}


def _steady(path: str) -> Any:
    """The configuration with the env option ``start_pool: 8``: after a warm-up every reset is a kept start."""
    cfg = _config(path, "torchrl")
    return dataclasses.replace(cfg, env={**cfg.env, "start_pool": 8})


def phases_sb3(path: str, iterations: int, seed: int) -> dict[str, Any]:
    """SB3's CPU milliseconds per iteration in the steady state: the rollout, and the rest (the update)."""
    from stable_baselines3.common.callbacks import BaseCallback

    from cv2x_marl.rl.train import make_ppo, make_vec_env

    cfg = dataclasses.replace(_steady(path), ppo=dataclasses.replace(_steady(path).ppo, backend="sb3"))
    vec = make_vec_env(cfg)
    model = make_ppo(vec, cfg.ppo, seed, layout=vec.envs[0].layout)
    rollout = cfg.ppo.n_steps * cfg.copies
    model.learn(6 * rollout)  # warm-up: every pool start computed once
    collect = [0.0]

    class Timer(BaseCallback):
        def _on_rollout_start(self) -> None:
            self.t = time.process_time()

        def _on_rollout_end(self) -> None:
            collect[0] += time.process_time() - self.t

        def _on_step(self) -> bool:
            return True

    t0 = time.process_time()
    model.learn(iterations * rollout, reset_num_timesteps=False, callback=Timer())
    total = time.process_time() - t0
    return {"collect_ms": 1e3 * collect[0] / iterations, "update_ms": 1e3 * (total - collect[0]) / iterations}


def phases_torchrl(path: str, iterations: int, seed: int) -> dict[str, Any]:
    """The torchrl loop's CPU milliseconds per iteration in the steady state: collection with GAE, update."""
    from cv2x_marl.rl.fast_ppo import FastPpo

    run = FastPpo(_steady(path), seed)
    for _ in range(6):  # warm-up: every pool start computed once
        run.iterate()
    collect = update = 0.0
    for _ in range(iterations):
        t0 = time.process_time()
        data = run.advantages(run.collect())
        t1 = time.process_time()
        run.update(data)
        collect, update = collect + t1 - t0, update + time.process_time() - t1
    return {"collect_ms": 1e3 * collect / iterations, "update_ms": 1e3 * update / iterations}


def run_step_only(path: str, timesteps: int, seed: int, backend: str) -> dict[str, Any]:
    """The env alone through ``backend``'s adapter: random actions, resets included."""
    cpu0 = time.process_time()
    cfg = _config(path, backend)
    rng = np.random.default_rng(seed)
    steps = -(-timesteps // cfg.copies)
    acts = rng.uniform(-1, 1, (64, cfg.copies, 2)).astype(np.float32)
    if backend == "sb3":
        from cv2x_marl.rl.train import make_vec_env

        vec = make_vec_env(cfg)
        vec.seed(seed)
        vec.reset()
        for k in range(steps):
            vec.step(acts[k % 64])
    else:
        from cv2x_marl.env.vector import SingleMoverVectorEnv

        env = SingleMoverVectorEnv(cfg.copies, autoreset_mode="SameStep", env_id=cfg.env_id, **cfg.env)
        env.reset(seed=seed)
        for k in range(steps):
            env.step(acts[k % 64])
    return {"agent_steps": steps * cfg.copies, "cpu_s": time.process_time() - cpu0}


def child(args: argparse.Namespace) -> None:
    import torch

    torch.set_num_threads(args.threads)
    if args.child.startswith("phases:"):
        fn = phases_sb3 if args.child == "phases:sb3" else phases_torchrl
        out = fn(args.config, 20, args.seed)
    elif args.child == "sb3":
        out = run_sb3(args.config, args.timesteps, args.seed)
    elif args.child == "torchrl":
        out = run_torchrl(args.config, args.timesteps, args.seed)
    else:
        out = run_step_only(args.config, args.timesteps, args.seed, args.child.split(":")[1])
    out["torch_threads"] = torch.get_num_threads()
    print(json.dumps(out))


def measure(kind: str, args: argparse.Namespace, threads: int) -> dict[str, Any]:
    cmd = [sys.executable, __file__, "--child", kind, "--threads-one", str(threads), "--config", args.config]
    cmd += ["--timesteps", str(args.timesteps), "--seed", str(args.seed)]
    res = subprocess.run(cmd, check=True, capture_output=True, text=True)
    out = json.loads(res.stdout.strip().splitlines()[-1])
    if "agent_steps" in out:
        out["steps_per_cpu_s"] = out["agent_steps"] / out["cpu_s"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="agents/configs/ppo_single_v3_deepsets.yaml")
    ap.add_argument("--timesteps", type=int, default=20_480)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--phases-only", action="store_true", help="only the steady-state collection / update split")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--threads-one", dest="threads_one", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        args.threads = args.threads_one
        child(args)
        return
    import stable_baselines3
    import torch
    import torchrl

    cfg = _config(args.config, "torchrl")
    rows: dict[str, Any] = {
        "config": args.config,
        "env_id": cfg.env_id,
        "copies": cfg.copies,
        "ppo": {k: getattr(cfg.ppo, k) for k in ("n_steps", "batch_size", "n_epochs", "encoder", "encoder_units")},
        "net_arch": list(cfg.ppo.net_arch),
        "timesteps": args.timesteps,
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs",
        "torch": torch.__version__,
        "torchrl": torchrl.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "runs": {},
    }
    for kind in ("phases:sb3", "phases:torchrl"):  # steady state, per iteration of n_steps x copies agent-steps
        rows["runs"][kind] = measure(kind, args, 1)
        print(kind, rows["runs"][kind], flush=True)
    if args.phases_only:
        write_json(Path(f"benchmarks/results/bench_train_speed_phases_{Path(args.config).stem}.json"), rows)
        return
    for kind in ("step:sb3", "step:torchrl"):
        rows["runs"][kind] = measure(kind, args, 1)
        print(kind, rows["runs"][kind], flush=True)
    for threads in args.threads:
        for kind in ("sb3", "torchrl"):
            key = f"{kind}_threads{threads}"
            rows["runs"][key] = measure(kind, args, threads)
            print(key, rows["runs"][key], flush=True)
        sb3, fast = rows["runs"][f"sb3_threads{threads}"], rows["runs"][f"torchrl_threads{threads}"]
        rows[f"ratio_threads{threads}"] = fast["steps_per_cpu_s"] / sb3["steps_per_cpu_s"]
        print(f"torchrl / sb3 agent-steps per CPU-second, {threads} thread(s): {rows[f'ratio_threads{threads}']:.2f}")
    write_json(Path(f"benchmarks/results/bench_train_speed_{Path(args.config).stem}.json"), rows)


if __name__ == "__main__":
    main()
