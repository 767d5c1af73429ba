"""The env inside RLlib's PettingZoo wrapper (issue 11): reset, step and render through
``ParallelPettingZooEnv``, which calls ``render(self.render_mode)``."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("ray.rllib")

from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

from cv2x_marl.env import parallel_env_v2

KW = {"overrides": ["sim.warmup_subframes=200"], "max_cycles": 2}


def test_rllib_wrapper_steps_and_renders() -> None:
    env = ParallelPettingZooEnv(parallel_env_v2(render_mode="rgb_array", **KW))
    obs, _ = env.reset(seed=3)
    assert len(obs) == 21 and obs["vehicle_0"].shape == env.observation_space["vehicle_0"].shape
    obs, rew, term, _, _ = env.step({a: np.zeros(2, np.float32) for a in obs})
    assert set(rew) == set(obs) and not term["__all__"]
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8
    _, _, _, trunc, _ = env.step({a: np.zeros(2, np.float32) for a in obs})
    assert trunc["__all__"]  # max_cycles = 2: the time limit is a truncation, not a termination


def test_render_mode_argument_must_match() -> None:
    env = parallel_env_v2(render_mode="rgb_array", **KW)
    env.reset(seed=0)
    assert env.render("rgb_array").shape[2] == 3
    with pytest.raises(ValueError, match="invalid render mode 'human'"):
        env.render("human")
    assert parallel_env_v2(**KW).render(None) is None
