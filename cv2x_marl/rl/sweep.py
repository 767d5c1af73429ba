"""Training sweeps on Ray Tune (`cv2x-marl sweep`), and Ray for any embarrassingly parallel loop.

One trial = one ``cv2x-marl train`` run (:func:`cv2x_marl.rl.train.train`) for a seed and a grid
point, followed by a held-out evaluation of its model (episodes from ``eval_seed``, never used in
training). Trials run as Ray Tune trials, one CPU each: with no ``address`` an embedded local Ray
is started (nothing to set up) and shut down afterwards; with one, an existing cluster is used.
Ray's session files go to a short temporary folder that is removed at the end (unix socket paths
must stay under ~107 characters, so they cannot live under a deep run folder); Tune's experiment
state goes under ``<out>/tune``. The sweep folder is a run folder (:mod:`cv2x_marl.runs`):
``trials/<name>/`` (each a complete train run folder), ``trials.csv``, ``results.json`` and
``sweep.png`` (held-out utility gain per grid point, one dot per seed).

Ray is the ``[ray]`` extra (``pip install 'cv2x_marl[ray]'``).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import itertools
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.parallel import ray_session
from cv2x_marl.policies.ppo import PpoPolicy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train import PpoConfig, TrainConfig, check_training_config, train
from cv2x_marl.runs import RunFolder
from cv2x_marl.yamlcore import YAMLError, parse_scalar

#: held-out metrics of a trial (from :func:`cv2x_marl.experiments.evaluate.evaluate`)
METRICS = ("mean_utility_gain", "effectiveness", "mean_prr_gain", "jain_fairness", "share_of_optimum")


def parse_grid(items: Sequence[str]) -> dict[str, list[Any]]:
    """``["ppo.learning_rate=1e-4,3e-4", "copies=4,8"]`` -> ``{key: [values]}`` (YAML 1.2 values).

    Keys are training-config keys: top-level (``copies``, ``checkpoint_every``, ...), ``ppo.NAME``
    or ``env.NAME`` (an env argument).

    Raises:
        TrainError: a malformed item, an unknown key or an empty value list, naming it.
    """
    top = {f.name for f in dataclasses.fields(TrainConfig)} - {"ppo", "env", "env_id"}
    ppo = {f.name for f in dataclasses.fields(PpoConfig)}
    grid: dict[str, list[Any]] = {}
    for item in items:
        key, sep, values = item.partition("=")
        key = key.strip()
        if not sep or not values.strip():
            raise TrainError(f"--grid expects key=v1,v2,..., got {item!r}")
        section, dot, name = key.partition(".")
        ok = (not dot and key in top) or (section == "ppo" and name in ppo) or (section == "env" and name)
        if not ok:
            raise TrainError(
                f"--grid key {key!r} unknown; keys: {', '.join(sorted(top))}, ppo.<{'|'.join(sorted(ppo))}>, "
                "env.<env argument>"
            )
        try:
            grid[key] = [parse_scalar(v) for v in values.split(",")]
        except YAMLError as exc:
            raise TrainError(f"--grid {key}: cannot parse {values!r}: {exc}") from exc
    return grid


def grid_points(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    """Every combination of the grid's values (one empty point for an empty grid)."""
    keys = list(grid)
    return [dict(zip(keys, combo, strict=True)) for combo in itertools.product(*(grid[k] for k in keys))]


def apply_point(cfg: TrainConfig, point: dict[str, Any]) -> TrainConfig:
    """``cfg`` with the grid point's values (validated by :class:`TrainConfig`)."""
    d = cfg.to_dict()
    for key, value in point.items():
        section, dot, name = key.partition(".")
        if dot:
            d[section] = {**d[section], name: value}
        else:
            d[key] = value
    d["ppo"] = PpoConfig(**{**d["ppo"], "net_arch": tuple(d["ppo"]["net_arch"])})
    return TrainConfig(**d)


def _label(point: dict[str, Any]) -> str:
    return ",".join(f"{k}={v}" for k, v in point.items()) or "base"


def _trial_name(seed: int, point: dict[str, Any]) -> str:
    safe = "".join(c if c.isalnum() or c in "._=-" else "-" for c in _label(point).replace(",", "_"))
    return f"seed{seed}_{safe}"


def _trial(spec: dict[str, Any]) -> dict[str, Any]:
    """One trial: train, then evaluate the model on held-out episodes. Runs in a Ray worker."""
    cfg: TrainConfig = spec["cfg"]
    run_dir = Path(spec["run_dir"])
    t0 = time.perf_counter()
    record = train(cfg, spec["timesteps"], spec["seed"], run_dir, progress=False)
    held = evaluate(
        cfg.env_id,
        PpoPolicy(run_dir / "model.zip"),
        spec["eval_episodes"],
        spec["eval_seed"],
        None,
        cfg.env,
        progress=False,
        vs_optimum=spec["vs_optimum"],
    )
    return {
        **{k: held.get(k) for k in METRICS},
        "timesteps": record["timesteps"],
        "train_wall_s": record["wall_s"],
        "trial_wall_s": time.perf_counter() - t0,
    }


def _tune_trial(config: dict[str, Any]) -> None:
    from ray import tune

    tune.report(_trial(config["trial"]))


def run_sweep(
    base: TrainConfig,
    seeds: Sequence[int],
    grid: dict[str, list[Any]],
    timesteps: int,
    out_dir: Path,
    address: str | None = None,
    eval_episodes: int = 48,
    eval_seed: int = 2026,
    vs_optimum: bool = False,
    overwrite: bool = False,
    progress: bool = True,
) -> dict[str, Any]:
    """Train one PPO run per (seed, grid point) as Ray Tune trials and evaluate each held out.

    Args:
        base: the training configuration the grid modifies.
        seeds: training seeds.
        grid: ``{key: [values]}`` (:func:`parse_grid`); the trials are seeds x grid points.
        timesteps: agent-steps per trial.
        out_dir: the sweep's run folder.
        address: a Ray cluster address (``ray://...`` or ``auto``); None starts a local Ray.
        eval_episodes, eval_seed: the held-out episodes every trial's model is evaluated on.
        vs_optimum: also compute the optimum on those episodes (``share_of_optimum``).

    Returns:
        ``{"trials": [{"name", "seed", "config", "status", <metrics>}], "points": [...], ...}``;
        a trial's ``status`` is Tune's (``TERMINATED`` or ``ERROR``).

    Raises:
        TrainError: no seeds, a bad grid value or configuration (every grid point is checked as
            :func:`cv2x_marl.rl.train.check_training_config` does, before the folder is created and
            Ray starts), or every trial failed.
        SweepInterrupted: Tune stopped before every trial finished; Ctrl-C and SIGTERM raise
            KeyboardInterrupt at once. Either way the sweep folder is rolled back and nothing is plotted.
    """
    if not seeds:
        raise TrainError("--seeds: give at least one seed")
    if len(set(seeds)) != len(seeds):
        raise TrainError(f"--seeds: repeated seed in {list(seeds)}")
    points = grid_points(grid)
    configs = [apply_point(base, p) for p in points]  # every grid value validated before Ray starts

    for point, cfg in zip(points, configs, strict=True):  # env arguments, SB3 rules, memory: before the folder
        try:
            check_training_config(cfg)
        except TrainError as exc:
            if not point:
                raise
            raise TrainError(f"grid point {_label(point)}: {exc}") from exc
    out_dir = Path(out_dir).resolve()
    params = {"seeds": list(seeds), "grid": grid, "timesteps": timesteps, "eval_seed": eval_seed}
    with RunFolder(out_dir, "sweep", overwrite=overwrite, parameters=params):
        specs = [
            {
                "name": _trial_name(seed, point),
                "seed": seed,
                "point": point,
                "cfg": cfg,
                "timesteps": timesteps,
                "run_dir": str(out_dir / "trials" / _trial_name(seed, point)),
                "eval_episodes": eval_episodes,
                "eval_seed": eval_seed,
                "vs_optimum": vs_optimum,
            }
            for point, cfg in zip(points, configs, strict=True)
            for seed in seeds
        ]
        t0 = time.perf_counter()
        rows = _run_on_tune(specs, out_dir, address, progress)
        result = _summarise(rows, points, seeds, timesteps, eval_episodes, eval_seed, time.perf_counter() - t0)
        _write(out_dir, result)
        if all(r["status"] != "TERMINATED" for r in rows):
            raise TrainError(f"every trial failed; first error: {rows[0].get('error')}")
    return result


class SweepInterrupted(KeyboardInterrupt):
    """A sweep stopped before its trials finished (Ctrl-C, SIGTERM, or Tune's own stop signal):
    the sweep folder is rolled back like any interrupted run, and nothing is summarised or plotted."""


#: Ray Tune's switch for its own SIGINT handler (read when ``Tuner.fit`` starts)
TUNE_SIGINT_SWITCH = "TUNE_DISABLE_SIGINT_HANDLER"


@contextlib.contextmanager
def _interrupts_raise() -> Any:
    """Ctrl-C and SIGTERM raise KeyboardInterrupt while Ray runs the sweep (enter before Ray starts).

    Ray and Tune each replace a handler: ``ray.init`` makes SIGTERM call ``sys.exit`` (and its core
    logs the signal and aborts the process: exit -6, no message), and ``Tuner.fit``
    (``ray.tune.tune._setup_signal_catching``) makes SIGINT only end Tune's loop, so ``fit`` returns
    the unfinished trials and logs a restore hint for a folder this run removes. Here Tune's switch
    (:data:`TUNE_SIGINT_SWITCH`) keeps Python's Ctrl-C, and :func:`_raise_on_sigterm`, called once
    Ray has started, puts back SIGTERM -> KeyboardInterrupt. Ray's shutdown
    (:func:`cv2x_marl.parallel.ray_session`) then stops the trials. The handlers (SIGINT, SIGTERM
    and the SIGUSR1 Tune also takes) and the switch are put back afterwards.
    """
    import os
    import signal
    import threading

    previous = os.environ.get(TUNE_SIGINT_SWITCH)
    main = threading.current_thread() is threading.main_thread()
    names = ("SIGINT", "SIGTERM", "SIGUSR1")
    handlers = {getattr(signal, n): signal.getsignal(getattr(signal, n)) for n in names if hasattr(signal, n)}
    os.environ[TUNE_SIGINT_SWITCH] = "1"
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(TUNE_SIGINT_SWITCH, None)
        else:
            os.environ[TUNE_SIGINT_SWITCH] = previous
        for sig, handler in handlers.items() if main else ():
            if handler is not None:
                signal.signal(sig, handler)


def _raise_on_sigterm() -> None:
    """SIGTERM raises KeyboardInterrupt (as in the CLI), replacing Ray's handler (main thread only)."""
    import signal
    import threading

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, handler)


def _run_on_tune(
    specs: list[dict[str, Any]], out_dir: Path, address: str | None, progress: bool
) -> list[dict[str, Any]]:
    with _interrupts_raise(), ray_session(address):
        _raise_on_sigterm()
        from ray import tune

        tuner = tune.Tuner(
            tune.with_resources(_tune_trial, {"cpu": 1}),
            param_space={"trial": tune.grid_search(specs)},
            run_config=tune.RunConfig(name="sweep", storage_path=str(out_dir / "tune"), verbose=1 if progress else 0),
        )
        with contextlib.redirect_stdout(sys.stderr):  # Tune's tables never mix into --json output
            grid = tuner.fit()
        rows = []
        unfinished = []
        for res in (grid[i] for i in range(len(grid))):
            spec = (res.config or {})["trial"]
            if not res.error and "timesteps" not in (res.metrics or {}):
                unfinished.append(spec["name"])  # stopped by Tune before it reported (an interrupt)
                continue
            row: dict[str, Any] = {
                "name": spec["name"],
                "seed": spec["seed"],
                "config": spec["point"],
                "status": "ERROR" if res.error else "TERMINATED",
            }
            if res.error:
                row["error"] = f"{type(res.error).__name__}: {res.error}"
            else:
                metrics = res.metrics or {}
                row.update({k: metrics.get(k) for k in (*METRICS, "timesteps", "train_wall_s", "trial_wall_s")})
            rows.append(row)
    if unfinished:
        raise SweepInterrupted(
            f"the sweep was stopped before {len(unfinished)} of {len(specs)} trials finished "
            f"({', '.join(unfinished[:3])}{', ...' if len(unfinished) > 3 else ''}); nothing of it is kept"
        )
    order = {s["name"]: i for i, s in enumerate(specs)}
    return sorted(rows, key=lambda r: order[r["name"]])


def _summarise(
    rows: list[dict[str, Any]],
    points: list[dict[str, Any]],
    seeds: Sequence[int],
    timesteps: int,
    eval_episodes: int,
    eval_seed: int,
    wall_s: float,
) -> dict[str, Any]:
    import numpy as np

    per_point = []
    for point in points:
        done = [r for r in rows if r["config"] == point and r["status"] == "TERMINATED"]
        done = [r for r in done if r.get("mean_utility_gain") is not None]
        gains = np.array([r["mean_utility_gain"] for r in done], dtype=float)
        per_point.append(
            {
                "config": point,
                "label": _label(point),
                "trials": len(done),
                "mean_utility_gain": float(gains.mean()) if done else None,
                "std_utility_gain": float(gains.std(ddof=1)) if len(done) > 1 else None,
            }
        )
    return {
        "trials": rows,
        "points": per_point,
        "seeds": list(seeds),
        "timesteps": timesteps,
        "eval_episodes": eval_episodes,
        "eval_seed": eval_seed,
        "wall_s": wall_s,
    }


def _write(out_dir: Path, result: dict[str, Any]) -> None:
    rows = result["trials"]
    fields = ["name", "seed", "config", "status", *METRICS, "timesteps", "train_wall_s", "trial_wall_s", "error"]

    def write_csv(tmp: Path) -> None:
        with tmp.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields, extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({**r, "config": _label(r["config"])})

    atomic_write(out_dir / "trials.csv", write_csv)
    write_json(out_dir / "results.json", result)
    from cv2x_marl.plotting import plot_sweep

    plot_sweep(result, out_dir / "sweep.png")
