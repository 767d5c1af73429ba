"""Episode starts worth keeping: the process-wide reset cache and the start pool.

A start is what :meth:`~cv2x_marl.env.mobility_env.MobilityEnv.reset` computes for an episode seed before
the first step: the stage-1 run (SPS warm-up, 20-30 ms) and its snapshot, the snapshot's links (with the
episode's shadowing field) and the plan. In traffic mode it is the simulator after its warm-up (most of a
``cv2x/Traffic-v0`` reset): the episode runs that simulator on, so the cache keeps a copy of it and every
episode from the cache runs on a fresh copy of that (:func:`copy_simulator`: its state and random streams
copied, so the episode is the fresh one bit for bit). SUMO lockstep (``vehicles.mobility=sumo``) is
refused there: libsumo's one simulation per process cannot be copied.

``reset_cache=C`` keeps up to C of them in :data:`START_CACHE`, shared by every env of the process with the
same settings, so that ``reset(seed=s)`` for a cached ``s`` reuses them (bit-identical to computing them).
``start_pool=P`` makes ``reset()`` without a seed draw its episode seed from the first P seeds of the
protocol's training list (:func:`cv2x_marl.env.seeds.training_pool`, disjoint from every task's held-out
list) and keeps their starts (the cache holds at least P): after the first P distinct starts, resets cost a
copy of the start.
"""

from __future__ import annotations

import copy
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.options import EPISODE_ROLES, options_with_role
from cv2x_marl.env.seeds import training_pool
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.ground_truth import SnapshotLinks

#: a :class:`~cv2x_marl.env.mobility_env.MobilityEnv` (not imported: it imports this module)
MobilityEnv = Any


@dataclass(frozen=True)
class Start:
    """What :meth:`MobilityEnv.reset` computes for an episode seed that is worth keeping: the
    stage-1 run (SPS warm-up) and its snapshot, the snapshot's links and the plan (shared, never
    modified in snapshot mode; in traffic mode ``links`` is None and the simulator is a kept copy)."""

    sim: Simulator
    snapshot: Any
    links: SnapshotLinks | None
    plan_m: NDArray[np.float64]

    def open(self) -> tuple[Simulator, Any, SnapshotLinks | None]:
        """The simulator, snapshot and links an episode starts from: shared in snapshot mode (never
        modified), a fresh copy of the simulator in traffic mode (the episode runs it on)."""
        return (self.sim if self.links is not None else copy_simulator(self.sim)), self.snapshot, self.links


def copy_simulator(sim: Simulator) -> Simulator:
    """An independent copy of a simulator (state, SPS scheduler, random streams; the frozen configuration
    shared): running it gives what running ``sim`` would, bit for bit."""
    return copy.deepcopy(sim, {id(sim.config): sim.config})


#: process-wide cache of episode starts: key -> start, oldest first (``reset_cache`` bounds it)
START_CACHE: OrderedDict[tuple[Any, ...], Start] = OrderedDict()


#: the options of :func:`start_key` (the scenario's own, ``preset``, ``overrides`` and ``config``, enter as the
#: scenario they give)
START_OPTIONS = tuple(n for n in options_with_role(*EPISODE_ROLES) if n not in ("preset", "overrides", "config"))


def start_key(env: MobilityEnv, seed: int) -> tuple[Any, ...]:
    """Everything a start may depend on: the scenario, every option an episode is made of (by role:
    :data:`~cv2x_marl.env.options.EPISODE_ROLES`; the plan reads the observation, the reach and ``p_min``) and
    the seed."""
    o = env.options
    values = tuple(repr(getattr(o, name)) for name in START_OPTIONS)
    return (repr(env.config), values, int(seed))


def cached_start(env: MobilityEnv, seed: int) -> Start | None:
    key = start_key(env, seed)
    start = START_CACHE.get(key)
    if start is not None:
        START_CACHE.move_to_end(key)
    return start


def store_start(env: MobilityEnv, seed: int) -> None:
    plan = getattr(env, "plan_m", env.positions_m)
    sim, links = (env.sim, env.links) if env.mode == "snapshot" else (copy_simulator(env.sim), None)
    START_CACHE[start_key(env, seed)] = Start(sim, env.snapshot, links, np.array(plan, dtype=np.float64))
    while len(START_CACHE) > cache_size(env):
        START_CACHE.popitem(last=False)


def cache_size(env: MobilityEnv) -> int:
    """Starts the env keeps: ``max(reset_cache, start_pool)``."""
    return max(env.reset_cache, env.start_pool)


def pool_seed(env: MobilityEnv, rng: np.random.Generator) -> int:
    """The episode seed of a ``reset()`` without a seed when ``start_pool`` is set: one of the pool's
    seeds, uniformly, drawn from the env's generator ``rng``."""
    pool = training_pool(env.start_pool)
    return int(pool[int(rng.integers(len(pool)))])


def episode_seed(env: MobilityEnv, seed: int | None) -> int:
    """The episode seed of ``env.reset(seed=seed)``, as Gymnasium seeds: ``seed`` itself, reseeding the env's own
    generator with it; without a seed a draw from that generator (OS entropy the first time), or with
    ``start_pool`` one of the pool's seeds (:func:`pool_seed`)."""
    if seed is not None:
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
            raise ValueError(f"invalid reset seed={seed!r}; allowed: an integer >= 0 or None")
        env._np_random = np.random.default_rng(int(seed))
        return int(seed)
    if env._np_random is None:
        env._np_random = np.random.default_rng()
    if env.start_pool:
        return pool_seed(env, env._np_random)
    return int(env._np_random.integers(0, 2**31 - 1))


def open_start(env: MobilityEnv, seed: int) -> Start | None:
    """Set the episode's simulator, snapshot (and in snapshot mode its links) on ``env``: a kept start when the
    cache holds one (returned; traffic mode runs on a copy of its simulator), else a fresh stage-1 run (None)."""
    cached = cached_start(env, seed) if cache_size(env) > 0 else None
    if cached is None:
        env.sim = Simulator(env.config)
        env.sim.keep_period_geometry = env.observer.keep_period_geometry
        env.sim.scheduler.record_selections = env.dynamics.record_selections
        env.snapshot = env.sim.reset(seed)
        env.dynamics.start(seed)
        return None
    env.sim, env.snapshot, links = cached.open()
    if links is not None:
        env.links = links
    return cached
