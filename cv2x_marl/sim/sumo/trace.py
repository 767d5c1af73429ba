"""Replay of a recorded SUMO FCD trace (XML from ``--fcd-output``, or parquet with the same
columns), interpolated linearly to the reservation period (issue 14)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ConfigError
from cv2x_marl.sim.mobility import TrackedState
from cv2x_marl.sim.sumo.slots import assign_slots, first_seen_order, moved_state, open_state, select_first
from cv2x_marl.sim.sumo.tools import SumoError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Trace:
    """An FCD trace as flat records (one per vehicle and timestep present).

    Attributes:
        time_s: [T] sorted distinct timesteps.
        ids: [V] sorted distinct vehicle IDs.
        ti, vi: [R] timestep index and vehicle index of every record.
        x_m, y_m, speed_mps, angle_deg: [R] the records' values (angle: degrees clockwise from north).
    """

    time_s: FloatArray
    ids: list[str]
    ti: IntArray
    vi: IntArray
    x_m: FloatArray
    y_m: FloatArray
    speed_mps: FloatArray
    angle_deg: FloatArray

    def dense(self, cols: Sequence[int] | IntArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """(x, y, speed, angle) of the vehicles ``cols`` as [T, len(cols)] arrays, NaN where absent."""
        cols = np.asarray(cols, dtype=np.int64)
        where = np.full(len(self.ids), -1, dtype=np.int64)
        where[cols] = np.arange(cols.size)
        keep = where[self.vi] >= 0
        out = [np.full((self.time_s.size, cols.size), np.nan) for _ in range(4)]
        for arr, val in zip(out, (self.x_m, self.y_m, self.speed_mps, self.angle_deg), strict=True):
            arr[self.ti[keep], where[self.vi[keep]]] = val[keep]
        return out[0], out[1], out[2], out[3]


_COLUMNS = {
    "time": ("time", "timestep_time"),
    "id": ("id", "vehicle_id"),
    "x": ("x", "vehicle_x"),
    "y": ("y", "vehicle_y"),
    "angle": ("angle", "vehicle_angle"),
    "speed": ("speed", "vehicle_speed"),
}


def read_trace(path: str | Path) -> Trace:
    """Read a SUMO FCD trace: XML (``--fcd-output``, streamed) or parquet (columns ``time, id, x, y,
    angle, speed``, or SUMO's ``timestep_time, vehicle_id, vehicle_x, ...``).

    Raises:
        ConfigError: naming ``vehicles.trace_file`` and the file (missing, unreadable, no vehicles).
    """
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"vehicles.trace_file: {str(path)!r} does not exist or is not a file")
    if p.suffix.lower() == ".parquet":
        t, vid, x, y, ang, spd = _read_parquet(p)
    else:
        t, vid, x, y, ang, spd = _read_fcd_xml(p)
    if t.size == 0:
        raise ConfigError(f"vehicles.trace_file: {p} holds no vehicle positions")
    for name, values in (("time", t), ("x", x), ("y", y), ("angle", ang), ("speed", spd)):
        bad = ~np.isfinite(values)
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            raise ConfigError(
                f"vehicles.trace_file: {p}: {name} = {values[k]} for vehicle {str(vid[k])!r} at t = {t[k]:g} s "
                f"({int(bad.sum())} such values); times, positions, angles and speeds must be finite numbers"
            )
    times, ti = np.unique(t, return_inverse=True)
    ids, vi = np.unique(vid, return_inverse=True)
    return Trace(times, [str(v) for v in ids], ti.astype(np.int64), vi.astype(np.int64), x, y, spd, ang)


def _read_fcd_xml(p: Path) -> tuple[FloatArray, NDArray[np.str_], FloatArray, FloatArray, FloatArray, FloatArray]:
    t: list[float] = []
    vid: list[str] = []
    vals: list[tuple[float, float, float, float]] = []
    now = float("nan")
    try:
        for event, el in ET.iterparse(p, events=("start", "end")):
            if event == "start":
                if el.tag == "timestep":
                    now = float(el.get("time", "nan"))
                continue
            if el.tag == "vehicle":
                t.append(now)
                vid.append(el.get("id", ""))
                vals.append(
                    (
                        float(el.get("x", "nan")),
                        float(el.get("y", "nan")),
                        float(el.get("angle", "0")),
                        float(el.get("speed", "0")),
                    )
                )
            elif el.tag == "timestep":
                el.clear()
    except (ET.ParseError, ValueError) as exc:
        raise ConfigError(f"vehicles.trace_file: {p} is not a readable SUMO FCD XML trace: {exc}") from exc
    v = np.array(vals, dtype=np.float64).reshape(-1, 4)
    return np.array(t), np.array(vid, dtype=str), v[:, 0], v[:, 1], v[:, 2], v[:, 3]


def _read_parquet(p: Path) -> tuple[FloatArray, NDArray[np.str_], FloatArray, FloatArray, FloatArray, FloatArray]:
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(p)
    except Exception as exc:
        raise ConfigError(f"vehicles.trace_file: {p} is not a readable parquet file: {exc}") from exc
    cols: dict[str, np.ndarray] = {}
    for name, options in _COLUMNS.items():
        hit = next((c for c in options if c in table.column_names), None)
        if hit is None:
            if name in ("angle", "speed"):
                cols[name] = np.zeros(table.num_rows)
                continue
            have = ", ".join(table.column_names)
            raise ConfigError(f"vehicles.trace_file: {p} has no column {' or '.join(options)} (columns: {have})")
        cols[name] = table.column(hit).to_numpy(zero_copy_only=False)
    return (
        cols["time"].astype(np.float64),
        cols["id"].astype(str),
        cols["x"].astype(np.float64),
        cols["y"].astype(np.float64),
        cols["angle"].astype(np.float64),
        cols["speed"].astype(np.float64),
    )


class TraceReplay:
    """Replay of an FCD trace, linearly interpolated to a period of ``step_s``.

    The tracked vehicles and time zero follow the rule of the lockstep (:mod:`cv2x_marl.sim.sumo`).
    Positions and velocity vectors are interpolated between the two samples around each time.

    With ``open_population`` every vehicle of the trace is tracked while it is in it: a vehicle is
    present at a time when the trace has it at both samples around that time (at the sample, on
    one), and takes a slot as in the lockstep (:func:`assign_slots`).

    Args:
        path: the trace file (``vehicles.trace_file``).
        n: vehicles to track (``open_population``: the slots).
        step_s: the period (``traffic.rri_ms`` in seconds).
        begin_s: trace time at which the run may start (``vehicles.sumo_begin_s``).
        open_population: ``vehicles.population=open``.
    """

    def __init__(
        self, path: str | Path, n: int, step_s: float, begin_s: float = 0.0, open_population: bool = False
    ) -> None:
        self.path = Path(path)
        self.trace = tr = read_trace(path)
        self.n = n
        self.step_s = step_s
        self.open_population = open_population
        self.k = 0
        if open_population:
            self._init_open(begin_s)
            return
        counts = np.bincount(tr.ti, minlength=tr.time_s.size)
        full = np.flatnonzero((counts >= n) & (tr.time_s >= begin_s - 1e-9))
        if full.size == 0:
            raise ConfigError(
                f"vehicles.trace_file: {self.path} never has {n} vehicles at once (at most {int(counts.max())}); "
                "lower vehicles.n_vehicles"
            )
        k0 = int(full[0])
        first = np.full(len(tr.ids), tr.time_s.size, dtype=np.int64)
        np.minimum.at(first, tr.vi, tr.ti)
        first_seen = {tr.ids[j]: float(tr.time_s[first[j]]) for j in np.unique(tr.vi[tr.ti == k0])}
        self.fixed_ids = select_first(list(first_seen), first_seen, n)
        self.slots: list[str | None] = list(self.fixed_ids)
        col = {v: j for j, v in enumerate(tr.ids)}
        self._x, self._y, s, ang = tr.dense([col[v] for v in self.fixed_ids])  # only the tracked vehicles
        a = np.deg2rad(ang)
        self._vx, self._vy = s * np.sin(a), s * np.cos(a)
        self.t0_s = float(tr.time_s[k0])
        self.state = self._at(self.t0_s)

    def _init_open(self, begin_s: float) -> None:
        tr = self.trace
        order = np.lexsort((tr.vi, tr.ti))  # records by time, then vehicle
        self._rec = {
            "vi": tr.vi[order],
            "x": tr.x_m[order],
            "y": tr.y_m[order],
            "vx": tr.speed_mps[order] * np.sin(np.deg2rad(tr.angle_deg[order])),
            "vy": tr.speed_mps[order] * np.cos(np.deg2rad(tr.angle_deg[order])),
        }
        self._starts = np.searchsorted(tr.ti[order], np.arange(tr.time_s.size + 1))
        after = np.flatnonzero(tr.time_s >= begin_s - 1e-9)
        if after.size == 0:
            raise ConfigError(
                f"vehicles.trace_file: {self.path} ends at t = {tr.time_s[-1]:g} s, before vehicles.sumo_begin_s = "
                f"{begin_s:g} s"
            )
        self.t0_s = float(tr.time_s[after[0]])
        first = np.full(len(tr.ids), np.inf)
        np.minimum.at(first, tr.vi, tr.time_s[tr.ti])
        ids, _ = self._open_values(self.t0_s)
        col = {v: j for j, v in enumerate(tr.ids)}
        first_seen = {v: float(first[col[v]]) for v in ids}
        self.slots = [None] * self.n
        self.state = self._open_at(self.t0_s, first_seen_order(ids, first_seen), None)

    @property
    def ids(self) -> list[str | None]:
        """The vehicle in each slot (vehicle ``i`` of the simulator); None where a slot is empty."""
        return list(self.slots)

    def _open_values(self, t: float) -> tuple[list[str], dict[str, tuple[float, float, float, float]]]:
        """The vehicles in the trace at ``t`` and their interpolated (x, y, vx, vy)."""
        times = self.trace.time_s
        hi = self._sample_at(t)
        r, st = self._rec, self._starts
        cols = ("x", "y", "vx", "vy")
        if abs(times[hi] - t) <= 1e-9:
            sl = slice(st[hi], st[hi + 1])
            vi = r["vi"][sl]
            vals = np.stack([r[c][sl] for c in cols], axis=1)
        else:
            lo = hi - 1
            w = float((t - times[lo]) / (times[hi] - times[lo]))
            a, b = slice(st[lo], st[lo + 1]), slice(st[hi], st[hi + 1])
            vi, ia, ib = np.intersect1d(r["vi"][a], r["vi"][b], assume_unique=True, return_indices=True)
            va = np.stack([r[c][a][ia] for c in cols], axis=1)
            vb = np.stack([r[c][b][ib] for c in cols], axis=1)
            vals = np.asarray((1.0 - w) * va + w * vb, dtype=np.float64)
        names = [self.trace.ids[j] for j in vi.tolist()]
        return names, {v: (row[0], row[1], row[2], row[3]) for v, row in zip(names, vals.tolist(), strict=True)}

    def _open_at(self, t: float, order: Sequence[str] | None, prev: TrackedState | None) -> TrackedState:
        ids, values = self._open_values(t)
        if order is None:
            held = set(self.slots)
            order = [v for v in ids if v in held] + sorted(v for v in ids if v not in held)
        entered = assign_slots(self.slots, order, f"vehicles.trace_file {self.path}")
        return open_state(self.slots, entered, values, t, prev)

    @property
    def time_s(self) -> float:
        return self.t0_s + self.k * self.step_s

    def _sample_at(self, t: float) -> int:
        """Index of the first trace sample at or after ``t`` (s); an error naming the file past its end."""
        times = self.trace.time_s
        if t > times[-1] + 1e-9:
            raise SumoError(
                f"vehicles.trace_file: {self.path} ends at t = {times[-1]:g} s; the run needs t = {t:g} s "
                f"({t - self.t0_s:g} s from its start at {self.t0_s:g} s); record a longer trace or run fewer subframes"
            )
        return int(np.searchsorted(times, t - 1e-9))

    def _at(self, t: float) -> TrackedState:
        times = self.trace.time_s
        hi = self._sample_at(t)
        if abs(times[hi] - t) <= 1e-9:
            lo, w = hi, 0.0
        else:
            lo, w = hi - 1, float((t - times[hi - 1]) / (times[hi] - times[hi - 1]))
        rows = [self._x, self._y, self._vx, self._vy]
        x, y, vx, vy = (r[lo] if w == 0.0 else (1.0 - w) * r[lo] + w * r[hi] for r in rows)
        gone = ~np.isfinite(x)
        if np.any(gone):
            j = int(np.flatnonzero(gone)[0])
            raise SumoError(
                f"vehicles.trace_file: vehicle {self.fixed_ids[j]!r} of {self.path} is not in the trace at t = {t:g} s "
                f"({int(gone.sum())} of the {self.n} tracked vehicles gone); this version keeps N fixed"
            )
        return TrackedState(np.stack([x, y], axis=1), np.stack([vx, vy], axis=1), np.zeros(self.n), t)

    def advance(self) -> TrackedState:
        """The state one period later."""
        self.k += 1
        if self.open_population:
            self.state = self._open_at(self.time_s, None, self.state)
        else:
            self.state = moved_state(self.state, self._at(self.time_s))
        return self.state

    def close(self) -> None:
        """Nothing to release (for symmetry with :class:`~cv2x_marl.sim.sumo.lockstep.SumoLockstep`)."""
