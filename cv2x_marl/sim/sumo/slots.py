"""Tracked-vehicle states shared by the SUMO lockstep and trace replay: SUMO's readings as a
:class:`~cv2x_marl.sim.mobility.TrackedState`, the odometer, and the slot table of an open population
(issue 14)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.sim.mobility import TrackedState
from cv2x_marl.sim.sumo.tools import SumoError

FloatArray = NDArray[np.float64]


def tracked_state(pos_m: FloatArray, speed_mps: FloatArray, angle_deg: FloatArray, time_s: float) -> TrackedState:
    """A :class:`TrackedState` from SUMO's position, speed and angle (degrees clockwise from north)."""
    a = np.deg2rad(angle_deg)
    vel = np.stack([speed_mps * np.sin(a), speed_mps * np.cos(a)], axis=1)
    return TrackedState(np.asarray(pos_m, dtype=np.float64), vel, np.zeros(pos_m.shape[0]), time_s)


def moved_state(prev: TrackedState, new: TrackedState) -> TrackedState:
    """``new`` with the odometer of ``prev`` advanced by the straight distance between them.

    Both sources count the odometer this way (it drives the shadowing decorrelation), so a
    replayed trace gives the same run as live stepping.
    """
    step = np.hypot(*(new.pos_m - prev.pos_m).T)
    return TrackedState(new.pos_m, new.vel_mps, prev.odometer_m + step, new.time_s)


def select_first(ids_present: Sequence[str], first_seen: dict[str, float], n: int) -> list[str]:
    """The first ``n`` vehicles present, by (first time seen, ID)."""
    return sorted(ids_present, key=lambda v: (first_seen[v], v))[:n]


def assign_slots(slots: list[str | None], now: Sequence[str], what: str) -> NDArray[np.bool_]:
    """``vehicles.population=open``: update the slot table ``slots`` (in place) to the vehicles ``now``
    present: the slots of vehicles gone are freed, then the new vehicles take the lowest free slots in
    the order given (the same rule for the lockstep and a trace, so a replay gives the lockstep run).

    Args:
        slots: [capacity] the vehicle ID in each slot, None where empty.
        now: the IDs present now, new ones in the order they take slots.
        what: the source, for the error message.

    Returns:
        [capacity] the slots whose vehicle is new.

    Raises:
        SumoError: more vehicles present than slots (naming ``vehicles.capacity``).
    """
    here = set(now)
    for k, v in enumerate(slots):
        if v is not None and v not in here:
            slots[k] = None
    held = {v for v in slots if v is not None}
    new = [v for v in now if v not in held]
    entered = np.zeros(len(slots), dtype=bool)
    if not new:
        return entered
    free = [k for k, v in enumerate(slots) if v is None]
    if len(new) > len(free):
        raise SumoError(
            f"{what} has {len(held) + len(new)} vehicles in the network at once, more than vehicles.capacity = "
            f"{len(slots)} slots; raise vehicles.capacity"
        )
    for k, v in zip(free, new, strict=False):
        slots[k] = v
        entered[k] = True
    return entered


def open_state(
    slots: list[str | None],
    entered: NDArray[np.bool_],
    values: dict[str, tuple[float, float, float, float]],
    time_s: float,
    prev: TrackedState | None,
) -> TrackedState:
    """The :class:`TrackedState` of an open population from ``values`` (ID -> x, y, vx, vy) of the
    vehicles in ``slots``; the odometer goes on for a vehicle that stays and starts at 0 for a new one."""
    n = len(slots)
    rows = np.full((n, 4), np.nan)
    present = np.array([v is not None for v in slots], dtype=bool)
    for k in np.flatnonzero(present).tolist():
        rows[k] = values[slots[k]]  # type: ignore[index]
    pos, vel = rows[:, :2].copy(), rows[:, 2:].copy()
    odo = np.zeros(n)
    if prev is not None:
        stay = present & ~entered
        step = np.hypot(*(pos[stay] - prev.pos_m[stay]).T)
        odo[stay] = prev.odometer_m[stay] + step
    return TrackedState(pos, vel, odo, time_s, present, entered)


def first_seen_order(ids: Sequence[str], first_seen: dict[str, float]) -> list[str]:
    """``ids`` by (first time seen, ID): the order in which the vehicles present at time zero take slots."""
    return sorted(ids, key=lambda v: (first_seen.get(v, np.inf), v))
