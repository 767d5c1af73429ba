"""One dynamics model per action kind: what an action does to the vehicles in one env step.

The kind follows from the options (:func:`action_kind`), and :class:`~cv2x_marl.env.mobility_env.MobilityEnv`
builds its model once, at construction (:func:`dynamics_model`):

    offset        snapshot mode: the action [-1, 1]^2 times ``max_step_m`` is the step
    plan_residual snapshot mode, observation 1 or 2: the action corrects the straight step towards the plan
    road_offset   traffic mode: the action moves the radio position off the road position (``max_drift_m``)
    target_speed  traffic mode: ``action[0]`` sets a target speed, ``action[1]`` asks for a lane change
                  (the lane model or SUMO)
    speed_change  traffic mode on the lane model: ``action[0]`` changes the own speed within
                  ``accel_mps2`` / ``decel_mps2``

Each model's :meth:`Dynamics.move` takes the decoded actions [N, 2] and returns the applied offsets [N, 2] (m;
zero where the traffic moves the vehicles) and which actions left the box [N] (the ``clipped`` info); in traffic
mode it also runs the simulator's period. Adding an action kind is a class here (or in a file of its own)
registered with :func:`register_dynamics`, and its rule in :func:`action_kind`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from cv2x_marl.env import step as step_core
from cv2x_marl.rng import env_stream
from cv2x_marl.sim import mobility
from cv2x_marl.sim.ground_truth import SnapshotLinks, pair_geometry
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.sim.shadow_field import ShadowField

if TYPE_CHECKING:
    from cv2x_marl.env.episode import EpisodeEnv
    from cv2x_marl.env.options import EnvOptions

FloatArray = NDArray[np.float64]
Moved = tuple[FloatArray, NDArray[np.bool_]]


def action_kind(options: EnvOptions) -> str:
    """The action kind of ``options`` (its ``mode``, ``action_mode``, ``traffic_action``, ``speed_command``)."""
    if options.mode == "snapshot":
        return options.action_mode
    if options.traffic_action == "offset":
        return "road_offset"
    if options.traffic_action == "resource":
        return "resource"
    return "speed_change" if options.speed_command == "change" else "target_speed"


class Dynamics:
    """The base of the action kinds: :meth:`move` applies the actions of one step.

    Attributes:
        kind: the kind's name (:func:`action_kind`).
        residual: the action is added to the straight step towards the plan (``plan_residual``).
    """

    kind: ClassVar[str] = ""
    residual: ClassVar[bool] = False
    #: the simulator's scheduler keeps its selections' sensing (traffic mode, ``SpsScheduler.record_selections``)
    record_selections: ClassVar[bool] = False

    def __init__(self, env: EpisodeEnv) -> None:
        self.env = env

    def action_space(self) -> spaces.Space[Any]:
        """Every agent's action space: a position offset or a speed command, ``Box(-1, 1, (2,))``."""
        return spaces.Box(-1.0, 1.0, (2,), np.float32)

    @property
    def null_action(self) -> Any:
        """The action of an agent that does nothing (what a one-agent view gives the vehicles it does not drive)."""
        return np.zeros(2, dtype=np.float32)

    def decode(self, actions: Any) -> Any:
        """A step's actions checked, laid out by vehicle index (:func:`~cv2x_marl.env.step.decode_actions`: [N, 2])."""
        env = self.env
        return step_core.decode_actions(actions, env._live, env.agents, env.possible_agents, env.agent_index)

    def infos(self, infos: dict[str, dict[str, Any]]) -> None:
        """Add the kind's own entries to every agent's info (none)."""

    def action_masks(self) -> NDArray[np.int8] | None:
        """[N, n] the valid actions of a discrete action kind (None: a continuous one, every action valid)."""
        return None

    def start(self, episode_seed: int) -> None:
        """A fresh start (after the simulator's stage-1 run, ``env.snapshot``): what the links need."""

    def move(self, act: FloatArray, settle: bool) -> Moved:
        """Apply actions ``act`` [N, 2] (``settle``: the settle phase, where vehicles stay put)."""
        raise NotImplementedError

    def links(self) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The links where the vehicles are now: success probabilities and target receivers [N(tx), N(rx)]; sets
        ``env.geometry`` (and ``env.rx_dbm`` when the observation model needs the received powers)."""
        raise NotImplementedError


#: the dynamics model of each action kind (:func:`register_dynamics` adds one)
DYNAMICS: dict[str, type[Dynamics]] = {}


def register_dynamics(model: type[Dynamics]) -> type[Dynamics]:
    """Make ``model`` the dynamics of its ``kind`` (a class decorator)."""
    if not model.kind or (model.kind in DYNAMICS and DYNAMICS[model.kind] is not model):
        raise ValueError(f"invalid or taken action kind {model.kind!r} of {model.__name__}")
    DYNAMICS[model.kind] = model
    return model


def dynamics_model(env: EpisodeEnv) -> Dynamics:
    """The dynamics of the env's action kind (:data:`DYNAMICS`)."""
    return DYNAMICS[action_kind(env.options)](env)


class Snapshot(Dynamics):
    """Snapshot mode: the stage-1 snapshot's links (:class:`~cv2x_marl.sim.ground_truth.SnapshotLinks`), evaluated
    where the actions moved the vehicles."""

    def start(self, episode_seed: int) -> None:
        env = self.env
        snap, field = env.snapshot, None
        if env.options.shadow_field:
            rng = env_stream(episode_seed, "shadow_field")
            field = ShadowField.draw(env.config, snap.positions_m, snap.shadowing_db, snap.los, rng)
        env.links = SnapshotLinks(env.config, snap, env.truth_los, field=field)

    def links(self) -> tuple[FloatArray, NDArray[np.bool_]]:
        env = self.env
        if env.observer.needs_rx:  # the field read once for P and the powers
            p, env.geometry, env.rx_dbm = env.links.evaluate_rx(env.positions_m)
        else:
            p, env.geometry = env.links.evaluate(env.positions_m)  # geometry shared with the observations
        return p, env.links.target


@register_dynamics
class Offset(Snapshot):
    """Snapshot mode: the step is the action times ``max_step_m`` (:func:`~cv2x_marl.env.step.move_vehicles`:
    clip, settle phase, ``max_drift_m`` and region bounds)."""

    kind = "offset"

    def move(self, act: FloatArray, settle: bool) -> Moved:
        env = self.env
        plan = env.plan_m if self.residual else env.positions_m
        env.positions_m, applied, clipped = step_core.move_vehicles(
            act, env.positions_m, env.start_m, plan, env.step_scale_m, env.max_step_m, self.residual, settle,
            env.drift_m, env.roi, env.box_m,
        )  # fmt: skip
        return applied, clipped


@register_dynamics
class PlanResidual(Offset):
    """Snapshot mode, observation 1 or 2: the action is added to ``clip((plan - position) / max_step_m)``."""

    kind = "plan_residual"
    residual = True


class Traffic(Dynamics):
    """Traffic mode: the simulator runs one SPS period per step; positions are the road's (plus offsets)."""

    def links(self) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The period's own link outcomes (half-duplex pairs are not targets)."""
        env = self.env
        env.geometry = pair_geometry(env.positions_m, env.wrap_road)
        assert env.sim.last_links is not None
        tx, rx, p, cause = env.sim.last_links
        dense = np.zeros((env.n, env.n))
        target = np.zeros((env.n, env.n), dtype=bool)
        ok = cause != CAUSE_CODE["half_duplex"]
        dense[tx, rx] = p
        target[tx[ok], rx[ok]] = True
        return dense, target

    def run_period(self) -> None:
        env = self.env
        env.sim.run(env.sim.rri, record=False)
        env.resource = env.sim.resource.copy()
        env.positions_m = mobility.positions_m(env.sim.road, env.sim.state) + env.offsets_m


@register_dynamics
class RoadOffset(Traffic):
    """The action moves the radio position off the road position (the traffic does not see it)."""

    kind = "road_offset"

    def move(self, act: FloatArray, settle: bool) -> Moved:
        env = self.env
        env.offsets_m, applied, clipped = step_core.traffic_offsets(
            act, env.offsets_m, env.step_scale_m, settle, env.drift_m
        )
        env.sim.set_offsets(env.offsets_m)
        self.run_period()
        return applied, clipped


@register_dynamics
class TargetSpeed(Traffic):
    """``action[0]`` sets a target speed from 0 to ``vehicles.speed_max_mps``, ``action[1]`` > 0.5 / < -0.5 asks
    for a lane left / right: the lane model reaches them within ``accel_mps2`` / ``decel_mps2``
    (:meth:`Simulator.set_drive`), SUMO within its own bounds and car-following safety."""

    kind = "target_speed"

    def targets(self, act: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
        """Target speeds and lane commands [N] of actions [N, 2] (NaN: no command)."""
        env = self.env
        active = env.t < env.max_cycles - env.settle_steps  # no command in the settle phase
        return step_core.speed_commands(act, env.mover_mask, env.config.vehicles.speed_max_mps, active)

    def move(self, act: FloatArray, settle: bool) -> Moved:
        env = self.env
        clipped = np.asarray(((act < -1.0) | (act > 1.0)).any(axis=1))
        o = env.options
        target, lanes = self.targets(act)
        if env.config.vehicles.mobility == "model":
            env.sim.set_drive(target, lanes, o.accel_mps2, o.decel_mps2)
        else:  # SUMO lockstep; the settle phase hands the movers back to SUMO's driver
            from cv2x_marl.sim import sumo  # libsumo: a heavy optional dependency

            if env.t >= env.max_cycles - env.settle_steps:
                target[env.mover_mask] = -1.0
            lock = sumo.lockstep_of(env.sim)
            lock.command(target, lanes, env.sim.rri / 1000.0, up_to_limit=env.layout.drive)
        self.run_period()
        return np.zeros((env.n, 2)), clipped


@register_dynamics
class SpeedChange(TargetSpeed):
    """The lane model: ``action[0]`` changes the own speed over the period, up to ``accel_mps2`` (+1) /
    ``decel_mps2`` (-1) times the period (a zero action holds the speed); ``action[1]`` as :class:`TargetSpeed`."""

    kind = "speed_change"

    def targets(self, act: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
        env, o = self.env, self.env.options
        active = env.t < env.max_cycles - env.settle_steps
        limit = env.config.vehicles.speed_max_mps
        return step_core.speed_change_commands(
            act, env.mover_mask, env.sim.state.speed_mps, limit, o.accel_mps2, o.decel_mps2, env.sim.rri / 1000.0,
            active,
        )  # fmt: skip
