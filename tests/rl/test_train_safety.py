"""Training runs that never lose the previous run nor count what they did not train on (issue 25):
every training config checked before the run folder exists (defects 11, 12), `--overwrite` keeping
the previous run on a config error or a Ctrl-C (defect 2), resume after an interrupt ending where an
uninterrupted run ends (defect 6), and a full disk during training (defect 13)."""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import signal
from pathlib import Path
from typing import Any

import pytest

import cv2x_marl.rl.train as train_mod
from cv2x_marl.cli import main
from cv2x_marl.rl.train import (
    MAX_COPIES,
    PpoConfig,
    TrainConfig,
    TrainingInterrupted,
    read_eval_rows,
    train,
    trained_steps,
)
from cv2x_marl.runs import read_manifest, sha256_file

#: rollouts of 16 steps x 2 copies = 32 agent-steps; checkpoints and evaluations every 64
TINY = TrainConfig(
    env_id="cv2x/SingleMover-v0",
    copies=2,
    env={"max_cycles": 10, "normalise_reward": True, "overrides": ["sim.warmup_subframes=200"]},
    ppo=PpoConfig(n_steps=16, batch_size=32, n_epochs=1, net_arch=(16, 16)),
    checkpoint_every=64,
    eval_every=64,
    eval_episodes=1,
)


def _config_file(tmp_path: Path, cfg: TrainConfig = TINY, **changes: Any) -> Path:
    """A JSON training config: ``cfg`` with top-level changes and ``env`` / ``ppo`` entries merged."""
    data = cfg.to_dict()
    for key, value in changes.items():
        if key in ("env", "ppo"):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    path = tmp_path / "train.json"
    path.write_text(json.dumps(data))
    return path


def _checksums(folder: Path) -> dict[str, str]:
    return {p.relative_to(folder).as_posix(): sha256_file(p) for p in sorted(folder.rglob("*")) if p.is_file()}


def _ckpts(run: Path) -> list[int]:
    return sorted(int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("ppo_*_steps.zip"))


def _eval_steps(run: Path) -> list[int]:
    return [int(r["timesteps"]) for r in read_eval_rows(run / "eval.csv")]


def _previous_run(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    out = tmp_path / "out"
    argv = ["train", "--config", str(_config_file(tmp_path)), "--timesteps", "32", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    manifest = read_manifest(out)
    assert manifest is not None and manifest["status"] == "complete"
    return out, _checksums(out)


# -- defect 12 (and 11): every training config refused before a folder exists ---------------------


@pytest.mark.parametrize(
    ("changes", "named"),
    [
        ({"env": {"foo": 1}}, ["'foo'", "max_step_m", "normalise_reward"]),  # the allowed names listed
        ({"env": {"max_step_m": -5.0}}, ["max_step_m", "> 0"]),
        ({"ppo": {"batch_size": 1}}, ["ppo.batch_size", ">= 2"]),
        ({"ppo": {"net_arch": [1e9]}}, ["ppo.net_arch", "65,536"]),
        ({"ppo": {"net_arch": [1000000000]}}, ["ppo.net_arch", "65,536"]),
        ({"ppo": {"n_steps": 1e9}}, ["ppo.n_steps", "rollout buffer", "GB"]),
        ({"copies": 1e9}, ["train.copies", f"{MAX_COPIES:,}"]),
    ],
    ids=["unknown-env-argument", "env-value", "batch-size-1", "net-arch-1e9", "net-arch-int", "n-steps-1e9", "copies"],
)
def test_a_bad_training_config_is_refused_before_the_run_folder_exists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], changes: dict[str, Any], named: list[str]
) -> None:
    out = tmp_path / "out"
    config = _config_file(tmp_path, **changes)
    assert main(["train", "--config", str(config), "--timesteps", "64", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err  # one line
    for text in named:
        assert text in err
    assert not out.exists() and not list(tmp_path.glob(".out*"))  # no folder, no lock, nothing to block a rerun


def test_copies_beyond_the_cap_are_refused_before_the_run_folder_exists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`train --copies 100000` used to grow by 10-100 MB/s until killed."""
    out = tmp_path / "out"
    argv = ["train", "--config", str(_config_file(tmp_path)), "--copies", "100000", "--out", str(out), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "train.copies (--copies) must be an integer in [1, 4,096]" in err and "100000" in err
    assert not out.exists()


def test_the_memory_estimate_refuses_with_its_figures(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Copies within the cap that need more memory than the limit: refused with the estimate, the
    limit and the key of the largest component first."""
    from cv2x_marl.rl.errors import TrainError
    from cv2x_marl.rl.train import check_training_config, estimate_training_memory, probe_env

    cfg = dataclasses.replace(TINY, copies=MAX_COPIES)
    est = estimate_training_memory(cfg, probe_env(cfg))
    # paper preset: measured 0.33 MB per copy kept after a reset; the estimate is 0.42 MB
    assert 330_000 <= est["per_copy"] <= 500_000
    assert est["total"] > MAX_COPIES * est["per_copy"]
    monkeypatch.setenv("CV2X_MARL_MEMORY_LIMIT_GB", "1")
    with pytest.raises(TrainError, match=r"estimated 1\.\d+ GB of memory, more than the 1 GB allowed") as info:
        check_training_config(cfg)
    assert str(info.value).index("train.copies=4096") < str(info.value).index("ppo.net_arch")


# -- defect 2: --overwrite keeps the previous run until the new one completes ----------------------


def test_overwrite_with_a_config_error_keeps_the_previous_run_byte_for_byte(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, before = _previous_run(tmp_path)
    capsys.readouterr()
    bad = _config_file(tmp_path, env={"max_step_m": -5.0})
    assert main(["train", "--config", str(bad), "--timesteps", "32", "--out", str(out), "--overwrite", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "max_step_m" in err and "Traceback" not in err
    assert _checksums(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "train.json"]  # no .old, no lock left


def test_ctrl_c_early_in_an_overwrite_run_keeps_the_previous_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C once the new run's folder is entered and training has started (train_config.json and
    tb/ written): the previous complete run is still there, byte for byte. Needs the RunFolder
    that keeps the previous run aside until the new one completes (runs.py)."""
    from stable_baselines3.common.callbacks import BaseCallback

    out, before = _previous_run(tmp_path)
    original = train_mod._callbacks

    class CtrlC(BaseCallback):
        def _on_step(self) -> bool:
            raise KeyboardInterrupt

    monkeypatch.setattr(train_mod, "_callbacks", lambda *a, **k: [*original(*a, **k), CtrlC()])
    argv = ["train", "--config", str(_config_file(tmp_path)), "--timesteps", "64", "--out", str(out)]
    assert main([*argv, "--overwrite", "--quiet"]) == 130
    assert _checksums(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "train.json"]


# -- defect 6: resume after an interrupt ends where an uninterrupted run ends ----------------------


def _interrupt_at(monkeypatch: pytest.MonkeyPatch, steps: int) -> None:
    """Send this process SIGINT once training reaches ``steps`` agent-steps (as Ctrl-C would)."""
    from stable_baselines3.common.callbacks import BaseCallback

    original = train_mod._callbacks

    class SigintAt(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps == steps:
                os.kill(os.getpid(), signal.SIGINT)
            return True

    monkeypatch.setattr(train_mod, "_callbacks", lambda *a, **k: [*original(*a, **k), SigintAt()])


def test_resume_after_an_interrupt_ends_where_an_uninterrupted_run_ends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    whole = tmp_path / "whole"
    ref = train(TINY, 192, seed=3, run_dir=whole, progress=False)
    assert ref["timesteps"] == 192 and _ckpts(whole) == [64, 128, 192] and _eval_steps(whole) == [2, 66, 130]

    run = tmp_path / "run"
    _interrupt_at(monkeypatch, 74)  # 10 steps into the rollout that starts at 64 (the eval row at 66 written)
    with pytest.raises(TrainingInterrupted, match=r"stopped at 64 steps \(the \d+ steps of the unfinished rollout"):
        train(TINY, 192, seed=3, run_dir=run, progress=False)
    assert _ckpts(run) == [64] and _eval_steps(run) == [2]
    monkeypatch.undo()
    rec = train(TINY, 192, seed=3, run_dir=run, resume=True, progress=False)
    assert rec["resumed_from"] == 64 and rec["timesteps"] == 192  # was 202: 74 + 4 rollouts of 32
    assert _ckpts(run) == _ckpts(whole) and _eval_steps(run) == _eval_steps(whole)


def test_resume_from_a_checkpoint_written_during_a_rollout_ends_where_an_uninterrupted_run_ends(
    tmp_path: Path,
) -> None:
    """After SIGKILL the newest checkpoint can fall inside a rollout (every 48 steps, rollouts of 32):
    resume continues from the steps it was trained on."""
    cfg = dataclasses.replace(TINY, checkpoint_every=48)
    whole = tmp_path / "whole"
    train(cfg, 192, seed=3, run_dir=whole, progress=False)
    assert _ckpts(whole) == [48, 96, 144, 192]
    run = tmp_path / "run"
    train(cfg, 192, seed=3, run_dir=run, progress=False)
    for steps in (96, 144, 192):  # as if killed at step 50
        (run / "checkpoints" / f"ppo_{steps}_steps.zip").unlink()
    assert trained_steps(48, 32) == 32
    rec = train(cfg, 192, seed=3, run_dir=run, resume=True, progress=False)
    assert rec["resumed_from"] == 32 and rec["timesteps"] == 192  # was 208: 48 + 5 rollouts of 32
    assert _ckpts(run) == _ckpts(whole) and _eval_steps(run) == _eval_steps(whole)


# -- defect 13: a full disk during training ------------------------------------------------------


def _disk_full_at(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    original = train_mod.save_model

    def save_model(model: Any, path: Path) -> Path:
        if Path(path).name == name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return original(model, path)

    monkeypatch.setattr(train_mod, "save_model", save_model)


def test_a_full_disk_during_training_is_recorded_as_failed_and_resume_completes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    argv = ["train", "--config", str(_config_file(tmp_path)), "--timesteps", "192", "--out", str(out), "--quiet"]
    _disk_full_at(monkeypatch, "ppo_128_steps.zip")
    assert main(argv) == 1
    assert "No space left on device" in capsys.readouterr().err
    manifest = read_manifest(out)
    assert manifest is not None and manifest["status"] == "failed" and "No space left" in manifest["error"]
    monkeypatch.undo()
    assert main([*argv, "--resume"]) == 0
    manifest = read_manifest(out)
    assert manifest is not None and manifest["status"] == "complete"
    assert _ckpts(out) == [64, 128, 192] and _eval_steps(out) == [2, 66, 130]


def test_a_run_left_running_by_a_full_disk_is_resumed_or_overwritten(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """When not even run.json can be written after the failure, the folder says `running`; the next
    run (whose lock shows nobody runs it) resumes it, or replaces it with --overwrite."""
    import cv2x_marl.runs as runs

    out = tmp_path / "out"
    argv = ["train", "--config", str(_config_file(tmp_path)), "--timesteps", "128", "--out", str(out), "--quiet"]
    _disk_full_at(monkeypatch, "ppo_128_steps.zip")
    original = runs.write_json

    def write_json(path: Path, data: Any) -> None:
        if data.get("status") != "running":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        original(path, data)

    monkeypatch.setattr(runs, "write_json", write_json)
    assert main(argv) == 1
    manifest = read_manifest(out)
    assert manifest is not None and manifest["status"] == "running"
    monkeypatch.undo()
    assert main([*argv, "--resume"]) == 0
    manifest = read_manifest(out)
    assert manifest is not None and manifest["status"] == "complete"
    assert [s["status"] for s in manifest["segments"]] == ["running"]
    assert _ckpts(out) == [64, 128]
    # the same state again, replaced as a whole this time
    _disk_full_at(monkeypatch, "ppo_128_steps.zip")
    monkeypatch.setattr(runs, "write_json", write_json)
    assert main([*argv, "--overwrite"]) == 1
    monkeypatch.undo()
    assert main([*argv, "--overwrite"]) == 0
    manifest = read_manifest(out)
    assert manifest is not None and manifest["status"] == "complete" and "segments" not in manifest
