"""Training the learned utility map: configuration checks, one seed one run, and the quick mode's
result against the scripts on training-list episodes."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from cv2x_marl.policies.utility_map import UtilityMap
from cv2x_marl.rl.errors import TrainError
from cv2x_marl.rl.utility_map import MapConfig, MapSettings, load_map_config, train_map


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("algo: utility-map\nmap: {explore: 2}\n", r"map.explore must be a number in \[0, 1\], got 2"),
        ("algo: utility-map\nmap: {hidden: []}\n", r"map.hidden must be a non-empty list"),
        ("algo: utility-map\nmap: {grids: 3}\n", r"unknown map key\(s\) \[.grids.\]; keys: batch_size, ensemble"),
        ("algo: utility-map\nenv_id: cv2x/Cooperative-v0\n", r"trains on cv2x/SingleMover-v3"),
        ("algo: utility-map\nenv: {start_pool: 0}\n", r"start_pool must be an integer >= 1"),
        ("algo: utility-map\nenv: {colour: 1}\n", r"unknown env argument\(s\) \['colour'\]"),
    ],
)
def test_bad_configs_name_the_key(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(TrainError, match=message):
        load_map_config(write(tmp_path / "c.yaml", text))


def test_the_shipped_config_loads() -> None:
    cfg = load_map_config(Path("agents/configs/map_single_v3.yaml"))
    assert cfg.env_id == "cv2x/SingleMover-v3" and cfg.env["start_pool"] >= 1


def tiny(copies: int = 2, **kw: object) -> MapConfig:
    settings = MapSettings(**{"fit_steps": 5, "batch_size": 32, "random_iterations": 1, **kw})  # type: ignore[arg-type]
    env = {"max_cycles": 20, "start_pool": 8}
    return MapConfig(copies=copies, map=settings, eval_every=100, eval_episodes=1, env=env)


def curve(run: Path) -> list[dict[str, str]]:
    with open(run / "curve.csv") as f:
        return [{k: v for k, v in row.items() if k != "cpu_s"} for row in csv.DictReader(f)]


def test_same_seed_same_run(tmp_path: Path) -> None:
    runs = []
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        train_map(tiny(), 2 * 2 * 20, seed, tmp_path / name, progress=False)
        runs.append((curve(tmp_path / name), UtilityMap.load(tmp_path / name / "model.npz").members[0]))
    (ca, wa), (cb, wb), (_, wc) = runs
    assert ca == cb and len(ca) == 2 and ca[-1]["eval_utility_gain"] != ""
    for (w1, b1), (w2, b2) in zip(wa, wb, strict=True):
        np.testing.assert_array_equal(w1, w2)
        np.testing.assert_array_equal(b1, b2)
    assert not np.array_equal(wa[0][0], wc[0][0])  # another seed, another run


def test_quick_mode_beats_random_and_gbmu(tmp_path: Path) -> None:
    """12 iterations of 16 episodes (19,200 agent-steps, about 20 s) and four training-list episodes after the
    pool: the map's mean utility gain is above gbmu's and random's on the same episodes."""
    from cv2x_marl.env import make_parallel_env
    from cv2x_marl.env.seeds import training_pool
    from cv2x_marl.experiments.evaluate import evaluate
    from cv2x_marl.policies.utility_map import UtilityMapPolicy

    env = {"max_cycles": 100, "max_step_m": 5.0, "start_pool": 64}
    cfg = MapConfig(copies=16, env=env, eval_every=100, eval_episodes=1)
    train_map(cfg, 12 * 16 * 100, 0, tmp_path / "run", progress=False)
    seeds = training_pool(64 + 8)[68:72]
    par = make_parallel_env("cv2x/SingleMover-v3", **env)
    policy = UtilityMapPolicy(tmp_path / "run" / "model.npz", par)
    gains = {
        name: evaluate("cv2x/SingleMover-v3", p, 4, 0, None, env, progress=False, seeds=seeds)["mean_utility_gain"]
        for name, p in (("map", policy), ("gbmu", "gbmu"), ("random", "random"))
    }
    assert gains["map"] > gains["gbmu"] and gains["map"] > gains["random"], gains
