"""``cv2x/SingleMover-v0``: the paper's own setting as a single-agent Gymnasium env.

Vehicle 0 moves; every other vehicle stays where the snapshot put it. Observation, action,
reward and info are vehicle 0's in :class:`cv2x_marl.env.MobilityEnv` with ``movers=[0]``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.mobility_env import MobilityEnv

AGENT = "vehicle_0"


class SingleMoverEnv(gym.Env):
    """Single-agent view of :class:`MobilityEnv` (keyword arguments are passed on)."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}  # noqa: RUF012 - Gymnasium declares it so

    def __init__(self, render_mode: str | None = None, **kwargs: Any) -> None:
        if "movers" in kwargs:
            raise ValueError("invalid env argument movers: SingleMover-v0 always moves vehicle 0")
        self.par = MobilityEnv(movers=[0], render_mode=render_mode, **kwargs)
        self.render_mode = render_mode
        self.observation_space = self.par.observation_space(AGENT)
        self.action_space = self.par.action_space(AGENT)
        self._zero = np.zeros(2, dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[NDArray, dict]:
        super().reset(seed=seed)
        episode_seed = seed if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
        obs, infos = self.par.reset(seed=episode_seed)
        return obs[AGENT], infos[AGENT]

    def step(self, action: Any) -> tuple[NDArray, float, bool, bool, dict]:
        actions = {a: self._zero for a in self.par.agents}
        actions[AGENT] = action
        obs, rew, term, trunc, info = self.par.step(actions)
        return obs[AGENT], rew[AGENT], term[AGENT], trunc[AGENT], info[AGENT]

    def render(self) -> Any:
        return self.par.render()

    def close(self) -> None:
        self.par.close()
