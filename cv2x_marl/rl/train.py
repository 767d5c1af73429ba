"""PPO movers with parameter sharing (`cv2x-marl train`).

A run folder holds ``train_config.json`` (the resolved configuration), ``checkpoints/``
(``ppo_<steps>_steps.zip`` every ``checkpoint_every`` steps), ``tb/`` (tensorboard),
``eval.csv`` (the learning curve: PPO and GBMU on fixed evaluation episodes), ``model.zip`` and
``record.json`` (timesteps, wall time, throughput, final evaluation) once training ends, and
``run.json`` (:mod:`cv2x_marl.runs`: status, arguments of every segment, file checksums). The
final state, and the state at an interrupt, are also saved as checkpoints.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import as_real, is_int
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.rl.errors import TrainError

ENV_IDS = (
    "cv2x/SingleMover-v0",
    "cv2x/Mobility-v0",
    "cv2x/SingleMover-v1",
    "cv2x/Mobility-v1",
    "cv2x/SingleMover-v2",
    "cv2x/Mobility-v2",
)


@dataclass(frozen=True)
class PpoConfig:
    """PPO hyperparameters (stable-baselines3 names)."""

    learning_rate: float = 3e-4
    n_steps: int = 64
    batch_size: int = 512
    n_epochs: int = 10
    gamma: float = 0.95
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    net_arch: tuple[int, ...] = (128, 128)
    #: initial log standard deviation of the Gaussian actions (SB3's default 0: std 1)
    log_std_init: float = 0.0

    def __post_init__(self) -> None:
        """Type and range checks; a numeric string (YAML 1.1 reads ``3e-4`` as one) becomes a number."""
        reals = {
            "learning_rate": (lambda v: v > 0, "a number > 0"),
            "gamma": (lambda v: 0 < v <= 1, "a number in (0, 1]"),
            "gae_lambda": (lambda v: 0 <= v <= 1, "a number in [0, 1]"),
            "clip_range": (lambda v: v > 0, "a number > 0"),
            "ent_coef": (lambda v: v >= 0, "a number >= 0"),
            "vf_coef": (lambda v: v >= 0, "a number >= 0"),
            "max_grad_norm": (lambda v: v > 0, "a number > 0"),
            "log_std_init": (lambda v: True, "a finite number"),
        }
        for name, (ok, allowed) in reals.items():
            value = as_real(getattr(self, name))
            if value is None or not ok(value):
                raise TrainError(f"ppo.{name} must be {allowed}, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        for name in ("n_steps", "batch_size", "n_epochs"):
            object.__setattr__(self, name, _check_count(f"ppo.{name}", getattr(self, name)))
        arch = self.net_arch
        if not isinstance(arch, tuple | list) or not arch or not all(is_int(a) and a >= 1 for a in arch):
            raise TrainError(f"ppo.net_arch must be a non-empty list of integers >= 1, got {arch!r}")
        object.__setattr__(self, "net_arch", tuple(int(a) for a in arch))


def _check_count(name: str, value: Any) -> int:
    """``value`` as an int >= 1; a whole float (YAML's ``1e4``) counts, ``1.5`` and bools do not."""
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    if not is_int(value) or value < 1:
        raise TrainError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a run needs besides timesteps and seed."""

    env_id: str = "cv2x/SingleMover-v0"
    copies: int = 8
    env: dict[str, Any] = field(
        default_factory=lambda: {"max_cycles": 100, "max_step_m": 5.0, "normalise_reward": True}
    )
    ppo: PpoConfig = field(default_factory=PpoConfig)
    checkpoint_every: int = 50_000
    eval_every: int = 50_000
    eval_episodes: int = 16
    eval_seed: int = 10_000
    #: None: every training episode from a fresh seed; N: from N seeds, their starts cached
    start_pool: int | None = None

    def __post_init__(self) -> None:
        if self.env_id not in ENV_IDS:
            raise TrainError(f"env_id {self.env_id!r} unknown; ids: {', '.join(ENV_IDS)}")
        for name in ("copies", "checkpoint_every", "eval_every", "eval_episodes"):
            object.__setattr__(self, name, _check_count(f"train.{name}", getattr(self, name)))
        if not is_int(self.eval_seed) or self.eval_seed < 0:
            raise TrainError(f"train.eval_seed must be an integer >= 0, got {self.eval_seed!r}")
        if not isinstance(self.env, dict):
            raise TrainError(f"train.env must be a mapping of env arguments, got {self.env!r}")
        if self.start_pool is not None:
            object.__setattr__(self, "start_pool", _check_count("train.start_pool", self.start_pool))

    def env_for_training(self) -> dict[str, Any]:
        """The env arguments of training and its evaluation callbacks: ``env`` plus, with a start
        pool, a reset cache that holds the pool and the evaluation episodes (bit-identical starts)."""
        if self.start_pool is None:
            return dict(self.env)
        return {**self.env, "reset_cache": self.start_pool + self.eval_episodes}

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["ppo"]["net_arch"] = list(self.ppo.net_arch)
        return d


#: what a run folder's ``train_config.json`` holds besides the configuration
RUN_KEYS = ("seed", "timesteps")


def run_settings(path: Path | None) -> dict[str, int]:
    """The ``seed`` and ``timesteps`` a training file names (a run folder's ``train_config.json``
    does), checked; empty for a plain configuration. ``cv2x-marl train --config FILE`` uses them
    when ``--seed`` / ``--timesteps`` are not given, so a shipped run can be trained again as it was."""
    from cv2x_marl.yamlcore import load_mapping

    if path is None:
        return {}
    data = load_mapping(path, "training config", TrainError)
    out: dict[str, int] = {}
    for key, low in (("seed", 0), ("timesteps", 1)):
        if key in data:
            value = data[key]
            if not is_int(value) or value < low:
                raise TrainError(f"{path}: {key} must be an integer >= {low}, got {value!r}")
            out[key] = int(value)
    return out


def load_train_config(path: Path | None, env_id: str | None = None, copies: int | None = None) -> TrainConfig:
    """Read a YAML/JSON file ``{env_id, copies, env: {...}, ppo: {...}, checkpoint_every, ...}``.

    Unknown keys raise :class:`TrainError` naming them; CLI values override the file. A run
    folder's ``train_config.json`` is a valid file: its ``seed`` and ``timesteps`` (the run's, see
    :func:`run_settings`) are not part of the configuration and are skipped here.
    """
    from cv2x_marl.yamlcore import load_mapping

    data = {} if path is None else load_mapping(path, "training config", TrainError)
    for key in RUN_KEYS:
        data.pop(key, None)
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    bad = sorted(set(data) - known)
    if bad:
        raise TrainError(f"unknown training config key(s) {bad}; keys: {', '.join(sorted(known))}")
    ppo_raw = data.pop("ppo", {}) or {}
    if not isinstance(ppo_raw, dict):
        raise TrainError(f"train.ppo must be a mapping of PPO settings, got {ppo_raw!r}")
    ppo_data = dict(ppo_raw)
    ppo_known = {f.name for f in dataclasses.fields(PpoConfig)}
    bad = sorted(set(ppo_data) - ppo_known)
    if bad:
        raise TrainError(f"unknown ppo key(s) {bad}; keys: {', '.join(sorted(ppo_known))}")
    if "net_arch" in ppo_data and isinstance(ppo_data["net_arch"], list | tuple):
        ppo_data["net_arch"] = tuple(ppo_data["net_arch"])
    defaults = TrainConfig()
    env_data = data.pop("env", {}) or {}
    if not isinstance(env_data, dict):
        raise TrainError(f"train.env must be a mapping of env arguments, got {env_data!r}")
    env = {**defaults.env, **env_data}
    cfg = TrainConfig(**{**data, "env": env, "ppo": PpoConfig(**ppo_data)})
    if env_id is not None:
        cfg = dataclasses.replace(cfg, env_id=env_id)
    if copies is not None:
        cfg = dataclasses.replace(cfg, copies=copies)
    return cfg


def make_ppo(vec: Any, p: PpoConfig, seed: int, tensorboard_log: str | None = None) -> Any:
    """A fresh SB3 PPO (MLP policy, CPU) with the hyperparameters of ``p`` on the VecEnv ``vec``."""
    from stable_baselines3 import PPO

    return PPO(
        "MlpPolicy",
        vec,
        learning_rate=p.learning_rate,
        n_steps=p.n_steps,
        batch_size=p.batch_size,
        n_epochs=p.n_epochs,
        gamma=p.gamma,
        gae_lambda=p.gae_lambda,
        clip_range=p.clip_range,
        ent_coef=p.ent_coef,
        vf_coef=p.vf_coef,
        max_grad_norm=p.max_grad_norm,
        policy_kwargs={"net_arch": list(p.net_arch), "log_std_init": p.log_std_init},
        tensorboard_log=tensorboard_log,
        seed=seed,
        device="cpu",
        verbose=0,
    )


def make_vec_env(cfg: TrainConfig) -> Any:
    """The agents x copies VecEnv of a training configuration."""
    from cv2x_marl.experiments.evaluate import make_eval_env
    from cv2x_marl.rl.vec_env import AgentsVecEnv

    env = cfg.env_for_training()
    return AgentsVecEnv(lambda: make_eval_env(cfg.env_id, **env), cfg.copies, start_pool=cfg.start_pool)


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The checkpoint with the most steps in ``run_dir/checkpoints`` (None when there is none)."""
    ckpts = list((Path(run_dir) / "checkpoints").glob("ppo_*_steps.zip"))
    if not ckpts:
        return None
    return max(ckpts, key=lambda p: int(p.stem.split("_")[1]))


def save_model(model: Any, path: Path) -> Path:
    """Save an SB3 model atomically (SB3 keeps a non-empty suffix such as ``.tmp`` as given)."""
    return atomic_write(path, lambda tmp: model.save(tmp))


class _StopRequest:
    """SIGINT/SIGTERM during training: the first signal asks training to stop at the next step
    (a checkpoint is then saved); a second one interrupts at once."""

    def __init__(self) -> None:
        self.signal: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _StopRequest:
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():  # handlers only work there
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signal is not None:
            raise KeyboardInterrupt
        self.signal = signum

    def __exit__(self, *exc: object) -> None:
        import signal

        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped on SIGINT/SIGTERM after saving a checkpoint (``--resume`` continues)."""


def _callbacks(
    cfg: TrainConfig, run_dir: Path, n_envs: int, total: int, progress: bool, stop: _StopRequest
) -> list[Any]:
    from stable_baselines3.common.callbacks import BaseCallback

    from cv2x_marl.experiments.evaluate import PpoPolicy, evaluate

    class Checkpoint(BaseCallback):
        """Atomic checkpoints every ``checkpoint_every`` steps (a crash never leaves a half file)."""

        def _on_training_start(self) -> None:  # after a resume restored num_timesteps
            self.next = (self.num_timesteps // cfg.checkpoint_every + 1) * cfg.checkpoint_every

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                save_model(self.model, checkpoint_path(run_dir, self.num_timesteps))
                self.next = (self.num_timesteps // cfg.checkpoint_every + 1) * cfg.checkpoint_every
            return True

    class EvalVsGbmu(BaseCallback):
        """Evaluate PPO (deterministic) and GBMU on the same fixed episodes; write eval.csv."""

        def __init__(self) -> None:
            super().__init__()
            self.gbmu: dict[str, Any] | None = None
            self.next = 0

        def _eval(self, policy: Any, env: dict[str, Any]) -> dict[str, Any]:
            return evaluate(cfg.env_id, policy, cfg.eval_episodes, cfg.eval_seed, None, env, progress=False)

        def _on_training_start(self) -> None:
            # GBMU acts with plain offsets, whatever action mode the learned mover trains with
            self.gbmu = self._eval("gbmu", {**cfg.env_for_training(), "action_mode": "offset"})
            done = [int(r["timesteps"]) for r in read_eval_rows(run_dir / "eval.csv")]
            self.next = max(done) + cfg.eval_every if done else self.num_timesteps

        def _on_step(self) -> bool:
            if self.num_timesteps >= self.next:
                self.next = self.num_timesteps + cfg.eval_every
                res = self._eval(PpoPolicy(self.model), cfg.env_for_training())
                assert self.gbmu is not None
                row = {
                    "timesteps": self.num_timesteps,
                    "ppo_mean_utility_gain": res["mean_utility_gain"],
                    "ppo_effectiveness": res["effectiveness"],
                    "ppo_mean_prr_gain": res["mean_prr_gain"],
                    "ppo_mean_return": res["mean_return"],
                    "gbmu_mean_utility_gain": self.gbmu["mean_utility_gain"],
                    "gbmu_effectiveness": self.gbmu["effectiveness"],
                    "gbmu_mean_prr_gain": self.gbmu["mean_prr_gain"],
                }
                for k, v in row.items():
                    if k != "timesteps":
                        self.logger.record(f"eval/{k}", v)
                write_eval_rows(run_dir / "eval.csv", [*read_eval_rows(run_dir / "eval.csv"), row])
            return True

    class StopOnSignal(BaseCallback):
        def _on_step(self) -> bool:
            return stop.signal is None  # False ends model.learn() cleanly

    class Progress(BaseCallback):
        def _on_training_start(self) -> None:
            from tqdm import tqdm

            self.bar = tqdm(
                total=total,
                initial=self.num_timesteps,
                unit="step",
                desc="train",
                file=sys.stderr,
                disable=not progress,
            )

        def _on_step(self) -> bool:
            self.bar.update(n_envs)
            return True

        def _on_training_end(self) -> None:
            self.bar.close()

    return [Checkpoint(), EvalVsGbmu(), StopOnSignal(), Progress()]


def checkpoint_path(run_dir: Path, steps: int) -> Path:
    """``run_dir/checkpoints/ppo_<steps>_steps.zip``."""
    return Path(run_dir) / "checkpoints" / f"ppo_{int(steps)}_steps.zip"


def read_eval_rows(path: Path) -> list[dict[str, str]]:
    """The rows of a learning curve ``eval.csv`` (empty when there is none)."""
    if not path.exists():
        return []
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def write_eval_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """Rewrite ``eval.csv`` atomically (a crash leaves the previous version, never a torn row)."""
    if not rows:
        path.unlink(missing_ok=True)
        return

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)

    atomic_write(path, write)


def train(
    cfg: TrainConfig,
    timesteps: int,
    seed: int,
    run_dir: Path,
    resume: bool = False,
    progress: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Train (or resume) a shared PPO policy; write the run folder; return the training record.

    The run folder (:class:`cv2x_marl.runs.RunFolder`) is locked while training and keeps its
    checkpoints if training fails. SIGINT/SIGTERM stop training at the next step, save a
    checkpoint and raise :class:`TrainingInterrupted` (``resume=True`` continues). With
    ``resume`` training continues from the newest checkpoint, and ``eval.csv`` is cut back to it.

    Raises:
        TrainError: bad arguments, a resume whose configuration differs, or a run that already
            has ``timesteps`` steps.
        cv2x_marl.runs.RunFolderError: the folder is in use, not empty (without ``overwrite`` or
            ``resume``) or not writable.
    """
    from cv2x_marl.extras import require
    from cv2x_marl.runs import RunFolder

    require("torch", "cv2x-marl train")
    require("stable_baselines3", "cv2x-marl train")
    if not is_int(timesteps) or timesteps < 1:
        raise TrainError(f"--timesteps must be an integer >= 1, got {timesteps!r}")
    run_dir = Path(run_dir)
    resolved = {**cfg.to_dict(), "seed": seed, "timesteps": timesteps}
    if resume:
        cfg_path = run_dir / "train_config.json"
        if not cfg_path.exists():
            raise TrainError(f"--resume: {run_dir} has no train_config.json (nothing to resume)")
        old = json.loads(cfg_path.read_text())
        if {k: v for k, v in old.items() if k != "timesteps"} != {
            k: v for k, v in resolved.items() if k != "timesteps"
        }:
            raise TrainError(f"--resume: the configuration or seed differs from the one in {cfg_path}")
        ckpt = latest_checkpoint(run_dir)
        done = int(ckpt.stem.split("_")[1]) if ckpt is not None else 0
        if done >= timesteps:
            raise TrainError(
                f"--resume: {run_dir} already has {done} steps (>= --timesteps {timesteps}); "
                "ask for more steps to continue it (its model.zip is kept as it is)"
            )
    params = {"env_id": cfg.env_id, "seed": seed, "timesteps": timesteps}
    with RunFolder(run_dir, "train", overwrite=overwrite, resume=resume, keep_on_failure=True, parameters=params):
        return _train(cfg, timesteps, seed, run_dir, resolved, resume, progress)


def _train(
    cfg: TrainConfig,
    timesteps: int,
    seed: int,
    run_dir: Path,
    resolved: dict[str, Any],
    resume: bool,
    progress: bool,
) -> dict[str, Any]:
    import torch
    from stable_baselines3 import PPO

    write_json(run_dir / "train_config.json", resolved)
    vec = make_vec_env(cfg)
    torch.set_num_threads(1)
    ckpt = latest_checkpoint(run_dir) if resume else None
    if ckpt is not None:
        model = PPO.load(str(ckpt), env=vec, device="cpu", tensorboard_log=str(run_dir / "tb"))
        model.set_random_seed(seed + model.num_timesteps)
        # the learning curve goes back to the checkpoint: rows of a discarded segment are dropped
        rows = read_eval_rows(run_dir / "eval.csv")
        write_eval_rows(run_dir / "eval.csv", [r for r in rows if int(r["timesteps"]) <= model.num_timesteps])
    else:
        model = make_ppo(vec, cfg.ppo, seed, str(run_dir / "tb"))
    start = model.num_timesteps
    remaining = max(0, timesteps - start)
    t0 = time.perf_counter()
    with _StopRequest() as stop:
        model.learn(
            remaining,
            callback=_callbacks(cfg, run_dir, vec.num_envs, timesteps, progress, stop),
            reset_num_timesteps=ckpt is None,
            tb_log_name="ppo",
        )
        wall = time.perf_counter() - t0
        # the final state is a checkpoint too: short runs and interrupted runs can be resumed
        save_model(model, checkpoint_path(run_dir, model.num_timesteps))
        if stop.signal is not None:
            vec.close()
            raise TrainingInterrupted(
                f"training stopped at {model.num_timesteps} steps; checkpoint saved in {run_dir / 'checkpoints'} "
                "(continue with --resume)"
            )
    save_model(model, run_dir / "model.zip")
    from cv2x_marl.experiments.evaluate import PpoPolicy, evaluate

    final = evaluate(cfg.env_id, PpoPolicy(model), cfg.eval_episodes, cfg.eval_seed, None, cfg.env, progress=False)
    record = {
        "env_id": cfg.env_id,
        "seed": seed,
        "timesteps": int(model.num_timesteps),
        "resumed_from": int(start) if ckpt is not None else None,
        "wall_s": wall,
        "steps_per_s": (model.num_timesteps - start) / wall if wall > 0 else float("nan"),
        "n_sub_envs": vec.num_envs,
        "final_eval": {
            k: final[k] for k in ("mean_utility_gain", "effectiveness", "mean_prr_gain", "jain_fairness", "mean_return")
        },
        "torch": torch.__version__,
    }
    write_json(run_dir / "record.json", record)
    vec.close()
    return record


def parameters_digest(model: Any) -> str:
    """A short hash of a model's policy parameters (to compare two runs)."""
    import hashlib

    h = hashlib.sha256()
    for _, v in sorted(model.policy.state_dict().items()):
        h.update(np.ascontiguousarray(v.cpu().numpy()).tobytes())
    return h.hexdigest()[:16]
