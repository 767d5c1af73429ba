"""``speed_command="change"`` (traffic mode, lane model): ``action[0]`` changes the own speed over the period,
so the zero action holds it; the target-speed road policies refuse it."""

import gymnasium as gym
import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env.step import speed_change_commands
from cv2x_marl.policies.registry import make_policy


def test_commands_by_hand() -> None:
    act = np.array([[1.0, 0.0], [-1.0, 0.9], [-0.5, -0.7], [2.0, 0.0], [0.3, 0.0]])
    speed = np.array([10.0, 5.0, 1.0, 16.5, 7.0])
    movers = np.array([True, True, True, True, False])
    target, lanes = speed_change_commands(act, movers, speed, 16.67, 2.6, 3.4, 0.1, True)
    # 10 + 2.6 * 0.1; 5 - 3.4 * 0.1; max(1 - 0.5 * 3.4 * 0.1, 0); min(16.5 + 0.26, limit) (the action clipped to 1)
    np.testing.assert_allclose(target[:4], [10.26, 4.66, 0.83, 16.67], rtol=0, atol=1e-12)
    assert np.isnan(target[4]) and lanes.tolist() == [0, 1, -1, 0, 0]
    idle, _ = speed_change_commands(act, movers, speed, 16.67, 2.6, 3.4, 0.1, False)  # the settle phase
    assert np.isnan(idle).all()


def test_zero_holds_the_speed_and_full_actions_reach_the_bounds() -> None:
    env = gym.make("cv2x/Traffic-v1", max_cycles=12, speed_command="change")
    env.reset(seed=4)
    par = env.unwrapped.par
    v0 = float(par.sim.state.speed_mps[0])
    for _ in range(3):
        env.step(np.zeros(2, dtype=np.float32))
        assert float(par.sim.state.speed_mps[0]) == v0  # bit for bit
    speeds = [v0]
    for _ in range(4):
        env.step(np.array([1.0, 0.0], dtype=np.float32))
        speeds.append(float(par.sim.state.speed_mps[0]))
    limit = par.config.vehicles.speed_max_mps
    want_up = [min(v0 + 0.26 * k, limit) for k in range(5)]
    np.testing.assert_allclose(speeds, want_up, rtol=0, atol=1e-9)
    for _ in range(4):
        before = float(par.sim.state.speed_mps[0])
        env.step(np.array([-1.0, 0.0], dtype=np.float32))
        assert float(par.sim.state.speed_mps[0]) == pytest.approx(max(before - 0.34, 0.0), abs=1e-9)


def test_static_holds_and_the_target_speed_policies_refuse_the_option() -> None:
    env = gym.make("cv2x/Traffic-v1", max_cycles=4, speed_command="change")
    par = env.unwrapped.par
    obs, _ = par.reset(seed=2)
    static = make_policy("static", par)
    assert all(not a.any() for a in static.act(obs).values())
    for name in ("gbmu", "sensing", "optimum"):
        with pytest.raises(ValueError, match="speed_command='change'"):
            make_policy(name, par)
    with pytest.raises(ValueError, match="speed_command"):
        gym.make("cv2x/SingleMover-v3", speed_command="change")


def test_a_trained_models_speed_command_is_rebuilt(tmp_path) -> None:
    """``--policy ppo:PATH`` rebuilds the env with the model's ``speed_command`` (it shapes the actions: a
    change-trained policy on target speeds would be judged on another task), not with its training-only options."""
    import json

    from cv2x_marl.experiments.evaluate import trained_env_options

    env = {"max_cycles": 100, "speed_command": "change", "start_pool": 64, "reward": "team", "sensing_window": 5}
    (tmp_path / "train_config.json").write_text(json.dumps({"env_id": "cv2x/Traffic-v1", "env": env}))
    assert trained_env_options(tmp_path / "model.zip") == (
        "cv2x/Traffic-v1",
        {"max_cycles": 100, "speed_command": "change", "sensing_window": 5},
    )
