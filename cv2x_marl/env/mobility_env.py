"""The controlled-mobility ParallelEnv: every vehicle an agent, an action a position offset.

A thin layer over the simulator (``cv2x_marl.sim``): it holds no physics. Rewards are the eq. 12
utility of each agent's broadcast computed with the simulator's link model
(:class:`cv2x_marl.sim.ground_truth.SnapshotLinks` in ``snapshot`` mode, the period's own link
outcomes in ``traffic`` mode), never with the regression model.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray
from pettingzoo import ParallelEnv

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.env import starts
from cv2x_marl.env import step as step_core
from cv2x_marl.env import traffic_measurement as tmeas
from cv2x_marl.env.measurement import Measurements, scaled_rsrp
from cv2x_marl.env.mover_links import MoverLinksStep
from cv2x_marl.env.observation import (
    ObservationLayout,
    build_observations,
    co_channel_table,
    decode_observations,
    fill_drive,
    fill_measured,
    fill_own_v3,
)
from cv2x_marl.env.options import (
    EnvOptions,
)
from cv2x_marl.env.planning import (
    PLAN_GRID_M,
    SearchGridError,
    check_reach_grid,
    model_plan,
    reachable_set,
    sensing_plan,
)
from cv2x_marl.env.team_search import difference_rewards
from cv2x_marl.rng import env_stream
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.ground_truth import PairGeometry, SnapshotLinks, pair_geometry
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.sim.road import Road
from cv2x_marl.sim.shadow_field import ShadowField

#: keys of every agent's info dict (all floats; ``clipped`` is 1.0 when the action left the box)
INFO_KEYS = ("utility", "utility_start", "prr", "prr_start", "jain", "offset_x_m", "offset_y_m", "clipped")
#: the infos' keys added by ``episode_metrics`` (the means over the episode's steps so far), and with
#: ``drive_observation`` (the vehicle's speed and lane now)
EPISODE_INFO_KEYS, DRIVE_INFO_KEYS = ("utility_mean", "prr_mean", "jain_mean"), ("speed_mps", "lane")


def check_copies(env: MobilityEnv, copies: int) -> None:
    """Refuse several copies of a traffic-mode env on SUMO lockstep in one process: libsumo runs one
    simulation per process, so each copy's reset would stop the others' (use one process per copy,
    e.g. ``vectorization_mode="async"``, or a trace: ``vehicles.mobility=trace``)."""
    if copies > 1 and env.mode == "traffic" and env.config.vehicles.mobility == "sumo":
        raise ValueError(
            f"{copies} copies of a traffic-mode env with vehicles.mobility=sumo cannot share one process "
            "(libsumo runs one simulation per process); use one process per copy (vectorization_mode='async') "
            "or replay a trace (vehicles.mobility=trace)"
        )


class MobilityEnv(ParallelEnv):
    """Controlled mobility in a C-V2X Mode 4 network (PettingZoo ParallelEnv).

    Args:
        preset: scenario preset (``paper``: the paper's 21-vehicle grid; ``highway``: the TR 36.885 highway
            with the standard's Mode 4 procedures; ``highway-legacy``: with the paper's simplified ones).
        overrides: ``section.key=value`` strings applied to the preset (a single string is one
            assignment); anything else is refused naming ``overrides``.
        config: a full :class:`ScenarioConfig` (takes precedence over preset/overrides).
        mode: ``snapshot`` (positions and SPS resources of a stage-1 snapshot; only the agents'
            offsets move the vehicles) or ``traffic`` (vehicles drive, SPS runs one period per
            step, agents add bounded offsets to their road positions).
        max_cycles: steps per episode (truncation, all agents together), 1 .. :data:`~cv2x_marl.env.options.MAX_CYCLES`.
        max_step_m: offset of a full action (actions are ``Box(-1, 1, (2,))`` times this); at most the
            diagonal of the scene (the road box: 636.4 m for ``paper``, 2000.1 m for ``highway``). With
            observation >= 1 in snapshot mode the plan searches the reachable square (``2 x max_cycles x
            max_step_m`` wide, unless ``max_drift_m`` or ``roi`` bound it) on a 20 m grid, which must fit
            :data:`~cv2x_marl.env.planning.MAX_GRID_POINTS` (``max_step_m`` up to 199.9 m with 100
            steps); larger ones are refused with the figure.
        movers: indices of the vehicles whose actions move them (None: all); the others stay put.
        reward: ``individual`` (own eq. 12 utility), ``team`` (mean over agents) or ``mixed``
            (``local_ratio`` individual + ``1 - local_ratio`` team).
        local_ratio: weight of the individual part in ``mixed``.
        normalise_reward: divide each utility by the number of target receivers.
        p_min: clip of P inside the log (eq. 12).
        n_neighbours: other vehicles in the observation (default N - 1).
        scale_m: length unit of the observation.
        max_drift_m: optional bound on the distance from the start position (traffic: default 10 m).
        roi: keep vehicles inside the region of interest (the road box).
        truth_los: LOS state of moved links (``snapshot``, ``geometry``, ``always``).
        render_mode: ``rgb_array``, ``human`` or None.
        observation: observation version (0 .. 4, see :mod:`cv2x_marl.env.observation`; 4: ``cv2x/Traffic-v1``).
        privileged: versions 1 and 2 only: also observe the true success of every neighbour link (for
            upper-bound studies; a vehicle cannot know it).
        reward_form: ``utility`` (the reward is the utility after the step) or ``improvement``
            (its change over the step: the episode's rewards sum to final minus start).
        settle_steps: the last ``settle_steps`` steps of an episode ignore the actions (vehicles
            stay where they are, the reward counts where they ended up).
        model: the two-distance model of observation version 1 (``paper-table2`` or a model file).
        replan_every: observation version 2: recompute the sensing plan every ``replan_every`` steps
            from where every vehicle is then (None: once, at reset).
        traffic_action: traffic mode: ``offset`` (the action moves the vehicle's radio position
            off its road position, bounded by ``max_drift_m``; the traffic itself does not see it) or
            ``speed`` (``vehicles.mobility=sumo`` only: a command SUMO honours: ``action[0]`` in
            [-1, 1] sets the target speed from 0 to ``vehicles.speed_max_mps``, ``action[1]`` > 0.5 /
            < -0.5 asks for one lane to the left / right; SUMO applies them within its acceleration,
            deceleration and car-following safety; see ``docs/mobility.md``).
        action_mode: ``offset`` (the action is the step) or ``plan_residual`` (observation >= 1,
            snapshot mode: the action corrects the straight step towards the observed plan, so a zero
            action follows the plan; residual policy learning, Silver et al. 2018).
        team_objective: the team part of ``team`` / ``mixed`` rewards: mean ``utility`` or mean ``prr``.
        shadow_field: shadowing that follows the vehicles (:mod:`cv2x_marl.sim.shadow_field`).
        sensing_window: observation 3: periods of the RSRP average (:mod:`cv2x_marl.env.measurement`).
        rsrp_error_db: observation 3: standard deviation of the RSRP report error (dB).
        start_pool: ``reset()`` without a seed starts from one of the first ``start_pool`` seeds of the
            protocol's training list, their starts kept (:mod:`cv2x_marl.env.starts`); 0: fresh seeds.
        accel_mps2, decel_mps2, speed_command, drive_observation, episode_metrics: the driving on the lane
            model (:class:`~cv2x_marl.env.options.EnvOptions`; :data:`EPISODE_INFO_KEYS`, :data:`DRIVE_INFO_KEYS`).
    """

    metadata: ClassVar[dict[str, Any]] = {
        "name": "cv2x_mobility_v0",
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        preset: str = "paper",
        overrides: Sequence[str] = (),
        config: ScenarioConfig | None = None,
        mode: str = "snapshot",
        max_cycles: int = 100,
        max_step_m: float = 5.0,
        movers: Sequence[int] | None = None,
        reward: str = "individual",
        local_ratio: float = 0.5,
        normalise_reward: bool = False,
        p_min: float = 1e-3,
        n_neighbours: int | None = None,
        scale_m: float = 100.0,
        max_drift_m: float | None = None,
        roi: bool = False,
        truth_los: str = "snapshot",
        render_mode: str | None = None,
        observation: int = 0,
        privileged: bool = False,
        reward_form: str = "utility",
        settle_steps: int = 0,
        model: str = "paper-table2",
        action_mode: str = "offset",
        replan_every: int | None = None,
        reset_cache: int = 0,
        traffic_action: str = "offset",
        team_objective: str = "utility",
        shadow_field: bool = False,
        sensing_window: int = 10,
        rsrp_error_db: float = 3.0,
        start_pool: int = 0,
        accel_mps2: float = 2.6,
        speed_command: str = "target",
        decel_mps2: float = 3.4,
        drive_observation: bool = False,
        episode_metrics: bool = False,
    ) -> None:
        opts = EnvOptions(
            preset=preset, overrides=overrides, config=config, mode=mode, max_cycles=max_cycles,
            max_step_m=max_step_m, movers=movers, reward=reward, local_ratio=local_ratio,
            normalise_reward=normalise_reward, p_min=p_min, n_neighbours=n_neighbours, scale_m=scale_m,
            max_drift_m=max_drift_m, roi=roi, truth_los=truth_los, render_mode=render_mode, observation=observation,
            privileged=privileged, reward_form=reward_form, settle_steps=settle_steps, model=model,
            action_mode=action_mode, replan_every=replan_every, reset_cache=reset_cache, traffic_action=traffic_action,
            team_objective=team_objective, shadow_field=shadow_field, sensing_window=sensing_window,
            rsrp_error_db=rsrp_error_db, start_pool=start_pool, accel_mps2=accel_mps2, speed_command=speed_command,
            decel_mps2=decel_mps2,
            drive_observation=drive_observation, episode_metrics=episode_metrics,
        )  # fmt: skip
        cfg = opts.scenario()
        road = Road.from_config(cfg.road)
        box = road.box_m
        #: [2] the scene's road box (m; a square of the road's length on the highway)
        self.box_m = np.array(box if np.isfinite(box[1]) else (box[0], box[0]))
        opts.check_scenario(cfg, float(np.hypot(*self.box_m)), self.box_m)
        if cfg.vehicles.population == "open":
            raise ConfigError(
                "the env needs vehicles.population=fixed: its agents are the vehicles of the scenario, a fixed set "
                "per episode (open populations, where vehicles enter and leave, are for the simulator: "
                "cv2x-marl simulate, docs/mobility.md)"
            )
        #: the validated options (:class:`~cv2x_marl.env.options.EnvOptions`)
        self.options = opts
        self.config = cfg
        self.n = cfg.n_vehicles
        self.mode = mode
        self.max_cycles = max_cycles
        #: the horizon in force (steps): ``max_cycles`` or a shorter Gymnasium ``TimeLimit`` (v3's time left)
        self.horizon = max_cycles
        self.max_step_m = float(max_step_m)
        self.reward_kind = reward
        self.local_ratio = local_ratio
        self.normalise_reward = normalise_reward
        self.p_min = p_min
        self.max_drift_m = max_drift_m if max_drift_m is not None or mode == "snapshot" else 10.0
        self._drift_m = np.inf if self.max_drift_m is None else float(self.max_drift_m)  # the kernels' "none"
        self.roi = roi
        self.truth_los = truth_los
        self.render_mode = render_mode
        self.traffic_action = traffic_action
        self.reward_form = reward_form
        self._improvement = reward_form == "improvement"
        self.replan_every = replan_every
        self.action_mode = action_mode
        self.settle_steps = settle_steps
        #: starts kept in the process-wide cache of :meth:`reset` (0: none); see :mod:`cv2x_marl.env.starts`
        self.reset_cache = int(reset_cache)
        #: ``reset()`` without a seed draws from the first ``start_pool`` training seeds (0: fresh seeds)
        self.start_pool = int(start_pool)
        self.possible_agents = [f"vehicle_{i}" for i in range(self.n)]
        self.agent_index = {a: i for i, a in enumerate(self.possible_agents)}
        self.mover_mask = np.ones(self.n, dtype=bool)
        if movers is not None:
            self.mover_mask[:] = False
            self.mover_mask[list(movers)] = True
        self._step_scale_m = self.max_step_m * self.mover_mask.astype(np.float64)  # [N]: 0 for who stays put
        self._wrap_road = road if cfg.road.wrap_distances else None
        #: [2] the torus of the pair geometry (inf where distances do not wrap)
        self.period_m = np.asarray(road.periodic_box_m if cfg.road.wrap_distances else np.full(2, np.inf), dtype=float)
        self._geometry: PairGeometry | None = None
        self.layout = ObservationLayout(
            self.n - 1 if n_neighbours is None else n_neighbours,
            scale_m, float(max(box)), cfg.metrics.interferer_range_m, 10.0, observation, privileged,
            drive_observation,
        )  # fmt: skip
        #: the infos' keys (with ``episode_metrics`` also :data:`EPISODE_INFO_KEYS`, :data:`DRIVE_INFO_KEYS`)
        self.info_keys: tuple[str, ...] = INFO_KEYS + (EPISODE_INFO_KEYS if episode_metrics else ())
        self.info_keys += DRIVE_INFO_KEYS if episode_metrics and drive_observation else ()
        #: the lane model drives the movers (``traffic_action="speed"``, ``vehicles.mobility=model``)
        self.drives = mode == "traffic" and traffic_action == "speed" and cfg.vehicles.mobility == "model"
        self.model_name = model
        self.model: Any = None
        if observation in (1, 2):
            from cv2x_marl.regression.model import load_model

            try:
                self.model = load_model(Path(model))
            except Exception as exc:
                raise ValueError(f"invalid env argument model={model!r}: {exc}") from exc
        if self.layout.version >= 1 and mode == "snapshot":  # the plan's search, refused before any reset
            try:
                check_reach_grid(self, PLAN_GRID_M, f"observation version {self.layout.version}'s plan")
            except SearchGridError as exc:
                raise SearchGridError(
                    f"invalid env arguments max_cycles={max_cycles!r}, max_step_m={max_step_m!r}: {exc}"
                ) from None
        self._np_random: np.random.Generator | None = None
        clip = self.layout.obs_clip
        self._obs_space = spaces.Box(-clip, clip, (self.layout.size,), np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        state_size = self.n * 6 + (2 * self.n * self.n if observation == 3 else 0)
        self.state_space = spaces.Box(-clip, clip, (state_size,), np.float32)
        self.agents: list[str] = []
        self._fig: Any = None

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space

    # ------------------------------------------------------------------- reset
    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        """Start an episode. Seeding follows Gymnasium: ``reset(seed=s)`` makes this episode a function of
        ``s`` and reseeds the env's own generator with ``s``; a later ``reset()`` draws its episode seed
        from that generator, so the same seeded first reset gives the same sequence of episodes.
        Without any seed the generator starts from OS entropy."""
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
                raise ValueError(f"invalid reset seed={seed!r}; allowed: an integer >= 0 or None")
            self._np_random = np.random.default_rng(int(seed))
            episode_seed = int(seed)
        else:
            if self._np_random is None:
                self._np_random = np.random.default_rng()
            if self.start_pool:
                episode_seed = starts.pool_seed(self, self._np_random)
            else:
                episode_seed = int(self._np_random.integers(0, 2**31 - 1))
        self.seed_used = episode_seed
        keep = starts.cache_size(self) > 0
        cached = starts.cached_start(self, episode_seed) if keep else None
        if cached is None:
            self.sim = Simulator(self.config)
            self.sim.keep_period_geometry = self.layout.version == 4  # Traffic-v1 measures each period's powers
            snap = self.sim.reset(self.seed_used)
            if self.mode == "snapshot":
                field = None
                if self.options.shadow_field:
                    rng = env_stream(episode_seed, "shadow_field")
                    field = ShadowField.draw(self.config, snap.positions_m, snap.shadowing_db, snap.los, rng)
                self.links = SnapshotLinks(self.config, snap, self.truth_los, field=field)
        else:  # traffic mode: a copy of the kept simulator (the episode runs it on); links are snapshot mode's
            self.sim, snap, links = cached.open()
            if links is not None:
                self.links = links
        self.snapshot = snap
        self.start_m = snap.positions_m.copy()
        self.positions_m = snap.positions_m.copy()
        self.resource = snap.slot * snap.n_subchannels + snap.subchannel
        self.offsets_m = np.zeros((self.n, 2))
        self._mover_row: Any = None
        self._co_resource = self.resource.copy()
        self._co_table: NDArray[np.int64] | None = None
        self.t = 0
        self.agents = self.possible_agents[:]
        self._live = set(self.agents)
        self.tracks = [self.positions_m.copy()]
        self.link_p, self.target = self._link_success()
        self._summarise()
        self.u0 = self.utility.copy()
        self.prr0 = self.prr.copy()
        self._u_sum = np.zeros(self.n)  # sums over the episode's steps (episode_metrics)
        self._prr_sum = np.zeros(self.n)
        self._jain_sum = np.zeros(self.n)
        self._base_prev = self._rewards(self.utility).copy()
        if self.layout.version >= 1:
            self._reset_v1_state(None if cached is None else cached.plan_m)
        if self.layout.version == 3:
            o = self.options
            rng = env_stream(episode_seed, "measurement")
            self.measure = Measurements.start(self._rx_dbm, self.link_p, o.sensing_window, o.rsrp_error_db, rng)
        if self.layout.version == 4:  # Traffic-v1: RSRP and SCI reports from the simulator's periods
            self.traffic_measure = tmeas.start_measurements(self, episode_seed)
        if keep and cached is None:
            starts.store_start(self, episode_seed)
        obs = self._observations()
        infos = self._infos(np.zeros((self.n, 2)), np.zeros(self.n, dtype=bool))
        return obs, infos

    # -------------------------------------------------------------------- step
    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("step() called on a finished episode: call reset()")
        act = self._decode(actions)
        settle = self.t >= self.max_cycles - self.settle_steps  # settle phase: vehicles stay where they are
        if self.mode == "snapshot":
            plan = self.plan_m if self.action_mode == "plan_residual" else self.positions_m
            self.positions_m, applied, clipped = step_core.move_vehicles(
                act, self.positions_m, self.start_m, plan, self._step_scale_m, self.max_step_m,
                self.action_mode == "plan_residual", settle, self._drift_m, self.roi, self.box_m,
            )  # fmt: skip
        elif self.traffic_action == "speed":
            clipped = np.asarray(((act < -1.0) | (act > 1.0)).any(axis=1))
            if self.drives:
                self._command_drive(act)
            else:
                self._command_sumo(act)
            applied = np.zeros((self.n, 2))
            self.sim.run(self.sim.rri, record=False)
            self.resource = self.sim.resource.copy()
            self.positions_m = self._traffic_positions()
        else:
            self.offsets_m, applied, clipped = step_core.traffic_offsets(
                act, self.offsets_m, self._step_scale_m, settle, self._drift_m
            )
            self.sim.set_offsets(self.offsets_m)
            self.sim.run(self.sim.rri, record=False)
            self.resource = self.sim.resource.copy()
            self.positions_m = self._traffic_positions()
        self.t += 1
        self.tracks.append(self.positions_m.copy())
        self.link_p, self.target = self._link_success()
        self._summarise()
        self._u_sum += self.utility
        self._prr_sum += self.prr
        self._jain_sum += self.jain
        if self.layout.version == 3:  # one more period of sensing at the new positions
            self.measure.update(self._rx_dbm, self.link_p)
        elif self.layout.version == 4:
            self.traffic_measure.update(self.sim)
        rewards_arr = step_core.step_rewards(self._rewards(self.utility), self._base_prev, self._improvement)
        if self.layout.version >= 1:
            step_core.own_state_updates(
                self.utility, self._target_count, self.normalise_reward, self._u_now, self._u_prev, self._u_best,
                self._best_m, self.positions_m,
            )  # fmt: skip
            self._maybe_replan()
        done = self.t >= self.max_cycles
        agents = self.agents
        obs = self._observations()
        rewards = dict(zip(agents, rewards_arr.tolist(), strict=True))
        terms = dict.fromkeys(agents, False)
        truncs = dict.fromkeys(agents, done)
        infos = self._infos(applied, clipped)
        if done:
            self.agents = []
            self._live = set()
        if self.render_mode == "human":
            self.render()
        return obs, rewards, terms, truncs, infos

    # ------------------------------------------------------- one-mover path
    @property
    def fast_mover(self) -> int | None:
        """The vehicle whose step :meth:`step_mover` computes alone, or None when it does not apply
        (it needs snapshot mode, one mover and the individual reward; with observation version 3 or the
        shadowing field also the compiled link kernels: WINNER+ B1, ``truth_los`` snapshot or always)."""
        movers = np.flatnonzero(self.mover_mask)
        ok = self.mode == "snapshot" and movers.size == 1 and self.reward_kind == "individual"
        if self.layout.version == 3 or self.options.shadow_field:
            ok = ok and self.config.channel.pathloss == "winner_b1" and self.truth_los != "geometry"
        return int(movers[0]) if ok else None

    def step_mover(self, action: Any) -> tuple[NDArray[np.float32], float, bool, dict[str, float]]:
        """One step in which only :attr:`fast_mover` moves: its observation, reward, truncation, info.

        What :meth:`step` returns for that vehicle, bit for bit, computed for it alone with the same
        step functions (:mod:`cv2x_marl.env.step`; the batched copies of :mod:`cv2x_marl.env.mover_batch`
        call them too): its links through :meth:`SnapshotLinks.mover_row` (the interference on them
        does not change while the others stand still), its row of the pair geometry and its observation. With
        the shadowing field or observation version 3 its row and column (what it hears: P and received
        power, for its measurements) read the field once (:class:`~cv2x_marl.env.mover_links.MoverLinksStep`);
        the measurement stream draws every pair's period as :meth:`step` does. The other vehicles' rewards,
        observations and measurements are not kept current, so after this call use only
        ``step_mover`` until the next :meth:`reset` (``SingleMover`` envs do).
        """
        i = self.fast_mover
        if i is None:
            raise RuntimeError("step_mover needs snapshot mode, exactly one mover and reward='individual'")
        if not self.agents:
            raise RuntimeError("step() called on a finished episode: call reset()")
        name = self.possible_agents[i]
        try:
            act = np.asarray(action, dtype=np.float64).reshape(2)
        except (ValueError, TypeError):
            raise ValueError(f"action of {name} must be numeric with shape (2,), got {action!r}") from None
        if not np.isfinite(act).all():
            raise ValueError(f"action of {name} is not finite: {act.tolist()}")
        clipped = bool(step_core.is_clipped(act[0], act[1]))
        pos = self.positions_m
        old_x, old_y = pos[i]
        plan_x, plan_y = self.plan_m[i] if self.action_mode == "plan_residual" else (old_x, old_y)
        pos[i] = step_core.move_vehicle(
            act[0], act[1], old_x, old_y, self.start_m[i, 0], self.start_m[i, 1], plan_x, plan_y,
            self.max_step_m, self.max_step_m, self.action_mode == "plan_residual",
            self.t >= self.max_cycles - self.settle_steps, self._drift_m, self.roi, self.box_m[0], self.box_m[1],
        )  # fmt: skip
        self.t += 1
        self.tracks.append(pos.copy())
        v3 = self.layout.version == 3
        if self._mover_row is None or self._mover_row.mover != i:
            self._mover_rows = np.array([i], dtype=np.int64)
            if v3 or self.links.field is not None:  # its row and (v3) its column, the field read once
                self._mover_row = MoverLinksStep(self.links, i, pos, column=v3)
            else:
                self._mover_row = self.links.mover_row(i, pos)
        if isinstance(self._mover_row, MoverLinksStep):
            self._mover_row.step(pos, self.link_p, self._rx_dbm if v3 else None)
        else:
            self.link_p[i] = self._mover_row.success(pos[i : i + 1])[0]
        if v3:  # the period's draws for every pair, as step(); the mover's column of reports
            self.measure.update(self._rx_dbm, self.link_p, self._mover_rows)
        u, self.prr[i], self.jain[i], count = step_core.utility_of(
            self.link_p[i], self.target[i], self.p_min, self.normalise_reward
        )
        self.utility[i] = u
        assert self._geometry is not None
        step_core.move_geometry(i, pos, self.period_m, self._geometry.disp_m, self._geometry.dist2_m2)
        reward, self._base_prev[i] = step_core.step_reward(u, self._base_prev[i], self._improvement)
        if self.layout.version >= 1:
            self._u_prev[i], self._u_now[i], self._u_best[i], better = step_core.own_state_update(
                step_core.per_receiver(u, count, self.normalise_reward), self._u_now[i], self._u_best[i]
            )
            if better:
                self._best_m[i] = pos[i]
            self._maybe_replan()
        done = self.t >= self.max_cycles
        rows = self._mover_rows
        obs = self._build(rows)
        if v3:
            self._fill_v3(obs, rows)
        elif self.layout.version >= 1:
            step_core.own_v1_entries(
                obs[0], self.layout.own_v1_offset, self.layout.obs_clip, self.layout.scale_m, self._reach_m(),
                self._u_now[i], self._u_prev[i], self._u_start[i], self._u_best[i], self._best_m[i, 0],
                self._best_m[i, 1], self.plan_m[i, 0], self.plan_m[i, 1], pos[i, 0], pos[i, 1],
            )  # fmt: skip
        x, y = pos[i]
        vals = (u, self.u0[i], self.prr[i], self.prr0[i], self.jain[i], x - old_x, y - old_y, clipped)
        info = dict(zip(INFO_KEYS, (float(v) for v in vals), strict=True))
        if done:
            self.agents = []
            self._live = set()
        return obs[0], reward, done, info

    def speed_targets(self, act: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Target speeds and lane commands [N] of actions [N, 2] (:func:`~cv2x_marl.env.step.speed_commands`)."""
        active = self.t < self.max_cycles - self.settle_steps  # no command in the settle phase
        limit = self.config.vehicles.speed_max_mps
        if self.options.speed_command == "change":  # a change of the own speed over the period (lane model)
            bounds = (self.options.accel_mps2, self.options.decel_mps2, self.sim.rri / 1000.0)
            return step_core.speed_change_commands(
                act, self.mover_mask, self.sim.state.speed_mps, limit, *bounds, active
            )
        return step_core.speed_commands(act, self.mover_mask, limit, active)

    def _command_drive(self, act: NDArray[np.float64]) -> None:
        """The lane model's speed and lane commands (:meth:`cv2x_marl.sim.Simulator.set_drive`)."""
        self.sim.set_drive(*self.speed_targets(act), self.options.accel_mps2, self.options.decel_mps2)

    def _command_sumo(self, act: NDArray[np.float64]) -> None:
        """``traffic_action="speed"``: the movers' actions [N, 2] as SUMO speed and lane commands (the settle
        phase hands the movers back to SUMO's driver; with the driving observation, Traffic-v0, up to the limit)."""
        from cv2x_marl.sim import sumo

        target, lanes = self.speed_targets(act)  # NaN: no command (the vehicles that do not move)
        if self.t >= self.max_cycles - self.settle_steps:
            target[self.mover_mask] = -1.0  # SUMO's own driver again
        sumo.lockstep_of(self.sim).command(target, lanes, self.sim.rri / 1000.0, up_to_limit=self.layout.drive)

    # ------------------------------------------------------------------ pieces
    def _decode(self, actions: dict[str, Any]) -> NDArray[np.float64]:
        """[N, 2] actions by vehicle index (:func:`~cv2x_marl.env.step.decode_actions`); raises on bad input."""
        return step_core.decode_actions(actions, self._live, self.agents, self.possible_agents, self.agent_index)

    def _traffic_positions(self) -> NDArray[np.float64]:
        from cv2x_marl.sim import mobility

        return mobility.positions_m(self.sim.road, self.sim.state) + self.offsets_m

    def _link_success(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        if self.mode == "snapshot" and self.layout.version == 3:  # the field read once for P and the powers
            p, self._geometry, self._rx_dbm = self.links.evaluate_rx(self.positions_m)
            return p, self.links.target
        if self.mode == "snapshot":
            p, self._geometry = self.links.evaluate(self.positions_m)  # geometry shared with the observations
            return p, self.links.target
        self._geometry = pair_geometry(self.positions_m, self._wrap_road)
        assert self.sim.last_links is not None
        tx, rx, p, cause = self.sim.last_links
        dense = np.zeros((self.n, self.n))
        target = np.zeros((self.n, self.n), dtype=bool)
        ok = cause != CAUSE_CODE["half_duplex"]
        dense[tx, rx] = p
        target[tx[ok], rx[ok]] = True
        return dense, target

    def _utilities(self, p: NDArray[np.float64], target: NDArray[np.bool_]) -> NDArray[np.float64]:
        """[N] eq. 12 utility of each agent's broadcast (per receiver with ``normalise_reward``)."""
        return step_core.utilities(p, target, self.p_min, self.normalise_reward)[0]

    def _summarise(self) -> None:
        """Utility (eq. 12), PRR and Jain's index of every agent from the current links."""
        self.utility, self.prr, self.jain, self._target_count = step_core.utilities(
            self.link_p, self.target, self.p_min, self.normalise_reward
        )

    def _rewards(self, u: NDArray[np.float64]) -> NDArray[np.float64]:
        if self.reward_kind == "individual":
            return u
        if self.reward_kind == "difference":
            return difference_rewards(
                self.links, self.positions_m, self.start_m, self.mover_mask, self.p_min, self.normalise_reward
            )
        team = np.full_like(u, (u if self.options.team_objective == "utility" else self.prr).mean())
        if self.reward_kind == "team":
            return team
        return self.local_ratio * u + (1.0 - self.local_ratio) * team

    # ------------------------------------------------------- observation v1
    def _reach_m(self) -> float:
        """How far a mover can still go (m): the v1 observation's reach entry, before scaling."""
        return float(step_core.reach_m(self.t, self.max_cycles, self.settle_steps, self.max_step_m))

    def _reset_v1_state(self, cached_plan_m: NDArray[np.float64] | None = None) -> None:
        self._u_now = self.utility.copy() if self.normalise_reward else self.utility / np.maximum(self._target_count, 1)
        self._u_prev = self._u_now.copy()
        self._u_start = self._u_now.copy()
        self._u_best = self._u_now.copy()
        self._best_m = self.positions_m.copy()
        self.plan_m = self.positions_m.copy()
        movers = np.flatnonzero(self.mover_mask)
        if cached_plan_m is not None:  # the start came from the reset cache, with its plan
            self.plan_m = cached_plan_m.copy()
        elif self.mode == "snapshot" and movers.size and self.layout.version == 2:
            self.plan_m[movers] = sensing_plan(self, movers)
        elif self.mode == "snapshot" and movers.size and self.layout.version == 1:
            v0 = self._build(movers)[:, : self.layout.v0_size]
            reaches = [reachable_set(self, int(i)) for i in movers]
            inputs = decode_observations(v0, self.layout)
            self.plan_m[movers] = model_plan(inputs, self.positions_m[movers], reaches, self.model, self.p_min)

    def _maybe_replan(self) -> None:
        """Observation version 2 with ``replan_every``: a new sensing plan from where everyone is."""
        if self.replan_every is None or self.mode != "snapshot" or self.t % self.replan_every:
            return
        if self.t >= self.max_cycles - self.settle_steps:
            return
        movers = np.flatnonzero(self.mover_mask)
        if movers.size:
            self.plan_m[movers] = sensing_plan(self, movers)

    def _build(self, rows: NDArray[np.int64] | None = None) -> NDArray[np.float32]:
        """[A, size] observations of agents ``rows`` (all when None)."""
        drift = self.positions_m - self.start_m
        if self._co_table is None or (self.mode == "traffic" and not np.array_equal(self._co_resource, self.resource)):
            self._co_resource = self.resource.copy()
            concurrent = self.config.metrics.nsv_scope == "concurrent"  # NSV over the subframe, not the resource
            group = self.resource // self.config.sps.n_subchannels if concurrent else self.resource
            self._co_table = co_channel_table(group)
        return build_observations(
            self.layout,
            self.positions_m,
            self.resource,
            self.target,
            drift,
            self.t / self.max_cycles,
            self._co_table,
            self._geometry,
            rows,
            self.model,
            self.link_p if self.layout.privileged else None,
        )

    def _observations(self) -> dict[str, NDArray[np.float32]]:
        obs = self._build()
        if self.layout.drive:
            self._fill_drive(obs)
        if self.layout.version == 3:
            self._fill_v3(obs, np.arange(self.n, dtype=np.int64))
        elif self.layout.version == 4:
            tmeas.fill_observations(self, obs)
        elif self.layout.version >= 1:
            step_core.own_v1_block(
                obs, self.layout.own_v1_offset, self.layout.obs_clip, self.layout.scale_m, self._reach_m(),
                self._u_now, self._u_prev, self._u_start, self._u_best, self._best_m, self.plan_m, self.positions_m,
            )  # fmt: skip
        return dict(zip(self.agents, obs, strict=True))

    def _fill_drive(self, obs: NDArray[np.float32]) -> None:
        """The driving entries of every vehicle into ``obs`` [N, size] (:func:`~.observation.fill_drive`)."""
        lanes, limit = self.config.road.lanes_per_direction, self.config.vehicles.speed_max_mps
        speed, heading, lane = step_core.drive_state(self.sim, lanes)
        left = max(self.horizon - self.t, 0) / self.horizon
        fill_drive(obs, self.layout, speed / limit, heading, lane, lanes, left)

    def _fill_v3(self, obs: NDArray[np.float32], rows: NDArray[np.int64]) -> None:
        """Observation version 3's measured and own entries of agents ``rows`` (into ``obs`` [A, size])."""
        assert self._co_table is not None and self._geometry is not None
        m, cfg = self.measure, self.config
        slot, sub = np.divmod(self.resource, cfg.sps.n_subchannels)
        fill_measured(
            obs, self.layout, self._geometry, self._co_table, scaled_rsrp(m.rsrp_dbm), m.age / m.window,
            slot / cfg.traffic.rri_ms, sub / cfg.sps.n_subchannels, rows,
        )  # fmt: skip
        left = max(self.horizon - self.t, 0)
        moving = max(min(self.horizon, self.max_cycles - self.settle_steps) - self.t, 0)
        fill_own_v3(
            obs, self.layout, self._u_now[rows], self._u_prev[rows], (self.positions_m - self.start_m)[rows],
            left / self.horizon, moving * self.max_step_m,
        )  # fmt: skip

    def _infos(self, applied: NDArray[np.float64], clipped: NDArray[np.bool_]) -> dict[str, dict[str, float]]:
        """Numeric infos of every agent (all agents are live whenever infos are built)."""
        cols = [self.utility, self.u0, self.prr, self.prr0, self.jain, applied[:, 0], applied[:, 1], clipped]
        if self.options.episode_metrics:  # the means over the steps so far (at reset: the start's)
            steps = max(self.t, 1)
            sums = (self._u_sum, self._prr_sum, self._jain_sum)
            cols += [x / steps for x in sums] if self.t else [self.utility, self.prr, self.jain]
            if self.layout.drive:
                speed, _, lane = step_core.drive_state(self.sim, self.config.road.lanes_per_direction)
                cols += [speed, lane]
        table = np.stack(cols, axis=1).tolist()
        keys = self.info_keys
        return {a: dict(zip(keys, row, strict=True)) for a, row in zip(self.possible_agents, table, strict=True)}

    # ----------------------------------------------------------- state / draw
    def state(self) -> NDArray[np.float32]:
        """Global state for centralised critics: positions / region, drifts / scale, slot / RRI and subchannel /
        n_subchannels of every vehicle [6N] (observation version 3: then every vehicle's RSRP reports,
        scaled as in the observation, and their ages / window, [N(tx) x N(rx)] each, row-major)."""
        if not hasattr(self, "positions_m"):
            raise RuntimeError("state() called before reset(): call reset() first")
        region = self.layout.region_m
        slot = self.resource // self.config.sps.n_subchannels
        sub = self.resource % self.config.sps.n_subchannels
        parts = [
            (self.positions_m / region).ravel(),
            ((self.positions_m - self.start_m) / self.layout.scale_m).ravel(),
            slot / self.config.traffic.rri_ms,
            sub / self.config.sps.n_subchannels,
        ]
        if self.layout.version == 3:  # every vehicle's measurements [tx, rx], as in the observations
            parts += [scaled_rsrp(self.measure.rsrp_dbm).ravel(), (self.measure.age / self.measure.window).ravel()]
        s = np.concatenate(parts)
        return np.clip(s, -self.layout.obs_clip, self.layout.obs_clip).astype(np.float32)

    def render(self, mode: str | None = None) -> NDArray[np.uint8] | None:
        """Draw the scene (``rgb_array``: an H x W x 3 uint8 image; ``human``: a window).

        Args:
            mode: accepted for wrappers that pass the mode again (RLlib's ``ParallelPettingZooEnv``
                calls ``render(self.render_mode)``); it must be None or the env's ``render_mode``.
        """
        if mode is not None and mode != self.render_mode:
            raise ValueError(
                f"invalid render mode {mode!r}: this env was made with render_mode={self.render_mode!r}; "
                "pass render_mode to the constructor"
            )
        if self.render_mode is None:
            return None
        if not hasattr(self, "positions_m"):
            raise RuntimeError("render() called before reset(): call reset() first")
        from cv2x_marl.env.render import draw

        img = draw(self)
        if self.render_mode == "human":
            from cv2x_marl.env.render import show

            self._fig = show(img, self._fig)
            return None
        return img

    def close(self) -> None:
        """Close the figure and stop the simulator's SUMO run (``vehicles.mobility=sumo``), if any."""
        sim = getattr(self, "sim", None)
        if sim is not None:
            sim.close()
        if self._fig is not None:
            import matplotlib.pyplot as plt

            plt.close(self._fig)
            self._fig = None
