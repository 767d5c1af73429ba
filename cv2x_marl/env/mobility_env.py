"""The controlled-mobility ParallelEnv: every vehicle an agent, an action a position offset or a speed command.

A thin layer over the simulator (``cv2x_marl.sim``): it holds no physics. Rewards are the eq. 12
utility of each agent's broadcast computed with the simulator's link model
(:class:`cv2x_marl.sim.ground_truth.SnapshotLinks` in ``snapshot`` mode, the period's own link
outcomes in ``traffic`` mode), never with the regression model.

The env is assembled from parts chosen once from its options (:class:`~cv2x_marl.env.options.EnvOptions`):
an observation model (:mod:`cv2x_marl.env.observation_models`, one per version), a dynamics model
(:mod:`cv2x_marl.env.dynamics`, one per action kind) and a reward model (:mod:`cv2x_marl.env.rewards`). The class
keeps the episode state and the PettingZoo plumbing; :mod:`cv2x_marl.env.mover_step` is its one-mover fast path.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray
from pettingzoo import ParallelEnv

from cv2x_marl.config import ConfigError
from cv2x_marl.env import mover_step, starts
from cv2x_marl.env import resource as _resource  # noqa: F401 - registers the resource action kind and observation 5
from cv2x_marl.env import step as step_core
from cv2x_marl.env.dynamics import TargetSpeed, dynamics_model
from cv2x_marl.env.infos import DRIVE_INFO_KEYS, EPISODE_INFO_KEYS, INFO_KEYS, global_state, infos_of
from cv2x_marl.env.observation import ObservationLayout, build_observations, co_channel_table
from cv2x_marl.env.observation_fills import fill_drive
from cv2x_marl.env.observation_models import OwnState, observation_model
from cv2x_marl.env.option_attributes import install_options
from cv2x_marl.env.options import EnvOptions
from cv2x_marl.env.rewards import RewardModel
from cv2x_marl.sim.ground_truth import PairGeometry
from cv2x_marl.sim.road import Road

FloatArray = NDArray[np.float64]
#: options whose attribute of the same name the env holds itself: ``config`` (the resolved scenario), ``model`` (the
#: loaded two-distance model; the option is ``model_name``), ``max_step_m`` (a float), ``max_drift_m`` (traffic
#: mode's default)
_OWN_ATTRIBUTES = ("config", "model", "max_step_m", "max_drift_m")


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
        options: the env's options (:class:`~cv2x_marl.env.options.EnvOptions`), or None to build them from
            ``kwargs``.
        **kwargs: the options as keyword arguments (``docs/env.md`` has the table: meaning, unit, default,
            allowed values); each is also an attribute of the env (``env.max_cycles``), read from :attr:`options`.

    Attributes:
        positions_m, start_m: [N, 2] every vehicle's position now and at the episode's start (m).
        resource: [N] every vehicle's SPS resource (slot x sub-channels + sub-channel).
        link_p, target: [N(tx), N(rx)] link success probabilities and the target receivers of the links now.
        utility, prr, jain, target_count: [N] eq. 12 utility, PRR, Jain's index and target receivers now.
        u0, prr0: [N] utility and PRR at the start.
        own: the own state of observation versions >= 1 (:class:`~cv2x_marl.env.observation_models.OwnState`).
        plan_m: [N, 2] the plan of observation versions 1 and 2 (versions 3, 4: the start positions).
        u_sum, prr_sum, jain_sum: [N] sums over the episode's steps (the ``episode_metrics`` infos).
        observer, dynamics, rewarder: the env's parts.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "name": "cv2x_mobility_v0",
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(self, options: EnvOptions | None = None, **kwargs: Any) -> None:
        if options is not None and not isinstance(options, EnvOptions):
            raise ValueError(
                f"invalid env argument options={options!r}; allowed: an EnvOptions or None (the options are keyword "
                "arguments: MobilityEnv(preset='paper', ...))"
            )
        opts = options if options is not None else EnvOptions.from_mapping(kwargs)
        if options is not None and kwargs:
            raise ValueError(f"pass options or keyword arguments, not both (got {', '.join(kwargs)} too)")
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
        #: the validated options (:class:`~cv2x_marl.env.options.EnvOptions`); each is also a read-only attribute
        self.options = opts
        self.config = cfg
        self.n = cfg.n_vehicles
        #: the horizon in force (steps): ``max_cycles`` or a shorter Gymnasium ``TimeLimit`` (v3's time left)
        self.horizon = opts.max_cycles
        #: the drift bound in force (m; traffic mode: 10 m unless set); :attr:`drift_m` is the kernels' (inf: none)
        self.max_step_m = float(opts.max_step_m)  # m
        self.max_drift_m = opts.max_drift_m if opts.max_drift_m is not None or opts.mode == "snapshot" else 10.0
        self.drift_m = np.inf if self.max_drift_m is None else float(self.max_drift_m)
        self.possible_agents = [f"vehicle_{i}" for i in range(self.n)]
        self.agent_index = {a: i for i, a in enumerate(self.possible_agents)}
        self.mover_mask = np.ones(self.n, dtype=bool)
        if opts.movers is not None:
            self.mover_mask[:] = False
            self.mover_mask[list(opts.movers)] = True
        #: [N] the step of a full action (m): ``max_step_m`` for the movers, 0 for who stays put
        self.step_scale_m = float(opts.max_step_m) * self.mover_mask.astype(np.float64)
        #: the road whose distances wrap (None: they do not)
        self.wrap_road = road if cfg.road.wrap_distances else None
        #: [2] the torus of the pair geometry (inf where distances do not wrap)
        self.period_m = np.asarray(road.periodic_box_m if cfg.road.wrap_distances else np.full(2, np.inf), dtype=float)
        self.geometry: PairGeometry | None = None
        n_neighbours = self.n - 1 if opts.n_neighbours is None else opts.n_neighbours
        self.layout = ObservationLayout(
            n_neighbours, opts.scale_m, float(max(box)), cfg.metrics.interferer_range_m, 10.0, opts.observation,
            opts.privileged, opts.drive_observation,
        )  # fmt: skip
        #: the infos' keys (with ``episode_metrics`` also :data:`EPISODE_INFO_KEYS`, :data:`DRIVE_INFO_KEYS`)
        self.info_keys: tuple[str, ...] = INFO_KEYS + (EPISODE_INFO_KEYS if opts.episode_metrics else ())
        self.info_keys += DRIVE_INFO_KEYS if opts.episode_metrics and opts.drive_observation else ()
        self.model: Any = None  # the two-distance model (observation versions 1 and 2 load it)
        self.own: OwnState | None = None
        self.observer = observation_model(self)
        self.dynamics = dynamics_model(self)
        self.rewarder = RewardModel()
        self._np_random: np.random.Generator | None = None
        clip = self.layout.obs_clip
        self._obs_space = spaces.Box(-clip, clip, (self.layout.size,), np.float32)
        self._act_space = self.dynamics.action_space()
        state_size = self.n * 6 + self.observer.state_per_pair * self.n * self.n
        self.state_space = spaces.Box(-clip, clip, (state_size,), np.float32)
        self.agents: list[str] = []
        self._live: set[str] = set()
        self._fig: Any = None

    if TYPE_CHECKING:  # the options are read-only attributes (set on the class from the schema, not restated here)

        def __getattr__(self, name: str) -> Any: ...

    @property
    def reward_kind(self) -> str:
        """The ``reward`` option."""
        return self.options.reward

    @property
    def model_name(self) -> str:
        """The ``model`` option (``env.model`` is the two-distance model it names, once loaded)."""
        return self.options.model

    @property
    def drives(self) -> bool:
        """The lane model drives the movers (``traffic_action="speed"``, ``vehicles.mobility=model``)."""
        return isinstance(self.dynamics, TargetSpeed) and self.config.vehicles.mobility == "model"

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Space[Any]:
        return self._act_space

    def action_masks(self) -> NDArray[np.int8] | None:
        """[N, n] every vehicle's valid actions now (``cv2x/Resource-v0``: the entries of its candidate list; also its
        info's ``action_mask``); None where the action space is continuous."""
        return self.dynamics.action_masks()

    # ------------------------------------------------------------------- reset
    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        """Start an episode. Seeding follows Gymnasium: ``reset(seed=s)`` makes this episode a function of
        ``s`` and reseeds the env's own generator with ``s``; a later ``reset()`` draws its episode seed
        from that generator, so the same seeded first reset gives the same sequence of episodes.
        Without any seed the generator starts from OS entropy."""
        episode_seed = self.seed_used = starts.episode_seed(self, seed)
        cached = starts.open_start(self, episode_seed)
        snap = self.snapshot
        self.start_m = snap.positions_m.copy()
        self.positions_m = snap.positions_m.copy()
        self.resource = snap.slot * snap.n_subchannels + snap.subchannel
        self.offsets_m = np.zeros((self.n, 2))
        self.mover_links: Any = None  # the one-mover path's links (:mod:`cv2x_marl.env.mover_step`)
        self._co_resource = self.resource.copy()
        self.co_table: NDArray[np.int64] | None = None
        self.t = 0
        self.agents = self.possible_agents[:]
        self._live = set(self.agents)
        self.tracks = [self.positions_m.copy()]
        self.link_p, self.target = self.dynamics.links()
        self._summarise()
        self.u0 = self.utility.copy()
        self.prr0 = self.prr.copy()
        self.u_sum, self.prr_sum, self.jain_sum = np.zeros(self.n), np.zeros(self.n), np.zeros(self.n)
        self.rewarder.reset(self)
        self.observer.reset(self, episode_seed, None if cached is None else cached.plan_m)
        if cached is None and starts.cache_size(self) > 0:
            starts.store_start(self, episode_seed)
        obs = self.observations()
        infos = infos_of(self, np.zeros((self.n, 2)), np.zeros(self.n, dtype=bool))
        self.dynamics.infos(infos)
        return obs, infos

    # -------------------------------------------------------------------- step
    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("step() called on a finished episode: call reset()")
        act = self.dynamics.decode(actions)
        applied, clipped = self.dynamics.move(act, self.t >= self.max_cycles - self.settle_steps)
        self.t += 1
        self.tracks.append(self.positions_m.copy())
        self.link_p, self.target = self.dynamics.links()
        self._summarise()
        self.u_sum += self.utility
        self.prr_sum += self.prr
        self.jain_sum += self.jain
        self.observer.after_links(self)
        rewards_arr = self.rewarder.step(self)
        self.observer.after_reward(self)
        done = self.t >= self.max_cycles
        agents = self.agents
        obs = self.observations()
        rewards = dict(zip(agents, rewards_arr.tolist(), strict=True))
        terms = dict.fromkeys(agents, False)
        truncs = dict.fromkeys(agents, done)
        infos = infos_of(self, applied, clipped)
        self.dynamics.infos(infos)
        if done:
            self.finish()
        if self.render_mode == "human":
            self.render()
        return obs, rewards, terms, truncs, infos

    def finish(self) -> None:
        """End the episode: no agent is live until the next :meth:`reset`."""
        self.agents = []
        self._live = set()

    # ------------------------------------------------------- one-mover path
    @property
    def fast_mover(self) -> int | None:
        """The vehicle whose step :meth:`step_mover` computes alone, or None when it does not apply
        (:func:`cv2x_marl.env.mover_step.fast_mover`)."""
        return mover_step.fast_mover(self)

    def step_mover(self, action: Any) -> tuple[NDArray[np.float32], float, bool, dict[str, float]]:
        """One step in which only :attr:`fast_mover` moves (:func:`cv2x_marl.env.mover_step.step_mover`)."""
        return mover_step.step_mover(self, action)

    def speed_targets(self, act: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
        """Target speeds and lane commands [N] of actions [N, 2] (``traffic_action="speed"``: the dynamics')."""
        if not isinstance(self.dynamics, TargetSpeed):
            kind = self.dynamics.kind
            raise ValueError(f"speed targets need traffic_action='speed' (this env's action kind: {kind})")
        return self.dynamics.targets(act)

    # ------------------------------------------------------------------ pieces
    def utilities(self, p: FloatArray, target: NDArray[np.bool_]) -> FloatArray:
        """[N] eq. 12 utility of each agent's broadcast over links ``p``, ``target`` [N, N] (per receiver with
        ``normalise_reward``)."""
        return step_core.utilities(p, target, self.p_min, self.normalise_reward)[0]

    def _summarise(self) -> None:
        """Utility (eq. 12), PRR and Jain's index of every agent from the current links."""
        self.utility, self.prr, self.jain, self.target_count = step_core.utilities(
            self.link_p, self.target, self.p_min, self.normalise_reward
        )

    def reach_m(self) -> float:
        """How far a mover can still go (m): the own entries' reach, before scaling."""
        return float(step_core.reach_m(self.t, self.max_cycles, self.settle_steps, self.max_step_m))

    def build(self, rows: NDArray[np.int64] | None = None) -> NDArray[np.float32]:
        """[A, size] the v0 block (and versions 1-2's link success) of agents ``rows`` (all when None)."""
        drift = self.positions_m - self.start_m
        if self.co_table is None or (self.mode == "traffic" and not np.array_equal(self._co_resource, self.resource)):
            self._co_resource = self.resource.copy()
            concurrent = self.config.metrics.nsv_scope == "concurrent"  # NSV over the subframe, not the resource
            group = self.resource // self.config.sps.n_subchannels if concurrent else self.resource
            self.co_table = co_channel_table(group)
        return build_observations(
            self.layout, self.positions_m, self.resource, self.target, drift, self.t / self.max_cycles, self.co_table,
            self.geometry, rows, self.model, self.link_p if self.layout.privileged else None,
        )  # fmt: skip

    def observations(self) -> dict[str, NDArray[np.float32]]:
        """Every agent's observation now (:meth:`build`, the driving entries, the version's entries)."""
        obs = self.build()
        if self.layout.drive:
            lanes, limit = self.config.road.lanes_per_direction, self.config.vehicles.speed_max_mps
            speed, heading, lane = step_core.drive_state(self.sim, lanes)
            left = max(self.horizon - self.t, 0) / self.horizon
            fill_drive(obs, self.layout, speed / limit, heading, lane, lanes, left)
        self.observer.fill(self, obs, np.arange(self.n, dtype=np.int64))
        return dict(zip(self.agents, obs, strict=True))

    # ----------------------------------------------------------- state / draw
    def state(self) -> NDArray[np.float32]:
        """Global state for centralised critics (:func:`~cv2x_marl.env.infos.global_state`)."""
        return global_state(self)

    def render(self, mode: str | None = None) -> NDArray[np.uint8] | None:
        """Draw the scene (``rgb_array``: an H x W x 3 uint8 image; ``human``: a window).

        Args:
            mode: accepted for wrappers that pass the mode again (RLlib's ``ParallelPettingZooEnv``
                calls ``render(self.render_mode)``); it must be None or the env's ``render_mode``.
        """
        from cv2x_marl.env.render import render_env  # matplotlib: a heavy optional dependency

        return render_env(self, mode)

    def close(self) -> None:
        """Close the figure and stop the simulator's SUMO run (``vehicles.mobility=sumo``), if any."""
        sim = getattr(self, "sim", None)
        if sim is not None:
            sim.close()
        if self._fig is not None:
            import matplotlib.pyplot as plt  # a heavy optional dependency

            plt.close(self._fig)
            self._fig = None


install_options(MobilityEnv, _OWN_ATTRIBUTES)
