"""Resume that never loses or mixes (issue 12, defect 3): checkpoint schedule after a resume,
eval.csv cut back to the checkpoint, a newer model never replaced by an older one, short runs
checkpointed, SIGTERM/Ctrl-C saving a checkpoint with a clean exit."""

from __future__ import annotations

import dataclasses
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.train import PpoConfig, TrainConfig, latest_checkpoint, read_eval_rows, train, write_eval_rows
from cv2x_marl.runs import read_manifest, sha256_file, verify

TINY = TrainConfig(
    env_id="cv2x/SingleMover-v0",
    copies=2,
    env={"max_cycles": 10, "normalise_reward": True, "overrides": ["sim.warmup_subframes=200"]},
    ppo=PpoConfig(n_steps=16, batch_size=32, n_epochs=2, net_arch=(16, 16)),
    checkpoint_every=64,
    eval_every=64,
    eval_episodes=2,
)


def _ckpts(run: Path) -> list[int]:
    return sorted(int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("ppo_*_steps.zip"))


def test_checkpoints_follow_the_schedule_across_a_resume(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(TINY, 128, seed=1, run_dir=run, progress=False)
    assert _ckpts(run) == [64, 128]
    rec = train(TINY, 256, seed=1, run_dir=run, resume=True, progress=False)
    assert rec["resumed_from"] == 128
    assert _ckpts(run) == [64, 128, 192, 256]  # no burst of extra checkpoints after the resume
    manifest = read_manifest(run)
    assert manifest is not None and manifest["status"] == "complete"
    assert [s["parameters"]["timesteps"] for s in manifest["segments"]] == [128]
    verify(run)


def test_resume_cuts_the_learning_curve_back_to_the_checkpoint(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(TINY, 128, seed=1, run_dir=run, progress=False)
    rows = read_eval_rows(run / "eval.csv")
    assert [int(r["timesteps"]) for r in rows] == [2, 66]
    # a later segment that was lost: its checkpoint is gone, its eval row is still there
    write_eval_rows(run / "eval.csv", [*rows, {**rows[-1], "timesteps": "200"}])
    (run / "checkpoints" / "ppo_128_steps.zip").unlink()
    rec = train(TINY, 192, seed=1, run_dir=run, resume=True, progress=False)
    assert rec["resumed_from"] == 64
    got = [int(r["timesteps"]) for r in read_eval_rows(run / "eval.csv")]
    assert got == [2, 66, 130]  # the row of the lost segment was dropped; the schedule continued


def test_resume_with_fewer_steps_never_replaces_the_newer_model(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(TINY, 128, seed=1, run_dir=run, progress=False)
    digest = sha256_file(run / "model.zip")
    with pytest.raises(TrainError, match="already has 128 steps"):
        train(TINY, 64, seed=1, run_dir=run, resume=True, progress=False)
    assert sha256_file(run / "model.zip") == digest
    assert read_manifest(run)["status"] == "complete"  # type: ignore[index]


def test_a_run_shorter_than_checkpoint_every_is_checkpointed(tmp_path: Path) -> None:
    run = tmp_path / "run"
    train(dataclasses.replace(TINY, checkpoint_every=10**9), 64, seed=1, run_dir=run, progress=False)
    assert _ckpts(run) == [64]


def test_sigterm_saves_a_checkpoint_and_exits_cleanly(tmp_path: Path) -> None:
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(
        "env_id: cv2x/SingleMover-v0\ncopies: 2\ncheckpoint_every: 1000000\neval_every: 1000000\n"
        "eval_episodes: 1\nenv:\n  max_cycles: 10\n  overrides: [sim.warmup_subframes=200]\n"
        "ppo:\n  n_steps: 16\n  batch_size: 32\n  n_epochs: 1\n  net_arch: [16, 16]\n"
    )
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "cv2x_marl.cli", "train", "--config", str(cfg), "--timesteps", "1e7"]
    proc = subprocess.Popen([*argv, "--out", str(run), "--quiet"], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (run / "tb").exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)  # tb/ appears once learning has started (the stop handler is installed)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert "training stopped at" in err and "--resume" in err and "Traceback" not in err
    steps = _ckpts(run)
    assert len(steps) == 1 and steps[0] > 0
    manifest = read_manifest(run)
    assert manifest is not None and manifest["status"] == "interrupted"
    assert f"checkpoints/ppo_{steps[0]}_steps.zip" in manifest["files"]
    ckpt = latest_checkpoint(run)
    assert ckpt is not None
    loaded = json.loads((run / "train_config.json").read_text())
    assert loaded["timesteps"] == 10**7
