"""``cv2x/SingleMover-v0`` .. ``-v3``: the paper's own setting as a single-agent Gymnasium env.

Vehicle 0 moves; every other vehicle stays where the snapshot put it. Observation, action,
reward and info are vehicle 0's in :class:`cv2x_marl.env.MobilityEnv` with ``movers=[0]``
(``-v1``, ``-v2``, ``-v3``: with :data:`~cv2x_marl.env.options.V1_DEFAULTS`, ``V2_DEFAULTS``, ``V3_DEFAULTS``).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.mobility_env import MobilityEnv
from cv2x_marl.env.options import VERSION_DEFAULTS

AGENT = "vehicle_0"


class SingleMoverEnv(gym.Env):
    """Single-agent view of :class:`MobilityEnv` (keyword arguments are passed on)."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}  # noqa: RUF012 - Gymnasium declares it so

    version = 0
    #: the key of the id's defaults in :data:`VERSION_DEFAULTS` (None: ``v{version}``)
    defaults: str | None = None
    #: the id's name in messages (None: ``SingleMover-v{version}``)
    label: str | None = None

    def __init__(self, render_mode: str | None = None, **kwargs: Any) -> None:
        if "movers" in kwargs:
            label = self.label or f"SingleMover-v{self.version}"
            raise ValueError(f"invalid env argument movers: {label} always moves vehicle 0")
        kwargs = {**VERSION_DEFAULTS[self.defaults or f"v{self.version}"], **kwargs}
        self.par = MobilityEnv(movers=[0], render_mode=render_mode, **kwargs)
        self.render_mode = render_mode
        self.observation_space = self.par.observation_space(AGENT)
        self.action_space = self.par.action_space(AGENT)
        self._zero = np.zeros(2, dtype=np.float32)
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


class SingleMoverEnvV1(SingleMoverEnv):
    """``cv2x/SingleMover-v1``: observation version 1 and improvement rewards (see ``docs/env.md``)."""

    version = 1


class SingleMoverEnvV2(SingleMoverEnv):
    """``cv2x/SingleMover-v2``: observation version 2 (the plan from the mover's sensing estimate) and
    improvement rewards (see ``docs/env.md``)."""

    version = 2


class SingleMoverEnvV3(SingleMoverEnv):
    """``cv2x/SingleMover-v3``: plan-free observation version 3 (measured RSRP, resources, interferers),
    shadowing that follows the mover, improvement rewards (see ``docs/env.md``). The observation's time
    left follows a shorter Gymnasium ``TimeLimit`` (``spec.max_episode_steps``) when one is in force."""

    version = 3


class TrafficEnv(SingleMoverEnv):
    """``cv2x/Traffic-v0``: vehicles drive the lane model and SPS runs one 100-ms period per step with live
    reselections; vehicle 0 commands its speed (``action[0]``: a target in [0, the speed limit], reached
    within ``accel_mps2`` / ``decel_mps2``) and its lane (``action[1]`` > 0.5 / < -0.5: one lane left /
    right, where one exists); the reward is the period's eq. 12 utility of its actual transmissions per
    target receiver; the observation is v0's block plus the driving entries; the infos carry the episode's
    means (:data:`~cv2x_marl.env.options.TRAFFIC_DEFAULTS`, ``docs/env.md``). ``preset="sumo-grid"``: SUMO
    drives instead of the lane model; the same id in PettingZoo is
    :class:`~cv2x_marl.env.traffic_parallel.TrafficParallelEnv`."""

    defaults = "traffic-v0"
    label = "Traffic-v0"


class TrafficEnvV1(TrafficEnv):
    """``cv2x/Traffic-v1``: :class:`TrafficEnv` (the same driving, SPS periods, reward and infos) observing what
    the mover measured on the road, observation version 4 (:data:`~cv2x_marl.env.options.TRAFFIC_V1_DEFAULTS`;
    :mod:`cv2x_marl.env.traffic_measurement`): per neighbour the RSRP over its sensing window of the packets it
    decoded, the measurement's age, the resource and reselection announcement of the last SCI it decoded; its
    own resource and reselection counter; the utility and its change; the driving entries (``docs/env.md``)."""

    defaults = "traffic-v1"
    label = "Traffic-v1"
