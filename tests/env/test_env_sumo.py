"""The env on SUMO mobility (issue 14): traffic and snapshot modes on ``sumo-grid``, speed commands.

libsumo runs one simulation per process, so the envs below run one after the other.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("libsumo")
pytest.importorskip("sumo")

from pettingzoo.test import parallel_api_test

from cv2x_marl.env import parallel_env
from cv2x_marl.sim import sumo

SHORT = ["sim.warmup_subframes=200"]


@pytest.fixture(autouse=True, scope="module")
def _private_cache(tmp_path_factory: pytest.TempPathFactory) -> object:
    mp = pytest.MonkeyPatch()
    mp.setenv(sumo.CACHE_ENV, str(tmp_path_factory.mktemp("sumo-cache")))
    yield None
    mp.undo()


@pytest.mark.parametrize("traffic_action", ["offset", "speed"])
def test_checkers_pass_in_traffic_mode_on_sumo_grid(traffic_action: str) -> None:
    env = parallel_env(preset="sumo-grid", overrides=SHORT, mode="traffic", max_cycles=6, traffic_action=traffic_action)
    parallel_api_test(env, num_cycles=8)
    env.close()


def test_snapshot_mode_takes_its_snapshot_from_sumo() -> None:
    env = parallel_env(preset="sumo-grid", overrides=SHORT, max_cycles=3)
    env.reset(seed=4)
    ids = env.sim.vehicle_ids
    assert ids is not None and len(ids) == env.n == 21
    # the snapshot's positions are SUMO's positions of the tracked vehicles at that instant
    lock = sumo.lockstep_of(env.sim)
    np.testing.assert_allclose(env.snapshot.positions_m, lock.state.pos_m)
    env.close()


def _speed_run(a0: float, steps: int = 40, seed: int = 2) -> tuple[np.ndarray, float]:
    """Vehicle 0 commanded with ``action[0] = a0`` for ``steps`` periods: its last positions and speed."""
    env = parallel_env(
        preset="sumo-grid", overrides=SHORT, mode="traffic", movers=[0], max_cycles=steps, traffic_action="speed"
    )
    env.reset(seed=seed)
    track = []
    for _ in range(steps):
        env.step({a: np.array([a0, 0.0], np.float32) for a in env.agents})
        track.append(env.positions_m[0].copy())
    speed = float(sumo.lockstep_of(env.sim).state.speed_mps[0])
    env.close()
    return np.array(track), speed


def test_speed_commands_are_honoured_by_sumo() -> None:
    stopped, v_stop = _speed_run(-1.0)  # target speed 0
    assert v_stop == 0.0
    assert np.abs(stopped[-10:] - stopped[-1]).max() < 1e-9  # it stands still
    driven, v_drive = _speed_run(1.0)  # target: the speed limit (SUMO keeps it safe)
    assert v_drive > 1.0
    assert np.linalg.norm(driven[-1] - driven[-10]) > 1.0
    # a target speed is never exceeded: 9 periods at most at the commanded speed
    half, v_half = _speed_run(0.0)  # target 8.335 m/s
    assert v_half <= 0.5 * 16.67 + 1e-6
    step_m = np.linalg.norm(np.diff(half[-10:], axis=0), axis=1)
    assert step_m.max() <= 0.5 * 16.67 * 0.1 + 1e-6


def test_speed_mode_same_seed_same_episode() -> None:
    a, _ = _speed_run(0.3, steps=15, seed=7)
    b, _ = _speed_run(0.3, steps=15, seed=7)
    np.testing.assert_array_equal(a, b)


def test_speed_mode_needs_sumo_traffic(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"invalid env argument traffic_action='speed'; allowed: offset \| speed"):
        parallel_env(
            traffic_action="speed"
        )  # snapshot mode (traffic mode on the lane model: tests/env/test_traffic.py)
    with pytest.raises(ValueError, match="traffic_action"):
        parallel_env(preset="sumo-grid", traffic_action="speed")  # snapshot mode
    with pytest.raises(ValueError, match="traffic_action"):
        parallel_env(preset="sumo-grid", mode="traffic", traffic_action="throttle")


def test_close_stops_sumo_and_copies_in_one_process_are_refused() -> None:
    from cv2x_marl.env.vector import SingleMoverVectorEnv
    from cv2x_marl.rl.sb3_vec_env import AgentsVecEnv

    env = parallel_env(preset="sumo-grid", overrides=SHORT, mode="traffic", max_cycles=3, traffic_action="speed")
    env.reset(seed=1)
    lock = sumo.lockstep_of(env.sim)
    env.close()
    assert lock.closed
    with pytest.raises(ValueError, match="cannot share one process"):
        AgentsVecEnv(lambda: parallel_env(preset="sumo-grid", mode="traffic", movers=[0]), 2)
    with pytest.raises(ValueError, match="cannot share one process"):
        SingleMoverVectorEnv(2, preset="sumo-grid", mode="traffic")
