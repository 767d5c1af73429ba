"""MAPPO keeps its work on Ctrl-C / SIGTERM: checkpoints every ``checkpoint_every`` iterations and at an
interrupt, and ``--resume`` ends where an uninterrupted run ends (the same parameters, learning curve and
checkpoints, bit for bit)."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("torchrl")

from cv2x_marl.cli import main
from cv2x_marl.rl import mappo as mappo_mod
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.mappo import train_mappo
from cv2x_marl.rl.train import TrainingInterrupted
from cv2x_marl.runs import read_manifest
from tests.rl.test_mappo import TINY as MAPPO_TINY

#: test_mappo.py's tiny run (8 vehicles, 10-step episodes, 2 copies, a row every iteration), checkpointed every
#: 2 iterations
TINY = dataclasses.replace(MAPPO_TINY, checkpoint_every=2)
#: agent-steps of one iteration: 2 copies x 10 steps x 8 agents
ITERATION = 2 * 10 * 8


def _ckpts(run: Path) -> list[int]:
    return sorted(int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("mappo_*.pt"))


def _iterations(run: Path) -> list[int]:
    return [int(line.split(",")[0]) for line in (run / "eval.csv").read_text().splitlines()[1:]]


def _sigint_in(monkeypatch: pytest.MonkeyPatch, method: str, call: int) -> None:
    """Send this process SIGINT (as Ctrl-C would) at the start of the ``call``-th call of ``Mappo.<method>``."""
    original = getattr(mappo_mod.Mappo, method)
    calls = {"n": 0}

    def wrapped(self: Any, *args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == call:
            os.kill(os.getpid(), signal.SIGINT)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(mappo_mod.Mappo, method, wrapped)


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    run = tmp_path_factory.mktemp("mappo") / "whole"
    return run, train_mappo(TINY, 5 * ITERATION, 7, run, progress=False)


def test_an_uninterrupted_run_checkpoints_on_schedule_and_at_the_end(whole: tuple[Path, dict[str, Any]]) -> None:
    run, rec = whole
    assert rec["iterations"] == 5 and rec["resumed_from"] is None
    assert _ckpts(run) == [2, 4, 5] and _iterations(run) == [1, 2, 3, 4, 5]


@pytest.mark.parametrize(
    ("method", "call", "done", "cut"),
    [
        ("collect", 3, 2, True),  # Ctrl-C as the 3rd iteration starts collecting: 2 iterations count
        ("update", 3, 3, False),  # Ctrl-C during the 3rd update: that iteration is finished, then the run stops
    ],
)
def test_resume_after_ctrl_c_ends_where_an_uninterrupted_run_ends(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    whole: tuple[Path, dict[str, Any]],
    method: str,
    call: int,
    done: int,
    cut: bool,
) -> None:
    ref_dir, ref = whole
    run = tmp_path / "run"
    _sigint_in(monkeypatch, method, call)
    with pytest.raises(TrainingInterrupted, match=rf"stopped after {done} of 5 iterations") as info:
        train_mappo(TINY, 5 * ITERATION, 7, run, progress=False)
    assert ("not counted" in str(info.value)) is cut
    assert _iterations(run) == list(range(1, done + 1))
    assert _ckpts(run) == sorted({2, done})  # the schedule's, and the interrupt's
    manifest = read_manifest(run)
    assert manifest is not None and manifest["status"] == "interrupted"
    assert not (run / "model.pt").exists()
    monkeypatch.undo()
    rec = train_mappo(TINY, 5 * ITERATION, 7, run, progress=False, resume=True)
    assert rec["resumed_from"] == done * ITERATION and rec["iterations"] == 5
    assert rec["parameters_digest"] == ref["parameters_digest"]
    assert (run / "eval.csv").read_text() == (ref_dir / "eval.csv").read_text()
    assert _ckpts(run) == sorted({2, 4, 5, done})
    manifest = read_manifest(run)
    assert manifest is not None and manifest["status"] == "complete"


def test_cli_resume_continues_a_mappo_run_and_refuses_a_finished_or_changed_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], whole: tuple[Path, dict[str, Any]]
) -> None:
    ref_dir, ref = whole
    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(TINY.to_dict()))
    out = tmp_path / "out"
    argv = ["train", "--config", str(cfg), "--seed", "7", "--out", str(out), "--quiet"]
    assert main([*argv, "--timesteps", str(3 * ITERATION)]) == 0
    assert main([*argv, "--timesteps", str(5 * ITERATION), "--resume"]) == 0  # 3 -> 5 iterations
    assert json.loads((out / "record.json").read_text())["parameters_digest"] == ref["parameters_digest"]
    assert (out / "eval.csv").read_text() == (ref_dir / "eval.csv").read_text()
    capsys.readouterr()
    assert main([*argv, "--timesteps", str(5 * ITERATION), "--resume"]) == 2
    assert "already has 800 agent-steps" in capsys.readouterr().err
    with pytest.raises(TrainError, match="configuration or seed differs"):
        train_mappo(dataclasses.replace(TINY, eval_episodes=3), 6 * ITERATION, 7, out, progress=False, resume=True)
