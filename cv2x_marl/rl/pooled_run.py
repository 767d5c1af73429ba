"""What the trainers that collect whole episodes from the start pool share (the utility map, imitation): their
configuration's common checks, the loop of rounds with its learning curve, the run folder around a run, and the
CLI's seed and budget."""

from __future__ import annotations

import csv
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cv2x_marl.io import write_json
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.mappo_config import count_at_least
from cv2x_marl.rl.train_config import MAX_COPIES, check_pooled_env, run_settings


def check_pooled_run(cfg: Any, algo: str, env_ids: tuple[str, ...], trainer: str) -> None:
    """Check the fields every pooled-run config has (``algo``, ``env_id``, ``copies``, ``env``, ``eval_every``,
    ``eval_episodes``), each error naming the key and the allowed values; counts are stored back as ints.

    Args:
        cfg: a frozen dataclass with those fields (checked in its ``__post_init__``).
        algo: the value ``algo`` must have; env_ids: the ids the trainer trains on; trainer: its name in errors.

    Raises:
        TrainError: the first bad field.
    """
    if cfg.algo != algo:
        raise TrainError(f"algo must be {algo!r} in a config of {trainer}, got {cfg.algo!r}")
    if cfg.env_id not in env_ids:
        raise TrainError(f"env_id {cfg.env_id!r}: {trainer} trains on {', '.join(env_ids)}")
    for name in ("copies", "eval_every", "eval_episodes"):
        object.__setattr__(cfg, name, count_at_least(f"train.{name}", getattr(cfg, name)))
    if cfg.copies > MAX_COPIES:
        raise TrainError(f"train.copies must be an integer in [1, {MAX_COPIES:,}], got {cfg.copies}")
    check_pooled_env(cfg.env_id, cfg.env, trainer)


def train_in_folder(
    run: Any, resolved: dict[str, Any], timesteps: int, seed: int, run_dir: Path, progress: bool, overwrite: bool
) -> dict[str, Any]:
    """Run ``run.train(timesteps, run_dir, progress)`` inside a :class:`~cv2x_marl.runs.RunFolder` (refused when
    in use or not empty without ``overwrite``; a failed run leaves the previous one as it was), writing
    ``train_config.json`` (``resolved``) before and ``record.json`` after; ``run.close()`` in every case."""
    from cv2x_marl.runs import RunFolder

    try:
        params = {"env_id": resolved["env_id"], "seed": seed, "timesteps": timesteps, "algo": resolved["algo"]}
        with RunFolder(run_dir, "train", overwrite=overwrite, parameters=params):
            write_json(Path(run_dir) / "train_config.json", resolved)
            record: dict[str, Any] = run.train(timesteps, Path(run_dir), progress)
            write_json(Path(run_dir) / "record.json", record)
            return record
    finally:
        run.close()


def cli_budget(args: Any, default_timesteps: int, what: str) -> tuple[int, int]:
    """``cv2x-marl train``'s ``--timesteps`` and ``--seed`` for a pooled run, else the ``--config`` file's (a run
    folder's ``train_config.json`` names them), else the defaults; ``--resume`` is refused (``what``: the run's
    name)."""
    if args.resume:
        raise TrainError(f"--resume: {what} run is not checkpointed (it takes minutes); train it again")
    from_file = run_settings(args.config)
    timesteps = args.timesteps if args.timesteps is not None else from_file.get("timesteps", default_timesteps)
    seed = args.seed if args.seed is not None else from_file.get("seed", 0)
    return int(timesteps), int(seed)


def train_rounds(
    iterations: int,
    agent_steps: int,
    round_fn: Callable[[int], float],
    evaluate_fn: Callable[[], dict[str, Any]],
    eval_every: int,
    progress: str | None,
) -> tuple[list[dict[str, Any]], float]:
    """Run ``iterations`` rounds, ``round_fn(it)`` each (collect and fit; it returns the fit's loss), and
    ``evaluate_fn()`` every ``eval_every`` rounds and after the last.

    Args:
        iterations: rounds; agent_steps: agent-steps of one round (for the curve).
        round_fn, evaluate_fn: one round; an evaluation (its ``mean_utility_gain`` is the curve's gain).
        eval_every: rounds between two evaluations.
        progress: the progress bar's name (None: no bar).

    Returns:
        The curve's rows (``iteration``, ``agent_steps``, ``cpu_s``: process CPU seconds since the first round,
        ``fit_loss``, ``eval_utility_gain``: empty without an evaluation) and the wall seconds.
    """
    rows: list[dict[str, Any]] = []
    cpu0, wall0 = time.process_time(), time.perf_counter()
    bar = None
    if progress is not None:
        from tqdm import tqdm

        bar = tqdm(total=iterations, desc=progress, unit="round")
    for it in range(iterations):
        loss = round_fn(it)
        row: dict[str, Any] = {
            "iteration": it + 1,
            "agent_steps": (it + 1) * agent_steps,
            "cpu_s": round(time.process_time() - cpu0, 3),
            "fit_loss": loss,
            "eval_utility_gain": "",
        }
        if (it + 1) % eval_every == 0 or it + 1 == iterations:
            row["eval_utility_gain"] = evaluate_fn()["mean_utility_gain"]
        rows.append(row)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.4f}", gain=row["eval_utility_gain"] or "-")
    if bar is not None:
        bar.close()
    return rows, round(time.perf_counter() - wall0, 3)


def round_record(
    algo: str, env_id: str, seed: int, agent_steps: int, rows: list[dict[str, Any]], wall_s: float
) -> dict[str, Any]:
    """The ``record.json`` entries every pooled run has, from its curve ``rows`` (:func:`train_rounds`)."""
    last = rows[-1]
    return {
        "algo": algo,
        "env_id": env_id,
        "seed": seed,
        "timesteps": len(rows) * agent_steps,
        "iterations": len(rows),
        "cpu_s": last["cpu_s"],
        "wall_s": wall_s,
        "final_eval_utility_gain": last["eval_utility_gain"],
        "final_fit_loss": last["fit_loss"],
    }


def write_curve(run_dir: Path, rows: list[dict[str, Any]], title: str) -> None:
    """``curve.csv`` (one row per round) and ``curve.png`` (utility gain against CPU seconds, when matplotlib is
    installed) of a pooled run."""
    with open(run_dir / "curve.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    try:
        from cv2x_marl import plotting

        plotting.plot_gain_vs_cpu({"run": rows}, run_dir / "curve.png", title)
    except ImportError:  # the figure needs matplotlib; the CSV is the data
        return
