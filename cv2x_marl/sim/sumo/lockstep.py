"""SUMO in lockstep through libsumo: one SUMO step per reservation period, the tracked vehicles'
positions, speeds and headings read back through a subscription, speed and lane commands sent
(issue 14)."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.sim.mobility import TrackedState
from cv2x_marl.sim.sumo.scenario import Scenario
from cv2x_marl.sim.sumo.slots import (
    assign_slots,
    first_seen_order,
    moved_state,
    open_state,
    select_first,
    tracked_state,
)
from cv2x_marl.sim.sumo.tools import SumoError, import_libsumo

FloatArray = NDArray[np.float64]

#: SUMO seconds the lockstep waits for ``N`` vehicles to be in the network before giving up
MAX_FILL_S = 3600.0

# TraCI variable ids (traci.constants), fixed by the protocol
_VAR_SPEED, _VAR_POSITION, _VAR_ANGLE, _VAR_LANE_INDEX = 0x40, 0x42, 0x43, 0x52


_ACTIVE: SumoLockstep | None = None


class SumoLockstep:
    """A SUMO scenario run through libsumo in this process, one step per call to :meth:`advance`.

    libsumo holds one simulation per process: starting a second lockstep closes the first (which
    then refuses to step). SUMO runs inside this process, so it cannot outlive it.

    Args:
        scenario: the scenario to run.
        n: vehicles to track (``open_population``: the slots, the most vehicles present at once).
        extra_args: further SUMO options (e.g. ``["--fcd-output", "fcd.xml"]``).
        begin_s: SUMO time at which the run may start (``vehicles.sumo_begin_s``).
        open_population: track every vehicle in the network as it enters and leaves
            (``vehicles.population=open``) instead of the first ``n``.
    """

    def __init__(
        self,
        scenario: Scenario,
        n: int,
        extra_args: Sequence[str] = (),
        begin_s: float = 0.0,
        open_population: bool = False,
    ) -> None:
        global _ACTIVE
        self.scenario = scenario
        self.n = n
        self.begin_s = begin_s
        self.open_population = open_population
        self.slots: list[str | None] = [None] * n
        self.closed = False
        self._ls = import_libsumo()
        if _ACTIVE is not None:
            _ACTIVE.close()
        args = [
            "sumo",
            "-c",
            str(scenario.sumocfg),
            "--seed",
            str(scenario.seed),
            "--step-length",
            repr(scenario.step_s),
            "--no-step-log",
            "true",
            "--no-warnings",
            "true",
            *extra_args,
        ]
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                self._ls.start(args)
        except self._ls.TraCIException as exc:
            key = "" if scenario.generated else "vehicles.sumo_config: "
            raise SumoError(
                f"{key}SUMO cannot load {scenario.sumocfg}: {str(exc).strip()} (SUMO's own messages are on stderr)"
            ) from exc
        _ACTIVE = self
        if open_population:
            first_seen, present = self._step_until(1)
            self.state = self._read_open(first_seen_order(present, first_seen), None)
        else:
            first_seen, present = self._step_until(self.n)
            self.fixed_ids = select_first(present, first_seen, self.n)
            self.slots = list(self.fixed_ids)
            for vid in self.fixed_ids:
                self._ls.vehicle.subscribe(vid, [_VAR_POSITION, _VAR_SPEED, _VAR_ANGLE, _VAR_LANE_INDEX])
            self.state = self._read()
        self.t0_s = self.time_s

    @property
    def ids(self) -> list[str | None]:
        """The vehicle in each slot (vehicle ``i`` of the simulator), None where a slot is empty."""
        return list(self.slots)

    def _read_open(self, now: Sequence[str], prev: TrackedState | None) -> TrackedState:
        """Open population: slots updated to the vehicles ``now`` present (new ones in slot order),
        new ones subscribed, every present vehicle read back."""
        entered = assign_slots(self.slots, now, f"the SUMO scenario {self.scenario.sumocfg}")
        veh = self._ls.vehicle
        for k in np.flatnonzero(entered).tolist():
            veh.subscribe(self.slots[k], [_VAR_POSITION, _VAR_SPEED, _VAR_ANGLE])
        res = veh.getAllSubscriptionResults()
        values: dict[str, tuple[float, float, float, float]] = {}
        for vid in self.slots:
            if vid is not None:
                r = res[vid]
                (x, y), sp, a = r[_VAR_POSITION], r[_VAR_SPEED], np.deg2rad(r[_VAR_ANGLE])
                values[vid] = (x, y, sp * np.sin(a), sp * np.cos(a))
        return open_state(self.slots, entered, values, self.time_s, prev)

    @property
    def time_s(self) -> float:
        """SUMO time of the state last read (the FCD ``time`` of the same instant)."""
        return float(self._ls.simulation.getTime()) - self.scenario.step_s

    def _step_until(self, need: int) -> tuple[dict[str, float], list[str]]:
        """Step until ``begin_s`` has passed and at least ``need`` vehicles are in the network (``n``
        with a fixed population, 1 with an open one); the time each vehicle was first seen and the IDs
        present."""
        first_seen: dict[str, float] = {}
        sim = self._ls.simulation
        while True:
            self._ls.simulationStep()
            t = self.time_s
            for vid in sim.getDepartedIDList():
                first_seen.setdefault(vid, t)
            present = list(self._ls.vehicle.getIDList())
            if len(present) >= need and t >= self.begin_s - 1e-9:
                return first_seen, present
            if sim.getMinExpectedNumber() == 0 or t >= self.begin_s + MAX_FILL_S:
                self.close()
                where = f"the SUMO scenario {self.scenario.sumocfg}"
                if self.open_population:
                    raise SumoError(
                        f"{where} has no vehicle in the network at or after vehicles.sumo_begin_s = "
                        f"{self.begin_s:g} s (looked until t = {t:g} s)"
                    )
                raise SumoError(
                    f"{where} never has {self.n} vehicles in the network at once (by t = {t:g} s it has "
                    f"{len(present)}); lower vehicles.n_vehicles or add demand to the scenario"
                )

    def _read(self) -> TrackedState:
        res = self._ls.vehicle.getAllSubscriptionResults()
        missing = [v for v in self.fixed_ids if v not in res]
        if missing:
            t = self.time_s
            self.close()
            raise SumoError(
                f"vehicle {missing[0]!r} of {self.scenario.sumocfg} left the network at t = {t:g} s "
                f"({len(missing)} of the {self.n} tracked vehicles gone); with vehicles.population=fixed every "
                "tracked vehicle must stay until the run ends (longer routes, fewer subframes, or "
                "vehicles.population=open)"
            )
        rows = [res[v] for v in self.fixed_ids]
        pos = np.array([r[_VAR_POSITION] for r in rows], dtype=np.float64)
        speed = np.array([r[_VAR_SPEED] for r in rows], dtype=np.float64)
        angle = np.array([r[_VAR_ANGLE] for r in rows], dtype=np.float64)
        a = np.deg2rad(angle)
        #: [N, 2] unit vector of each tracked vehicle's direction (SUMO's angle: defined at standstill too)
        self.heading = np.stack([np.sin(a), np.cos(a)], axis=1)
        #: [N] SUMO's lane index of each tracked vehicle (0: the rightmost lane of its edge)
        self.lane_index = np.array([r[_VAR_LANE_INDEX] for r in rows], dtype=np.int64)
        return tracked_state(pos, speed, angle, self.time_s)

    def advance(self) -> TrackedState:
        """One SUMO step (one reservation period); the new state."""
        if self.closed:
            raise RuntimeError(
                "this SUMO run is closed (libsumo runs one simulation per process: a newer Simulator with "
                "vehicles.mobility=sumo took it over, or close() was called); reset() the simulator"
            )
        self._ls.simulationStep()
        if self.open_population:
            ids = self._ls.vehicle.getIDList()
            held = set(self.slots)
            now = [v for v in ids if v in held] + sorted(v for v in ids if v not in held)  # new ones in ID order
            self.state = self._read_open(now, self.state)
        else:
            self.state = moved_state(self.state, self._read())
        return self.state

    def command(
        self,
        target_speed_mps: FloatArray,
        lane_change: NDArray[np.int64],
        duration_s: float,
        up_to_limit: bool = False,
    ) -> None:
        """Commands for the next step, honoured by SUMO within its own limits (the env's
        ``traffic_action="speed"``).

        Args:
            target_speed_mps: [N] speed each tracked vehicle should drive at (``vehicle.setSpeed``:
                SUMO approaches it within the vehicle type's acceleration and deceleration, and its
                car-following model still keeps the vehicle safe); a negative value hands the vehicle
                back to its own driver model; NaN leaves it as it is (no command).
            lane_change: [N] -1 (one lane to the right), 0 (stay), +1 (one lane to the left)
                (``vehicle.changeLaneRelative`` for ``duration_s``; ignored where no such lane exists).
            duration_s: how long a lane-change request holds (s).
            up_to_limit: first set each vehicle given a target >= 0 to ``speedFactor`` 1, so that a target up to
                its lane's speed limit is honoured (SUMO caps a vehicle at the limit times its speedFactor, the
                scenario's draw of its desired speed; ``cv2x/Traffic-v0``); False: that cap stays.
        """
        if self.closed:
            raise RuntimeError("this SUMO run is closed; reset() the simulator")
        target = np.asarray(target_speed_mps, dtype=np.float64)
        lanes = np.asarray(lane_change, dtype=np.int64)
        if target.shape != (self.n,) or lanes.shape != (self.n,):
            raise ValueError(f"target_speed_mps and lane_change must have shape ({self.n},)")
        if self.open_population:
            raise ValueError("commands need vehicles.population=fixed (the env's agents are a fixed set of vehicles)")
        veh = self._ls.vehicle
        for vid, v, dl in zip(self.fixed_ids, target.tolist(), lanes.tolist(), strict=True):  # libsumo: per vehicle
            if v == v:  # not NaN
                if up_to_limit and v >= 0:
                    veh.setSpeedFactor(vid, 1.0)
                veh.setSpeed(vid, -1.0 if v < 0 else v)  # -1: SUMO's own driver again
            if dl != 0:
                veh.changeLaneRelative(vid, int(dl), float(duration_s))

    def close(self) -> None:
        """Stop the SUMO simulation (idempotent)."""
        global _ACTIVE
        if self.closed:
            return
        self.closed = True
        if _ACTIVE is self:
            _ACTIVE = None
            with contextlib.suppress(Exception), contextlib.redirect_stdout(io.StringIO()):
                self._ls.close()


def lockstep_of(simulator: Any) -> SumoLockstep:
    """The running :class:`SumoLockstep` of a simulator with ``vehicles.mobility=sumo`` (after reset)."""
    source = getattr(simulator, "_source", None)
    if not isinstance(source, SumoLockstep):
        raise ValueError("this simulator does not run SUMO in lockstep (vehicles.mobility must be sumo)")
    return source
