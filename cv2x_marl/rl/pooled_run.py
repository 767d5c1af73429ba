"""What the trainers that collect whole episodes from the start pool share (the utility map, imitation): their
configuration's common checks, the run folder around a run, and the CLI's seed and budget."""

from __future__ import annotations

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
