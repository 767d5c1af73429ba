"""PPO movers with parameter sharing (`cv2x-marl train`).

A run folder holds ``train_config.json`` (the resolved configuration), ``checkpoints/``
(``ppo_<steps>_steps.zip`` every ``checkpoint_every`` steps), ``tb/`` (tensorboard),
``eval.csv`` (the learning curve: PPO and GBMU on fixed evaluation episodes), ``model.zip`` and
``record.json`` (timesteps, wall time, throughput, final evaluation) once training ends, and
``run.json`` (:mod:`cv2x_marl.runs`: status, arguments of every segment, file checksums). The
final state, and the state at an interrupt, are also saved as checkpoints. What is checked of a configuration
before training (an env copy, SB3's size rule, the memory estimate) is :mod:`cv2x_marl.rl.train_checks`'
(re-exported here).
"""

from __future__ import annotations

import csv
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.checks import is_int
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.extras import require
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.ppo import PpoPolicy
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train_checks import (  # noqa: F401 - re-exported: train's names before the split
    check_training_config,
    check_training_memory,
    estimate_training_memory,
    probe_env,
)
from cv2x_marl.rl.train_config import (  # noqa: F401 - re-exported: the configuration's home is train_config
    _COPY_OVERHEAD_BYTES,
    ENCODERS,
    MAX_COPIES,
    MAX_LAYER_UNITS,
    RUN_KEYS,
    PpoConfig,
    TrainConfig,
    check_count,
    env_arguments,
    load_train_config,
    run_settings,
)
from cv2x_marl.runs import RunFolder


def make_ppo(vec: Any, p: PpoConfig, seed: int, tensorboard_log: str | None = None, layout: Any = None) -> Any:
    """A fresh SB3 PPO (MLP policy, CPU) with the hyperparameters of ``p`` on the VecEnv ``vec``; ``layout``:
    the env's :class:`~cv2x_marl.env.observation.ObservationLayout`, needed by ``p.encoder`` other than ``mlp``.
    ``p.recurrent``: sb3-contrib's ``RecurrentPPO`` with ``MlpLstmPolicy`` (an LSTM of ``p.lstm_units`` for the
    actor and one for the critic, after the features), the same hyperparameters."""
    from stable_baselines3 import PPO

    policy_kwargs: dict[str, Any] = {"net_arch": list(p.net_arch), "log_std_init": p.log_std_init}
    if p.encoder != "mlp":
        from cv2x_marl.policies.encoders import encoder_policy_kwargs

        policy_kwargs.update(encoder_policy_kwargs(p.encoder, p.encoder_units, layout))
    algo: Any = PPO
    policy = "MlpPolicy"
    if p.recurrent:
        algo = require("sb3_contrib", "ppo.recurrent (sb3-contrib's RecurrentPPO)").RecurrentPPO
        policy = "MlpLstmPolicy"
        policy_kwargs["lstm_hidden_size"] = p.lstm_units
    return algo(
        policy,
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
        policy_kwargs=policy_kwargs,
        tensorboard_log=tensorboard_log,
        seed=seed,
        device="cpu",
        verbose=0,
    )


def make_vec_env(cfg: TrainConfig) -> Any:
    """The agents x copies VecEnv of a training configuration."""
    from cv2x_marl.rl.sb3_vec_env import AgentsVecEnv

    env = cfg.env_for_training()
    return AgentsVecEnv(lambda: make_parallel_env(cfg.env_id, **env), cfg.copies, start_pool=cfg.start_pool)


def build_training(cfg: TrainConfig, seed: int, tensorboard_log: str | None = None) -> tuple[Any, Any]:
    """Check ``cfg`` (:func:`check_training_config`) and build its VecEnv and a fresh PPO model:
    everything that can fail on a bad configuration, done before a run folder is touched.

    Returns:
        ``(vec_env, model)``; the caller closes the VecEnv.

    Raises:
        TrainError: a bad configuration, naming the key.
    """
    check_training_config(cfg)
    try:
        vec = make_vec_env(cfg)
    except (ValueError, TypeError) as exc:
        raise TrainError(f"train.env of {cfg.env_id}: {exc}") from exc
    try:
        model = make_ppo(vec, cfg.ppo, seed, tensorboard_log, layout=vec.envs[0].layout)
    except (AssertionError, ValueError, TypeError) as exc:
        vec.close()
        raise TrainError(f"train.ppo: stable-baselines3 refuses the PPO settings: {exc}") from exc
    except BaseException:
        vec.close()
        raise
    return vec, model


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The checkpoint with the most steps in ``run_dir/checkpoints`` (None when there is none)."""
    ckpts = list((Path(run_dir) / "checkpoints").glob("ppo_*_steps.zip"))
    if not ckpts:
        return None
    return max(ckpts, key=lambda p: int(p.stem.split("_")[1]))


def save_model(model: Any, path: Path) -> Path:
    """Save an SB3 model atomically (SB3 keeps a non-empty suffix such as ``.tmp`` as given)."""
    return atomic_write(path, lambda tmp: model.save(tmp))


class StopRequest:
    """SIGINT/SIGTERM during training: the first signal asks training to stop at the next step
    (a checkpoint is then saved); a second one interrupts at once."""

    def __init__(self) -> None:
        self.signal: int | None = None
        #: steps the policy has been updated on: the count when the current rollout started
        self.trained_steps = 0
        #: whether the signal cut a rollout short (its steps were collected but never trained on)
        self.cut = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopRequest:
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
    cfg: TrainConfig, run_dir: Path, n_envs: int, total: int, progress: bool, stop: StopRequest
) -> list[Any]:
    from stable_baselines3.common.callbacks import BaseCallback

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
            # GBMU acts with plain offsets (and target speeds on a road), whatever actions the learned mover has
            env = {**cfg.env_for_training(), "action_mode": "offset"}
            if env.get("speed_command", "target") != "target":
                env["speed_command"] = "target"
            self.gbmu = self._eval("gbmu", env)
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
        """Ends ``model.learn()`` cleanly at the next step after a signal, and keeps count of the
        steps trained on (a rollout is trained on once it is complete, before the next starts)."""

        def _on_training_start(self) -> None:
            stop.trained_steps = self.num_timesteps

        def _on_rollout_start(self) -> None:
            stop.trained_steps = self.num_timesteps

        def _on_step(self) -> bool:
            if stop.signal is None:
                return True
            stop.cut = True
            return False

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


def rollout_steps(cfg: TrainConfig, n_envs: int) -> int:
    """Agent-steps of one PPO rollout: ``ppo.n_steps`` x sub-envs. Training advances in whole
    rollouts, so every segment of a run (fresh or resumed) starts at a multiple of it."""
    return cfg.ppo.n_steps * n_envs


def trained_steps(steps: int, rollout: int) -> int:
    """The steps a checkpoint saved at ``steps`` was trained on: back to the start of its rollout
    (a checkpoint written during a rollout, or at an interrupt, holds the policy of the last update;
    the steps collected since were never trained on and are collected again on resume)."""
    return int(steps) - int(steps) % int(rollout)


def check_resume_config(run_dir: Path, resolved: dict[str, Any]) -> None:
    """Refuse ``--resume`` on a folder without ``train_config.json`` or whose configuration or seed differs from
    ``resolved`` (the timesteps may differ: a resume may ask for more), before the folder is touched."""
    cfg_path = Path(run_dir) / "train_config.json"
    if not cfg_path.exists():
        raise TrainError(f"--resume: {run_dir} has no train_config.json (nothing to resume)")
    try:
        old = json.loads(cfg_path.read_text())
    except (OSError, ValueError) as exc:
        raise TrainError(f"--resume: cannot read {cfg_path}: {exc}") from exc
    if not isinstance(old, dict) or {k: v for k, v in old.items() if k != "timesteps"} != {
        k: v for k, v in resolved.items() if k != "timesteps"
    }:
        raise TrainError(f"--resume: the configuration or seed differs from the one in {cfg_path}")


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

    Everything a bad configuration can break (the env arguments, SB3's rules, the memory
    estimate, building the VecEnv and the PPO model: :func:`build_training`) runs before the run
    folder is touched, so a refused run leaves ``run_dir`` as it was. The run folder
    (:class:`cv2x_marl.runs.RunFolder`) is locked while training and keeps its checkpoints if
    training fails. SIGINT/SIGTERM stop training at the next step, save a checkpoint of the steps
    trained on (the unfinished rollout is not counted) and raise :class:`TrainingInterrupted`
    (``resume=True`` continues). With ``resume`` training continues from the newest checkpoint, at
    the steps it was trained on (:func:`trained_steps`), and ``eval.csv`` is cut back to them: the
    step count, the evaluation rows and the checkpoint names then equal those of an uninterrupted run.

    Raises:
        TrainError: bad arguments or configuration, a resume whose configuration differs, or a
            run that already has ``timesteps`` steps.
        cv2x_marl.runs.RunFolderError: the folder is in use, not empty (without ``overwrite`` or
            ``resume``) or not writable.
    """
    if cfg.ppo.backend == "torchrl":  # TorchRL's loss over the batched vector env (docs/rl.md)
        from cv2x_marl.rl.fast_ppo import train_fast

        return train_fast(cfg, timesteps, seed, run_dir, resume=resume, progress=progress, overwrite=overwrite)
    require("torch", "cv2x-marl train")
    require("stable_baselines3", "cv2x-marl train")
    if not is_int(timesteps) or timesteps < 1:
        raise TrainError(f"--timesteps must be an integer >= 1, got {timesteps!r}")
    run_dir = Path(run_dir)
    resolved = {**cfg.to_dict(), "seed": seed, "timesteps": timesteps}
    if resume:
        check_resume_config(run_dir, resolved)
    import torch

    torch.set_num_threads(1)
    vec, model = build_training(cfg, seed, str(run_dir / "tb"))
    try:
        rollout = rollout_steps(cfg, vec.num_envs)
        if resume:
            ckpt = latest_checkpoint(run_dir)
            done = trained_steps(int(ckpt.stem.split("_")[1]), rollout) if ckpt is not None else 0
            if done >= timesteps:
                raise TrainError(
                    f"--resume: {run_dir} already has {done} steps (>= --timesteps {timesteps}); "
                    "ask for more steps to continue it (its model.zip is kept as it is)"
                )
        params = {"env_id": cfg.env_id, "seed": seed, "timesteps": timesteps}
        with RunFolder(run_dir, "train", overwrite=overwrite, resume=resume, keep_on_failure=True, parameters=params):
            return _train(cfg, timesteps, seed, run_dir, resolved, resume, progress, vec, model, rollout)
    finally:
        vec.close()


def _train(
    cfg: TrainConfig,
    timesteps: int,
    seed: int,
    run_dir: Path,
    resolved: dict[str, Any],
    resume: bool,
    progress: bool,
    vec: Any,
    model: Any,
    rollout: int,
) -> dict[str, Any]:
    import torch

    write_json(run_dir / "train_config.json", resolved)
    ckpt = latest_checkpoint(run_dir) if resume else None
    if ckpt is not None:
        model = type(model).load(str(ckpt), env=vec, device="cpu", tensorboard_log=str(run_dir / "tb"))
        # continue from the steps trained on: a checkpoint written during a rollout counts steps
        # that were collected but never trained on
        model.num_timesteps = trained_steps(model.num_timesteps, rollout)
        model.set_random_seed(seed + model.num_timesteps)
    if resume:  # the learning curve goes back to the checkpoint (to nothing without one): rows of a lost segment go
        _cut_back(run_dir, model.num_timesteps, checkpoints=False)
    start = model.num_timesteps
    remaining = max(0, timesteps - start)
    t0 = time.perf_counter()
    with StopRequest() as stop:
        model.learn(
            remaining,
            callback=_callbacks(cfg, run_dir, vec.num_envs, timesteps, progress, stop),
            reset_num_timesteps=ckpt is None,
            tb_log_name="ppo",
        )
        wall = time.perf_counter() - t0
        if stop.signal is not None and stop.cut:
            # the rollout the signal cut short was never trained on: not counted, so --resume
            # collects it again and ends where an uninterrupted run ends
            cut = model.num_timesteps - stop.trained_steps
            model.num_timesteps = stop.trained_steps
            _cut_back(run_dir, model.num_timesteps, checkpoints=True)
        # the final state is a checkpoint too: short runs and interrupted runs can be resumed
        save_model(model, checkpoint_path(run_dir, model.num_timesteps))
        if stop.signal is not None:
            not_counted = f" (the {cut} steps of the unfinished rollout are not counted)" if stop.cut else ""
            raise TrainingInterrupted(
                f"training stopped at {model.num_timesteps} steps{not_counted}; checkpoint saved in "
                f"{run_dir / 'checkpoints'} (continue with --resume)"
            )
    save_model(model, run_dir / "model.zip")

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
    return record


def _cut_back(run_dir: Path, steps: int, checkpoints: bool) -> None:
    """Drop the learning-curve rows (and with ``checkpoints`` the checkpoints) after ``steps``."""
    rows = read_eval_rows(run_dir / "eval.csv")
    kept = [r for r in rows if int(r["timesteps"]) <= steps]
    if len(kept) != len(rows):
        write_eval_rows(run_dir / "eval.csv", kept)
    if checkpoints:
        for path in (run_dir / "checkpoints").glob("ppo_*_steps.zip"):
            if int(path.stem.split("_")[1]) > steps:
                path.unlink()


def parameters_digest(model: Any) -> str:
    """A short hash of a model's policy parameters (to compare two runs)."""
    import hashlib

    h = hashlib.sha256()
    for _, v in sorted(model.policy.state_dict().items()):
        h.update(np.ascontiguousarray(v.cpu().numpy()).tobytes())
    return h.hexdigest()[:16]
