"""The Gymnasium ids (``cv2x/SingleMover-v0`` .. ``-v3``, ``cv2x/Traffic-v0`` / ``-v1``): vehicle 0's view of the
id's parallel env.

Vehicle 0 moves (SingleMover: every other vehicle stays where the snapshot put it; Traffic: the others drive).
Observation, action, reward and info are vehicle 0's in the parallel env of the same id
(:func:`cv2x_marl.env.registry.make_parallel_env`, with ``movers=[0]``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.registry import SPECS, make_parallel_env, spec_of

AGENT = "vehicle_0"


class SingleMoverEnv(gym.Env):
    """Vehicle 0's view of the parallel env of a Gymnasium id (:func:`~cv2x_marl.env.registry.make_parallel_env`;
    the other keyword arguments are passed on): every ``cv2x/SingleMover-v*`` and ``cv2x/Traffic-v*`` id is this
    class with its ``env_id`` (``gymnasium.register(..., kwargs={"env_id": ...})``)."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}  # noqa: RUF012 - Gymnasium declares it so

    def __init__(self, env_id: str = "cv2x/SingleMover-v0", render_mode: str | None = None, **kwargs: Any) -> None:
        spec = spec_of(env_id)
        if "gymnasium" not in spec.frameworks:
            gym_ids = ", ".join(s.env_id for s in SPECS if "gymnasium" in s.frameworks)
            raise ValueError(f"invalid env_id {env_id!r}: not a Gymnasium id; allowed: {gym_ids}")
        if "movers" in kwargs:
            raise ValueError(f"invalid env argument movers: {env_id.split('/', 1)[1]} always moves vehicle 0")
        #: the registered id (:data:`cv2x_marl.env.registry.SPECS`)
        self.env_id = env_id
        self.par = make_parallel_env(env_id, render_mode=render_mode, **kwargs, movers=[0])
        self.render_mode = render_mode
        self.observation_space = self.par.observation_space(AGENT)
        self.action_space = self.par.action_space(AGENT)
        self._zero = self.par.dynamics.null_action
        #: a Gymnasium ``TimeLimit`` around this env (steps; None: none): the observation's time left
        #: follows the shorter of it and ``max_cycles`` (:func:`follow_time_limit` sets it)
        self.time_limit: int | None = None
        #: steps go through :meth:`MobilityEnv.step_mover` (snapshot mode, individual reward)
        self.fast = self.par.fast_mover == 0 and render_mode is None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[NDArray, dict]:
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0):
            raise ValueError(f"invalid reset seed={seed!r}; allowed: an integer >= 0 or None")
        super().reset(seed=None if seed is None else int(seed))
        self.par.horizon = self.horizon_in_force()
        if seed is None and self.par.start_pool:  # a start from the pool, drawn by the parallel env's generator
            if self.par._np_random is None:  # seeded from this env's generator (itself from OS entropy)
                self.par._np_random = np.random.default_rng(int(self.np_random.integers(0, 2**63 - 1)))
            obs, infos = self.par.reset()
        else:
            episode_seed = int(seed) if seed is not None else int(self.np_random.integers(0, 2**31 - 1))
            obs, infos = self.par.reset(seed=episode_seed)
        return obs[AGENT], infos[AGENT]

    def horizon_in_force(self) -> int:
        """The episode's horizon (steps) the observation's time left counts down from: ``max_cycles``, or a
        shorter Gymnasium ``TimeLimit`` (``spec.max_episode_steps`` or :attr:`time_limit`)."""
        limit = (
            self.time_limit if self.spec is None or self.spec.max_episode_steps is None else self.spec.max_episode_steps
        )
        return int(self.par.max_cycles if limit is None else min(self.par.max_cycles, int(limit)))

    def step(self, action: Any) -> tuple[NDArray, float, bool, bool, dict]:
        if self.fast:  # vehicle 0 alone: bit-identical to the full step (tested), several times faster
            ob, reward, done, inf = self.par.step_mover(action)
            return ob, reward, False, done, inf
        actions = {a: self._zero for a in self.par.agents}
        actions[AGENT] = action
        obs, rew, term, trunc, info = self.par.step(actions)
        return obs[AGENT], rew[AGENT], term[AGENT], trunc[AGENT], info[AGENT]

    def action_masks(self) -> NDArray[np.bool_]:
        """Vehicle 0's valid actions now, as sb3-contrib's ``MaskablePPO`` asks (``cv2x/Resource-v0``: the entries of
        its candidate list when it decides, every action otherwise, since its action is then ignored).

        Raises:
            ValueError: the id's actions are continuous (no mask).
        """
        masks = self.par.action_masks()
        if masks is None:
            raise ValueError(f"{self.env_id} has continuous actions: no action mask (cv2x/Resource-v0 has one)")
        mine = masks[self.par.agent_index[AGENT]].astype(bool)
        return mine if mine.any() else np.ones_like(mine)

    def render(self) -> Any:
        return self.par.render()

    def close(self) -> None:
        self.par.close()


def follow_time_limit(env: gym.Env) -> gym.Env:
    """Make a ``cv2x/SingleMover-*`` env's observation follow the ``TimeLimit`` wrapped around it; returns ``env``.

    ``gymnasium.make(id, max_episode_steps=T)`` wraps the env in a ``TimeLimit`` the env itself cannot see
    (its own ``spec.max_episode_steps`` is None): this finds the wrapper and sets
    :attr:`SingleMoverEnv.time_limit` to ``T``, so that from the next reset observation version 3's time
    left and reach count down from ``min(T, max_cycles)``. ``gymnasium.make`` cannot do it itself: it hides
    the limit from the env, and an id registered with an additional wrapper could no longer be made with
    ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``. Without it the time left counts
    down from ``max_cycles``; setting ``env.unwrapped.time_limit`` directly does the same.
    """
    layer: Any = env
    while isinstance(layer, gym.Wrapper):
        if isinstance(layer, gym.wrappers.TimeLimit):
            break
        layer = layer.env
    if isinstance(layer, gym.wrappers.TimeLimit) and isinstance(env.unwrapped, SingleMoverEnv):
        env.unwrapped.time_limit = int(layer._max_episode_steps)
    return env
