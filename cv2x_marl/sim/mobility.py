"""Vehicle state as arrays, placement on lanes, and motion with turns at crossings (Sec. 3).

A vehicle is ``(axis, direction, road, lane, s_m, speed_mps)``: it drives along x (axis 0) or y
(axis 1) in direction +1 or -1 on road ``road`` (index across that axis) and lane ``lane``, at
coordinate ``s_m`` along the road. The area wraps around, so the vehicle count stays fixed.
At a grid crossing a vehicle goes straight, turns left or right with the configured
probabilities (paper reading: 0.5 / 0.25 / 0.25) and keeps its lane index.

With ``vehicles.mobility`` = ``sumo`` or ``trace`` the vehicles come from SUMO instead
(:mod:`cv2x_marl.sim.sumo`) and their state is a :class:`TrackedState` of positions and velocity
vectors; :func:`positions_m` and :func:`velocities_mps` accept either kind of state.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import RoadConfig, VehiclesConfig
from cv2x_marl.sim.road import FloatArray, IntArray, Road


@dataclass(frozen=True)
class VehicleState:
    """Arrays of length N describing every vehicle."""

    axis: NDArray[np.int8]
    direction: NDArray[np.int8]
    road: IntArray
    lane: IntArray
    s_m: FloatArray
    speed_mps: FloatArray
    odometer_m: FloatArray

    @property
    def n(self) -> int:
        return int(self.s_m.shape[0])


@dataclass(frozen=True)
class TrackedState:
    """Vehicle state read from an external mobility source (SUMO lockstep or a trace replay).

    Attributes:
        pos_m: [N, 2] positions (x, y) in metres, SUMO network coordinates (our frame).
        vel_mps: [N, 2] velocity vectors in m/s.
        odometer_m: [N] distance covered since the source started (sum of the straight
            displacements between periods; drives the shadowing decorrelation).
        time_s: source time of the state (SUMO / trace seconds).
        present: [N] which slots hold a vehicle (``vehicles.population=open``; None: all, always).
            An empty slot has NaN position and velocity and a zero odometer.
        entered: [N] slots whose vehicle is new since the previous state (None: none).
    """

    pos_m: FloatArray
    vel_mps: FloatArray
    odometer_m: FloatArray
    time_s: float
    present: NDArray[np.bool_] | None = None
    entered: NDArray[np.bool_] | None = None

    @property
    def n(self) -> int:
        return int(self.pos_m.shape[0])

    @property
    def speed_mps(self) -> FloatArray:
        """[N] speeds."""
        return np.asarray(np.hypot(self.vel_mps[:, 0], self.vel_mps[:, 1]))


MobilityState = VehicleState | TrackedState


def positions_m(road: Road, st: MobilityState) -> FloatArray:
    """[N, 2] positions (x, y) in metres."""
    if isinstance(st, TrackedState):
        return st.pos_m.copy()
    across = road.road_pos_m[st.road] + road.lane_offset_m(st.direction, st.lane) * np.where(st.axis == 0, -1, 1)
    pos = np.empty((st.n, 2))
    pos[:, 0] = np.where(st.axis == 0, st.s_m, across)
    pos[:, 1] = np.where(st.axis == 0, across, st.s_m)
    return pos


def velocities_mps(st: MobilityState) -> FloatArray:
    """[N, 2] velocity vectors in m/s."""
    if isinstance(st, TrackedState):
        return st.vel_mps.copy()
    out = np.zeros((st.n, 2))
    out[np.arange(st.n), st.axis] = st.direction * st.speed_mps  # along the vehicle's axis
    return out


def place(road: Road, vcfg: VehiclesConfig, n: int, rng: np.random.Generator) -> VehicleState:
    """Drop ``n`` vehicles on the lanes: at random, or equally spaced per lane (random phase)."""
    n_lanes = road.n_lanes_total
    if vcfg.placement == "random":
        lane_slot = rng.integers(0, n_lanes, size=n)
        s = rng.uniform(0.0, road.length_m, size=n)
    else:
        lane_slot = np.arange(n) % n_lanes
        rank = np.arange(n) // n_lanes
        per_lane = np.bincount(lane_slot, minlength=n_lanes)
        phase = rng.uniform(0.0, road.length_m, size=n_lanes)
        s = (phase[lane_slot] + rank * road.length_m / per_lane[lane_slot]) % road.length_m
    # lane_slot enumerates (axis, road, direction, lane)
    lanes = road.lanes_per_direction
    lane = lane_slot % lanes
    direction = np.where((lane_slot // lanes) % 2 == 0, 1, -1).astype(np.int8)
    road_idx = (lane_slot // (2 * lanes)) % road.n_roads
    axis = (lane_slot // (2 * lanes * road.n_roads)).astype(np.int8)
    speed = rng.uniform(vcfg.speed_min_mps, vcfg.speed_max_mps, size=n)
    return VehicleState(axis, direction, road_idx.astype(np.int64), lane.astype(np.int64), s, speed, np.zeros(n))


def advance(road: Road, rcfg: RoadConfig, st: VehicleState, dt_s: float, rng: np.random.Generator) -> VehicleState:
    """Move every vehicle by ``speed * dt_s``; on the grid, turn at the first crossing passed.

    One uniform draw per vehicle per call (whether it crosses or not), so the stream's
    consumption does not depend on the trajectory. ``dt_s`` must be short enough that no
    vehicle passes two crossings (checked).
    """
    dist = st.speed_mps * dt_s
    s_new = st.s_m + st.direction * dist
    u = rng.random(st.n)
    axis, direction, road_idx = st.axis.copy(), st.direction.copy(), st.road.copy()
    if road.kind == "grid":
        spacing = road.length_m / road.n_roads
        if np.any(dist >= spacing):
            raise ValueError(
                f"mobility step {float(dist.max()):g} m passes more than one crossing ({spacing:g} m apart)"
            )
        off = road.road_pos_m[0]
        k_old = np.floor((st.s_m - off) / spacing)
        k_new = np.floor((s_new - off) / spacing)
        crossed = k_new != k_old
        k_cross = np.where(st.direction > 0, k_new, k_old)
        c = off + k_cross * spacing
        left = crossed & (u >= rcfg.p_straight) & (u < rcfg.p_straight + rcfg.p_left)
        right = crossed & (u >= rcfg.p_straight + rcfg.p_left)
        turn = left | right
        if np.any(turn):
            remaining = np.abs(s_new - c)
            # heading (d, 0) on axis 0 or (0, d) on axis 1; left rotates +90 deg, right -90 deg
            sign = np.where(st.axis == 0, 1, -1) * np.where(left, 1, -1)
            new_dir = (st.direction * sign).astype(np.int8)
            new_road = k_cross.astype(np.int64) % road.n_roads
            new_s = road.road_pos_m[st.road] + new_dir * remaining
            axis = np.where(turn, 1 - st.axis, st.axis).astype(np.int8)
            direction = np.where(turn, new_dir, st.direction).astype(np.int8)
            road_idx = np.where(turn, new_road, st.road)
            s_new = np.where(turn, new_s, s_new)
    return replace(
        st,
        axis=axis,
        direction=direction,
        road=road_idx,
        s_m=np.mod(s_new, road.length_m),
        odometer_m=st.odometer_m + dist,
    )


#: lane commands of :func:`drive`: one lane to the left (towards the centre line: lane index - 1), none,
#: one lane to the right (lane index + 1)
LANE_LEFT, LANE_KEEP, LANE_RIGHT = 1, 0, -1


def headings(st: VehicleState) -> FloatArray:
    """[N, 2] unit vectors of each vehicle's direction of travel (defined at standstill too)."""
    out = np.zeros((st.n, 2))
    out[np.arange(st.n), st.axis] = st.direction
    return out


def drive(
    road: Road,
    st: VehicleState,
    target_mps: FloatArray,
    lane_change: IntArray,
    accel_mps2: float,
    decel_mps2: float,
    dt_s: float,
    limit_mps: float,
) -> VehicleState:
    """Speed and lane commands applied over one step of ``dt_s`` (the lane model; opt-in: only vehicles
    with a finite target are touched, every other one keeps its speed and lane bit for bit).

    A commanded vehicle's speed moves towards ``clip(target, 0, limit_mps)`` by at most ``accel_mps2 *
    dt_s`` up and ``decel_mps2 * dt_s`` down, so a speed in ``[0, limit_mps]`` stays there; the new speed
    holds over the step (semi-implicit Euler: :func:`advance` then moves the vehicle by ``new speed x
    dt_s``). A lane command moves it one lane left (``+1``, towards the centre line) or right (``-1``) at
    the end of the step (lateral motion is not modelled); a lane that does not exist (beyond the
    ``lanes_per_direction`` of its road) is ignored. The lane model has no car following: vehicles
    pass through each other.

    Args:
        road: the road (its lanes per direction).
        st: the vehicles' state.
        target_mps: [N] target speeds (m/s); NaN: no command.
        lane_change: [N] :data:`LANE_LEFT`, :data:`LANE_KEEP` or :data:`LANE_RIGHT` (ignored without a target).
        accel_mps2, decel_mps2: the bounds of the speed change (m/s^2, > 0).
        dt_s: the step (s).
        limit_mps: the speed limit (m/s).

    Returns:
        the state with the new speeds and lanes (positions unchanged).
    """
    target_mps = np.asarray(target_mps, dtype=np.float64)
    lane_change = np.asarray(lane_change, dtype=np.int64)
    if target_mps.shape != (st.n,) or lane_change.shape != (st.n,):
        raise ValueError(f"target_mps and lane_change must have shape ({st.n},)")
    if not np.isin(lane_change, (LANE_LEFT, LANE_KEEP, LANE_RIGHT)).all():
        raise ValueError("lane_change must hold -1 (right), 0 (keep) or +1 (left)")
    if not (accel_mps2 > 0 and decel_mps2 > 0 and dt_s > 0 and limit_mps > 0):
        raise ValueError("accel_mps2, decel_mps2, dt_s and limit_mps must be > 0")
    cmd = np.isfinite(target_mps)
    v = st.speed_mps
    goal = np.clip(np.where(cmd, target_mps, 0.0), 0.0, limit_mps)
    speed = np.where(cmd, np.clip(goal, v - decel_mps2 * dt_s, v + accel_mps2 * dt_s), v)
    lane = st.lane - np.where(cmd, lane_change, 0)
    lane = np.where((lane >= 0) & (lane < road.lanes_per_direction), lane, st.lane)
    return replace(st, speed_mps=speed, lane=lane.astype(st.lane.dtype))
