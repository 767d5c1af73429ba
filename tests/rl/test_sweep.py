"""`cv2x-marl sweep` on Ray Tune and `dataset --ray` (issue 11): two tiny trials on a local Ray
give the same models as `train` run directly; the Ray dataset equals the serial one."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from cv2x_marl.cli import main
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.sweep import apply_point, grid_points, parse_grid
from cv2x_marl.rl.train import load_train_config, parameters_digest, train
from cv2x_marl.runs import verify

TINY = """\
env_id: cv2x/SingleMover-v0
copies: 2
checkpoint_every: 1000000
eval_every: 1000000
eval_episodes: 1
env:
  max_cycles: 10
  overrides: [sim.warmup_subframes=200]
ppo: {n_steps: 16, batch_size: 32, n_epochs: 1, net_arch: [16, 16]}
"""


def _ray_dirs() -> set[str]:
    return {p.name for p in Path(tempfile.gettempdir()).glob("cv2x-ray-*")}


def test_grid_parsing_and_validation(tmp_path: Path) -> None:
    grid = parse_grid(["ppo.learning_rate=1e-4,3e-4", "env.replan_every=25,50", "copies=4"])
    assert grid == {"ppo.learning_rate": [1e-4, 3e-4], "env.replan_every": [25, 50], "copies": [4]}
    points = grid_points(grid)
    assert len(points) == 4 and points[0] == {"ppo.learning_rate": 1e-4, "env.replan_every": 25, "copies": 4}
    cfg = apply_point(load_train_config(None), points[3])
    assert cfg.ppo.learning_rate == 3e-4 and cfg.env["replan_every"] == 50 and cfg.copies == 4
    assert grid_points({}) == [{}]
    with pytest.raises(TrainError, match=r"--grid key 'ppo\.lr' unknown"):
        parse_grid(["ppo.lr=1"])
    with pytest.raises(TrainError, match="--grid expects key=v1,v2"):
        parse_grid(["copies"])
    with pytest.raises(TrainError, match=r"ppo\.gamma must be a number in \(0, 1\]"):
        apply_point(load_train_config(None), {"ppo.gamma": 5})


def test_sweep_runs_two_trials_on_a_local_ray(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg_file = tmp_path / "tiny.yaml"
    cfg_file.write_text(TINY)
    out = tmp_path / "sweep"
    before = _ray_dirs()
    argv = ["sweep", "--config", str(cfg_file), "--seeds", "0,1", "--timesteps", "64", "--eval-episodes", "2"]
    assert main([*argv, "--out", str(out), "--json", "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)  # Tune's tables went to stderr: stdout is pure JSON
    assert [t["status"] for t in result["trials"]] == ["TERMINATED", "TERMINATED"]
    assert [t["seed"] for t in result["trials"]] == [0, 1]
    assert all(t["timesteps"] == 64 for t in result["trials"])
    assert result["points"][0]["trials"] == 2
    for name in ("trials.csv", "results.json", "sweep.png", "run.json"):
        assert (out / name).exists(), name
    verify(out)
    assert _ray_dirs() == before  # Ray's session files were removed
    # a trial is exactly `train` with that seed: the same parameters, bit for bit
    from stable_baselines3 import PPO

    direct = tmp_path / "direct"
    train(load_train_config(cfg_file), 64, seed=1, run_dir=direct, progress=False)
    trial = out / "trials" / result["trials"][1]["name"] / "model.zip"
    assert parameters_digest(PPO.load(trial)) == parameters_digest(PPO.load(direct / "model.zip"))


def test_dataset_on_ray_equals_the_serial_dataset(tmp_path: Path) -> None:
    base = ["dataset", "--runs", "2", "--seed", "5", "--subframes", "400", "--quiet"]
    base += ["--set", "sim.warmup_subframes=100"]
    assert main([*base, "--out", str(tmp_path / "serial")]) == 0
    assert main([*base, "--ray", "--out", str(tmp_path / "ray")]) == 0
    a = pq.read_table(tmp_path / "serial" / "samples.parquet")
    b = pq.read_table(tmp_path / "ray" / "samples.parquet")
    assert a.num_rows > 1000 and a.equals(b)


# -- issue 25, defect 9: Ctrl-C during a sweep stops it cleanly -------------------------------------


class _FakeResult:
    def __init__(self, spec: dict[str, Any], metrics: dict[str, Any] | None) -> None:
        self.config = {"trial": spec}
        self.error = None
        self.metrics = metrics


def _fake_tune(monkeypatch: pytest.MonkeyPatch, fit: Any) -> None:
    """Replace Ray (session and Tuner) by ``fit(specs) -> results``: the sweep logic around Tune,
    without starting Ray (the session sets the SIGTERM handler ``ray.init`` sets)."""
    import contextlib
    import sys

    from ray import tune

    import cv2x_marl.rl.sweep as sweep

    @contextlib.contextmanager
    def ray_session(address: str | None) -> Any:
        import signal

        signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(signum))  # as ray.init does
        yield

    class Tuner:
        def __init__(self, trainable: Any, param_space: dict[str, Any], run_config: Any) -> None:
            self.specs = param_space["trial"]["grid_search"]

        def fit(self) -> list[_FakeResult]:
            return fit(self.specs)

    monkeypatch.setattr(sweep, "ray_session", ray_session)
    monkeypatch.setattr(tune, "Tuner", Tuner)
    monkeypatch.setattr(tune, "with_resources", lambda trainable, resources: trainable)


def _plots(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    import cv2x_marl.plotting as plotting

    calls: list[Any] = []
    monkeypatch.setattr(plotting, "plot_sweep", lambda *a: calls.append(a))
    return calls


def _tiny_sweep(tmp_path: Path, out: Path) -> int:
    """``cv2x-marl sweep`` of the tiny config over seeds 0 and 1 into ``out``; its exit status."""
    cfg_file = tmp_path / "tiny.yaml"
    cfg_file.write_text(TINY)
    argv = ["sweep", "--config", str(cfg_file), "--seeds", "0,1", "--timesteps", "64", "--out", str(out)]
    return main([*argv, "--quiet"])


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_ctrl_c_or_sigterm_during_a_sweep_raises_and_rolls_the_folder_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], signame: str
) -> None:
    """Tune's own SIGINT handler (installed by ``tune.run``, which only ends its loop and returns
    the unfinished trials) is switched off during the sweep: Ctrl-C raises at once; so does SIGTERM
    (``ray.init`` made it ``sys.exit``, and Ray's core aborted the process: exit -6)."""
    import os
    import signal
    import time

    from ray.tune.tune import _setup_signal_catching

    def fit(specs: list[dict[str, Any]]) -> list[_FakeResult]:
        tune_stopped = _setup_signal_catching()  # what Tuner.fit does first
        os.kill(os.getpid(), getattr(signal, signame))
        time.sleep(1.0)  # a Tune step; Python runs the handler here
        raise AssertionError(f"{signame} did not raise (Tune caught it: {tune_stopped.is_set()})")

    _fake_tune(monkeypatch, fit)
    plots = _plots(monkeypatch)
    out = tmp_path / "sweep"
    assert _tiny_sweep(tmp_path, out) == 130
    assert "interrupted" in capsys.readouterr().err
    assert not out.exists() and plots == []
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handler before the CLI's, put back by main


def test_a_sweep_whose_trials_tune_stopped_is_an_interrupt_not_a_plot(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Tune stopped before a trial reported (SIGUSR1, or a Ctrl-C Tune caught): no summary with
    None metrics, no plot (it used to raise TypeError: int * NoneType), the folder rolled back."""

    def fit(specs: list[dict[str, Any]]) -> list[_FakeResult]:
        done = {"mean_utility_gain": 0.01, "effectiveness": 0.5, "timesteps": 64}
        return [_FakeResult(specs[0], done), _FakeResult(specs[1], {})]

    _fake_tune(monkeypatch, fit)
    plots = _plots(monkeypatch)
    out = tmp_path / "sweep"
    assert _tiny_sweep(tmp_path, out) == 130
    err = capsys.readouterr().err
    assert "stopped before 1 of 2 trials finished (seed1_base)" in err
    assert not out.exists() and plots == []


def test_plot_sweep_draws_points_whose_trials_failed(tmp_path: Path) -> None:
    from cv2x_marl.plotting import plot_sweep

    trials = [
        {"config": {"copies": 2}, "status": "TERMINATED", "mean_utility_gain": 0.02},
        {"config": {"copies": 2}, "status": "TERMINATED", "mean_utility_gain": None},
        {"config": {"copies": 4}, "status": "ERROR", "mean_utility_gain": None},
    ]
    points = [
        {"config": {"copies": 2}, "label": "copies=2", "mean_utility_gain": 0.02, "std_utility_gain": None},
        {"config": {"copies": 4}, "label": "copies=4", "mean_utility_gain": None, "std_utility_gain": None},
    ]
    result = {"trials": trials, "points": points, "seeds": [0, 1], "timesteps": 64, "eval_episodes": 2, "eval_seed": 1}
    path = plot_sweep(result, tmp_path / "sweep.png")
    assert path.stat().st_size > 1000


def test_a_bad_grid_point_is_refused_before_the_sweep_folder_exists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg_file = tmp_path / "tiny.yaml"
    cfg_file.write_text(TINY)
    out = tmp_path / "sweep"
    argv = ["sweep", "--config", str(cfg_file), "--grid", "env.max_step_m=5,-5", "--out", str(out), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "grid point env.max_step_m=-5" in err and "max_step_m" in err
    assert not out.exists()
