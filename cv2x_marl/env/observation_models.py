"""One observation model per observation version: what the version keeps, updates and writes.

:class:`~cv2x_marl.env.mobility_env.MobilityEnv` picks the model of its ``observation`` option once, at
construction (:func:`observation_model`), and calls it at fixed points of an episode:

    reset          after the start's links and utilities: the version's state (own state, plan, measurements)
    after_links    after each step's links and utilities: one more period of measurements
    after_reward   after each step's reward: the own state and, version 2 with ``replan_every``, a new plan
    fill           the version's entries after the v0 block of agents ``rows`` (the v0 block, and the model /
                   true link success of versions 1 and 2, come from :func:`~cv2x_marl.env.observation.
                   build_observations`, the driving entries from ``drive_observation``)

and the one-mover path of :meth:`MobilityEnv.step_mover` its ``*_mover`` twins, which compute the same values for
one vehicle with the same arithmetic. The layout's sizes of each version are
:data:`~cv2x_marl.env.observation.VERSION_BLOCKS`.

Adding a version is one class here or in a file of its own, registered with :func:`register_observation` (its
sizes, and the ``observation`` option then accepts it); ``docs/architecture.md`` has a worked example and
``tests/env/test_observation_models.py`` registers a toy version from the test file alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env import step as step_core
from cv2x_marl.env import traffic_measurement as tmeas
from cv2x_marl.env.measurement import Measurements, scaled_rsrp
from cv2x_marl.env.observation import VERSION_BLOCKS, decode_observations
from cv2x_marl.env.observation_fills import fill_measured, fill_own_v3
from cv2x_marl.env.planning import (
    PLAN_GRID_M,
    SearchGridError,
    check_reach_grid,
    model_plan,
    reachable_set,
    sensing_plan,
)
from cv2x_marl.regression.model import load_model
from cv2x_marl.rng import env_stream

if TYPE_CHECKING:
    from cv2x_marl.env.episode import EpisodeEnv

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class OwnState:
    """The state behind the own entries of observation versions >= 1, [N] per vehicle.

    Attributes:
        u_now: utility after the last step (per target receiver).
        u_prev: utility after the step before.
        u_start: utility at the episode's start.
        u_best: best utility of the episode so far.
        best_m: [N, 2] where the best was seen (m).
    """

    u_now: FloatArray
    u_prev: FloatArray
    u_start: FloatArray
    u_best: FloatArray
    best_m: FloatArray

    @classmethod
    def start(cls, env: EpisodeEnv) -> OwnState:
        """Every field from the episode's start (utilities per target receiver)."""
        u = env.utility.copy() if env.normalise_reward else env.utility / np.maximum(env.target_count, 1)
        return cls(u, u.copy(), u.copy(), u.copy(), env.positions_m.copy())

    def update(self, env: EpisodeEnv) -> None:
        """After a step of every vehicle (:func:`~cv2x_marl.env.step.own_state_updates`), in place."""
        step_core.own_state_updates(
            env.utility, env.target_count, env.normalise_reward, self.u_now, self.u_prev, self.u_best, self.best_m,
            env.positions_m,
        )  # fmt: skip

    def update_mover(self, env: EpisodeEnv, i: int, u: float, count: int) -> None:
        """After a step of vehicle ``i`` alone, with utility ``u`` over ``count`` targets."""
        self.u_prev[i], self.u_now[i], self.u_best[i], better = step_core.own_state_update(
            step_core.per_receiver(u, count, env.normalise_reward), self.u_now[i], self.u_best[i]
        )
        if better:
            self.best_m[i] = env.positions_m[i]


class ObservationModel:
    """Observation version 0 (the paper's observation: the v0 block alone), and the base of every version.

    Attributes:
        version: the ``observation`` option's value.
        per_neighbour, own: the sizes the version adds (:data:`~cv2x_marl.env.observation.VERSION_BLOCKS`).
        state_per_pair: the global state's extra entries per pair of vehicles (:meth:`state_parts`).
    """

    version: ClassVar[int] = 0
    per_neighbour: ClassVar[int] = 0
    own: ClassVar[int] = 0
    state_per_pair: ClassVar[int] = 0
    #: the snapshot links also return each pair's received power (:meth:`SnapshotLinks.evaluate_rx`)
    needs_rx: ClassVar[bool] = False
    #: the simulator keeps each period's powers (traffic mode, :attr:`Simulator.keep_period_geometry`)
    keep_period_geometry: ClassVar[bool] = False

    def __init__(self, env: EpisodeEnv) -> None:
        """Load what the version needs and refuse what it cannot do, before any reset."""

    def reset(self, env: EpisodeEnv, episode_seed: int, cached_plan_m: FloatArray | None) -> None:
        """The version's state at the episode's start."""

    def after_links(self, env: EpisodeEnv) -> None:
        """After a step's links and utilities (every vehicle)."""

    def after_reward(self, env: EpisodeEnv) -> None:
        """After a step's reward (every vehicle)."""

    def fill(self, env: EpisodeEnv, obs: NDArray[np.float32], rows: IntArray) -> None:
        """Write the version's entries of agents ``rows`` into ``obs`` [len(rows), size] (the v0 block is there)."""

    def after_links_mover(self, env: EpisodeEnv, rows: IntArray) -> None:
        """:meth:`after_links` when only the vehicle in ``rows`` moved."""

    def after_reward_mover(self, env: EpisodeEnv, i: int, u: float, count: int) -> None:
        """:meth:`after_reward` when only vehicle ``i`` moved (utility ``u`` over ``count`` targets)."""

    def fill_mover(self, env: EpisodeEnv, obs: NDArray[np.float32], i: int) -> None:
        """:meth:`fill` of vehicle ``i`` alone (``obs`` [1, size])."""
        self.fill(env, obs, np.array([i], dtype=np.int64))

    def state_parts(self, env: EpisodeEnv) -> list[FloatArray]:
        """Extra entries of the global state (:meth:`MobilityEnv.state`), ``state_per_pair`` per pair."""
        return []


#: the observation model of each version (:func:`register_observation` adds one)
OBSERVATIONS: dict[int, type[ObservationModel]] = {}


def register_observation(model: type[ObservationModel]) -> type[ObservationModel]:
    """Make ``model`` the observation model of its ``version`` (a class decorator): the ``observation`` option
    accepts the version, the layout gets its sizes (:data:`~cv2x_marl.env.observation.VERSION_BLOCKS`)."""
    v = model.version
    if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
        raise ValueError(f"invalid observation version {v!r} of {model.__name__}; allowed: an integer >= 0")
    if v in OBSERVATIONS and OBSERVATIONS[v] is not model:
        raise ValueError(f"observation version {v} is taken by {OBSERVATIONS[v].__name__}")
    OBSERVATIONS[v] = model
    VERSION_BLOCKS[v] = (model.per_neighbour, model.own)
    return model


def observation_model(env: EpisodeEnv) -> ObservationModel:
    """The model of the env's observation version (:data:`OBSERVATIONS`)."""
    return OBSERVATIONS[env.layout.version](env)


class OwnStateModel(ObservationModel):
    """The versions with own entries (1 to 4): the own state, and the plan versions 1 and 2 observe."""

    def __init__(self, env: EpisodeEnv) -> None:
        if env.mode == "snapshot":  # the reach's search grid (the plan's, the ceiling's), refused before any reset
            try:
                check_reach_grid(env, PLAN_GRID_M, f"observation version {self.version}'s plan")
            except SearchGridError as exc:
                raise SearchGridError(
                    f"invalid env arguments max_cycles={env.max_cycles!r}, max_step_m={env.max_step_m!r}: {exc}"
                ) from None

    def reset(self, env: EpisodeEnv, episode_seed: int, cached_plan_m: FloatArray | None) -> None:
        env.own = OwnState.start(env)
        env.plan_m = env.positions_m.copy() if cached_plan_m is None else cached_plan_m.copy()

    def after_reward(self, env: EpisodeEnv) -> None:
        assert env.own is not None
        env.own.update(env)

    def after_reward_mover(self, env: EpisodeEnv, i: int, u: float, count: int) -> None:
        assert env.own is not None
        env.own.update_mover(env, i, u, count)


class PlanModel(OwnStateModel):
    """Versions 1 and 2: the own entries (:data:`~cv2x_marl.env.observation.OWN_V1_NAMES`) with a plan."""

    def fill(self, env: EpisodeEnv, obs: NDArray[np.float32], rows: IntArray) -> None:
        own, lay = env.own, env.layout
        assert own is not None and rows.size == env.n, "the block fills every vehicle"
        step_core.own_v1_block(
            obs, lay.own_v1_offset, lay.obs_clip, lay.scale_m, env.reach_m(), own.u_now, own.u_prev, own.u_start,
            own.u_best, own.best_m, env.plan_m, env.positions_m,
        )  # fmt: skip

    def fill_mover(self, env: EpisodeEnv, obs: NDArray[np.float32], i: int) -> None:
        own, lay, pos = env.own, env.layout, env.positions_m
        assert own is not None
        step_core.own_v1_entries(
            obs[0], lay.own_v1_offset, lay.obs_clip, lay.scale_m, env.reach_m(), own.u_now[i], own.u_prev[i],
            own.u_start[i], own.u_best[i], own.best_m[i, 0], own.best_m[i, 1], env.plan_m[i, 0], env.plan_m[i, 1],
            pos[i, 0], pos[i, 1],
        )  # fmt: skip


@register_observation
class ModelPlanObservation(PlanModel):
    """Version 1: the two-distance model's predicted link success per neighbour, the plan it gives."""

    version = 1
    per_neighbour, own = VERSION_BLOCKS[1]

    def __init__(self, env: EpisodeEnv) -> None:
        try:
            env.model = load_model(Path(env.model_name))
        except Exception as exc:
            raise ValueError(f"invalid env argument model={env.model_name!r}: {exc}") from exc
        super().__init__(env)

    def reset(self, env: EpisodeEnv, episode_seed: int, cached_plan_m: FloatArray | None) -> None:
        super().reset(env, episode_seed, cached_plan_m)
        movers = np.flatnonzero(env.mover_mask)
        if cached_plan_m is None and env.mode == "snapshot" and movers.size:
            v0 = env.build(movers)[:, : env.layout.v0_size]
            reaches = [reachable_set(env, int(i)) for i in movers]
            inputs = decode_observations(v0, env.layout)
            env.plan_m[movers] = model_plan(inputs, env.positions_m[movers], reaches, env.model, env.p_min)


@register_observation
class SensingPlanObservation(ModelPlanObservation):
    """Version 2: version 1's entries with the plan from the mover's own sensing estimate (``replan_every``)."""

    version = 2
    per_neighbour, own = VERSION_BLOCKS[2]

    def reset(self, env: EpisodeEnv, episode_seed: int, cached_plan_m: FloatArray | None) -> None:
        OwnStateModel.reset(self, env, episode_seed, cached_plan_m)
        movers = np.flatnonzero(env.mover_mask)
        if cached_plan_m is None and env.mode == "snapshot" and movers.size:
            env.plan_m[movers] = sensing_plan(env, movers)

    def after_reward(self, env: EpisodeEnv) -> None:
        super().after_reward(env)
        self._replan(env)

    def after_reward_mover(self, env: EpisodeEnv, i: int, u: float, count: int) -> None:
        super().after_reward_mover(env, i, u, count)
        self._replan(env)

    @staticmethod
    def _replan(env: EpisodeEnv) -> None:
        """With ``replan_every``: a new sensing plan from where everyone is, while the movers still move."""
        every = env.replan_every
        if every is None or env.mode != "snapshot" or env.t % every or env.t >= env.max_cycles - env.settle_steps:
            return
        movers = np.flatnonzero(env.mover_mask)
        if movers.size:
            env.plan_m[movers] = sensing_plan(env, movers)


@register_observation
class MeasuredObservation(OwnStateModel):
    """Version 3: what each vehicle measured (RSRP over its sensing window, :mod:`cv2x_marl.env.measurement`),
    plan-free own entries (:data:`~cv2x_marl.env.observation.OWN_V3_NAMES`)."""

    version = 3
    per_neighbour, own = VERSION_BLOCKS[3]
    state_per_pair = 2
    needs_rx = True

    def reset(self, env: EpisodeEnv, episode_seed: int, cached_plan_m: FloatArray | None) -> None:
        super().reset(env, episode_seed, cached_plan_m)
        o = env.options
        rng = env_stream(episode_seed, "measurement")
        env.measure = Measurements.start(env.rx_dbm, env.link_p, o.sensing_window, o.rsrp_error_db, rng)

    def after_links(self, env: EpisodeEnv) -> None:
        env.measure.update(env.rx_dbm, env.link_p)  # one more period of sensing at the new positions

    def after_links_mover(self, env: EpisodeEnv, rows: IntArray) -> None:
        env.measure.update(env.rx_dbm, env.link_p, rows)  # every pair's draws, the mover's column of reports

    def fill(self, env: EpisodeEnv, obs: NDArray[np.float32], rows: IntArray) -> None:
        assert env.co_table is not None and env.geometry is not None and env.own is not None
        m, cfg, own = env.measure, env.config, env.own
        slot, sub = np.divmod(env.resource, cfg.sps.n_subchannels)
        fill_measured(
            obs, env.layout, env.geometry, env.co_table, scaled_rsrp(m.rsrp_dbm), m.age / m.window,
            slot / cfg.traffic.rri_ms, sub / cfg.sps.n_subchannels, rows,
        )  # fmt: skip
        left = max(env.horizon - env.t, 0)
        moving = max(min(env.horizon, env.max_cycles - env.settle_steps) - env.t, 0)
        fill_own_v3(
            obs, env.layout, own.u_now[rows], own.u_prev[rows], (env.positions_m - env.start_m)[rows],
            left / env.horizon, moving * env.max_step_m,
        )  # fmt: skip

    def fill_mover(self, env: EpisodeEnv, obs: NDArray[np.float32], i: int) -> None:
        self.fill(env, obs, np.array([i], dtype=np.int64))

    def state_parts(self, env: EpisodeEnv) -> list[FloatArray]:
        """Every vehicle's RSRP reports, scaled as in the observation, and their ages / window [tx, rx]."""
        return [scaled_rsrp(env.measure.rsrp_dbm).ravel(), (env.measure.age / env.measure.window).ravel()]


@register_observation
class RoadMeasuredObservation(OwnStateModel):
    """Version 4 (``cv2x/Traffic-v1``): what the mover measured on the road: RSRP and decoded SCIs from the
    simulator's periods, its own SPS state (:mod:`cv2x_marl.env.traffic_measurement`)."""

    version = 4
    per_neighbour, own = VERSION_BLOCKS[4]

    keep_period_geometry = True

    def reset(self, env: EpisodeEnv, episode_seed: int, cached_plan_m: FloatArray | None) -> None:
        super().reset(env, episode_seed, cached_plan_m)
        env.traffic_measure = tmeas.start_measurements(env, episode_seed)

    def after_links(self, env: EpisodeEnv) -> None:
        env.traffic_measure.update(env.sim)

    def fill(self, env: EpisodeEnv, obs: NDArray[np.float32], rows: IntArray) -> None:
        tmeas.fill_observations(env, obs, rows)


register_observation(ObservationModel)
