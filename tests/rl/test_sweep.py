"""`cv2x-marl sweep` on Ray Tune and `dataset --ray` (issue 11): two tiny trials on a local Ray
give the same models as `train` run directly; the Ray dataset equals the serial one."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

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
