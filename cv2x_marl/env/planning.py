"""The plans of observation versions 1 and 2: searches of a mover's reachable set.

What the env itself computes at reset (and with ``replan_every``) to put a plan in the observation,
and what the reference policies reuse (:mod:`cv2x_marl.policies.optimum`):

- :class:`ReachableSet` and :func:`reachable_set`: where a mover can be at the end of the episode;
- :func:`best_reachable`: the position of largest eq. 12 utility in it, under any :class:`UtilityRow`
  (the true links, the two-distance model's :class:`ModelRow`, the sensing estimate);
- :func:`model_plan` (observation v1) and :func:`sensing_plan` (v2);
- the grid limits (:data:`MAX_GRID_POINTS`, :func:`check_reach_grid`, :class:`SearchGridError`).

Reachable set of mover i from its start ``s_i`` with ``T`` steps left: the square
``|x - s_i|_inf <= T * max_step_m`` (an action moves each axis by at most ``max_step_m``),
intersected with the drift disc ``|x - s_i| <= max_drift_m`` and the region of interest when the
env bounds them. The set is convex and contains the straight path to any of its points, so the
mover reaches its target exactly, whatever the env's bounding does.

Search: a grid of pitch ``grid_m`` over the set (every point evaluated, compiled), then the
``refine`` best grid points are refined twice on 21 x 21 grids of a tenth of the previous pitch,
and the start position is always a candidate (so the search never loses utility). The search is
exact up to the grid: a peak narrower than ``grid_m`` can be missed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.sim import kernels
from cv2x_marl.sim.ground_truth import MoverRow, mean_rx_dbm
from cv2x_marl.utility import utility_log

if TYPE_CHECKING:
    from cv2x_marl.env.observation import GbmuInputs, ObservationLayout
    from cv2x_marl.regression.model import TwoDistanceModel
    from cv2x_marl.sim.ground_truth import SnapshotLinks

FloatArray = NDArray[np.float64]


class PlanningEnv(Protocol):
    """What the plans and the reference policies read of an env (:class:`~cv2x_marl.env.MobilityEnv`).

    Attributes:
        positions_m, start_m: [N, 2] current and episode-start positions (m).
        t, max_cycles, settle_steps: steps taken, per episode, and the last ones that do not move.
        max_step_m: offset of a full action (m).
        max_drift_m: bound on the distance from the start (m; None: none).
        roi: whether positions stay in the road box ``[0, box_m]``.
        box_m: [2] the road box (m).
        period_m: [2] torus period of the pair geometry (inf where distances do not wrap).
        links: the snapshot's ground-truth links (snapshot mode).
        p_min: clip of P inside eq. 12's log.
        mode: ``snapshot`` or ``traffic``.
        mover_mask: [N] which vehicles move.
        agent_index: agent name -> vehicle index.
        layout: the observation layout.
        plan_m: [N, 2] the observed plans (observation >= 1).
    """

    positions_m: FloatArray
    start_m: FloatArray
    t: int
    max_cycles: int
    settle_steps: int
    max_step_m: float
    max_drift_m: float | None
    roi: bool
    box_m: FloatArray
    period_m: FloatArray
    links: SnapshotLinks
    p_min: float
    mode: str
    mover_mask: NDArray[np.bool_]
    agent_index: dict[str, int]
    layout: ObservationLayout
    plan_m: FloatArray


class UtilityRow(Protocol):
    """One mover's eq. 12 utility at many positions, the others fixed (:class:`MoverRow`,
    :class:`ModelRow`, the GBMU study's judge rows)."""

    def utility(self, candidates_m: FloatArray, p_min: float) -> FloatArray:
        """[M] utility at candidate positions [M, 2] (m)."""
        ...


@dataclass(frozen=True)
class ReachableSet:
    """Where a mover can be at the end of the episode (see the module docstring).

    Attributes:
        start_m: [2] start position (m).
        radius_m: half-width of the Chebyshev square (m).
        max_drift_m: radius of the drift disc around the start (None: no disc).
        box_m: [2] upper corner of the region of interest [0, box] (None: unbounded).
        period_m: [2] torus period of the link geometry per axis (inf: no wrap; None: no torus).
        drift_center_m: [2] centre of the drift disc (None: ``start_m``; differs when a plan is
            made mid-episode from the current position).
    """

    start_m: FloatArray
    radius_m: float
    max_drift_m: float | None = None
    box_m: FloatArray | None = None
    period_m: FloatArray | None = None
    drift_center_m: FloatArray | None = None

    def _drift_center(self) -> FloatArray:
        return self.start_m if self.drift_center_m is None else np.asarray(self.drift_center_m, dtype=np.float64)

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        """Lower and upper corner of the axis-aligned box that holds the set (the part worth searching).

        When distances wrap (``period_m``) and the set, unbounded by drift or box, spans a whole period
        of an axis, every position has an image within half a period of the start with the same
        links: the box shrinks to that period window.
        """
        lo, hi = self.start_m - self.radius_m, self.start_m + self.radius_m
        if self.max_drift_m is not None:
            c = self._drift_center()
            lo, hi = np.maximum(lo, c - self.max_drift_m), np.minimum(hi, c + self.max_drift_m)
        r = self.radius_m
        if self.box_m is not None:
            lo, hi = np.maximum(lo, 0.0), np.minimum(hi, self.box_m)
        elif self.period_m is not None and self.max_drift_m is None:
            half = 0.5 * np.asarray(self.period_m, dtype=np.float64)
            wraps = np.isfinite(half) & (r >= half)
            lo = np.where(wraps, self.start_m - half, lo)
            hi = np.where(wraps, self.start_m + half, hi)
        return lo, hi

    def contains(self, points_m: FloatArray, tol_m: float = 1e-9) -> NDArray[np.bool_]:
        """[M] which of the points [M, 2] lie in the set."""
        d = np.asarray(points_m, dtype=np.float64) - self.start_m
        ok = np.abs(d).max(axis=-1) <= self.radius_m + tol_m
        if self.max_drift_m is not None:
            e = np.asarray(points_m, dtype=np.float64) - self._drift_center()
            ok &= np.hypot(e[..., 0], e[..., 1]) <= self.max_drift_m + tol_m
        if self.box_m is not None:
            p = np.asarray(points_m)
            ok &= np.all((p >= -tol_m) & (p <= self.box_m + tol_m), axis=-1)
        return ok


#: most points a search grid may hold: about 224 MB at the search's peak of 56 bytes per point
#: (positions, masks, utilities; measured) and some seconds of link evaluation per search
MAX_GRID_POINTS = 4_000_000
#: peak bytes per grid point of :func:`best_reachable` (measured with tracemalloc: 56.0)
GRID_POINT_BYTES = 56


class SearchGridError(ValueError):
    """A search grid that would exceed :data:`MAX_GRID_POINTS`; raised before anything is allocated."""


def grid_points(width_m: float, height_m: float, pitch_m: float) -> int:
    """Points of a grid of pitch ``pitch_m`` over a ``width_m`` x ``height_m`` box (as :func:`_grid` lays it)."""
    return _axis_points(width_m, pitch_m) * _axis_points(height_m, pitch_m)


def _axis_points(span_m: float, pitch_m: float) -> int:
    if not np.isfinite(span_m) or not np.isfinite(pitch_m) or pitch_m <= 0:
        raise SearchGridError(f"cannot lay a search grid of pitch {pitch_m!r} m over {span_m!r} m")
    return max(int(np.ceil(span_m / pitch_m)) + 1, 1)


def grid_size_text(n_points: int) -> str:
    """``N points (about X MB)``: a grid's size and its memory at the search's peak."""
    return f"{n_points:,} points (about {_bytes_text(n_points * GRID_POINT_BYTES)})"


def _bytes_text(n_bytes: float) -> str:
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n_bytes >= size:
            return f"{n_bytes / size:,.1f} {unit}"
    return f"{n_bytes / 1e3:,.1f} kB"


def _grid(lo: FloatArray, hi: FloatArray, pitch_m: float) -> FloatArray:
    counts = [_axis_points(float(hi[c] - lo[c]), pitch_m) for c in range(2)]
    if counts[0] * counts[1] > MAX_GRID_POINTS:  # checked before anything is allocated
        raise SearchGridError(
            f"the position search would lay {grid_size_text(counts[0] * counts[1])} over "
            f"{hi[0] - lo[0]:,.0f} m x {hi[1] - lo[1]:,.0f} m at a pitch of {pitch_m:g} m, above the limit of "
            f"{MAX_GRID_POINTS:,} points; lower max_step_m or max_cycles (the reachable square is "
            "2 x max_cycles x max_step_m wide), or bound it with max_drift_m or roi=True"
        )
    axes = [np.linspace(lo[c], hi[c], counts[c]) for c in range(2)]
    gx, gy = np.meshgrid(*axes, indexing="ij")
    return np.stack((gx.ravel(), gy.ravel()), axis=1)


def best_reachable(
    row: UtilityRow,
    reach: ReachableSet,
    p_min: float,
    grid_m: float = 2.5,
    refine: int = 16,
) -> tuple[FloatArray, float]:
    """The position of largest eq. 12 utility in the reachable set, and that utility.

    Args:
        row: the mover's links (:meth:`SnapshotLinks.mover_row`), others fixed.
        reach: the mover's :class:`ReachableSet`.
        p_min: clip of P inside the log (the env's ``p_min``).
        grid_m: pitch of the global grid (m).
        refine: grid points refined (the best ones).

    Returns:
        ``(position_m [2], utility)``; the utility is in the env's units before any normalisation.
    """
    if grid_m <= 0 or refine < 1:
        raise ValueError(f"grid_m must be > 0 and refine >= 1, got {grid_m}, {refine}")
    start = np.asarray(reach.start_m, dtype=np.float64)
    lo, hi = reach.bounds()
    cand = _grid(lo, hi, grid_m)
    cand = np.concatenate([start[None], cand[reach.contains(cand)]])
    u = row.utility(cand, p_min)
    best_pos, best_u = start.copy(), float(u[0])
    pitch = grid_m
    seeds = cand[np.argsort(-u, kind="stable")[:refine]]
    for _ in range(2):  # two refinements, each a tenth of the previous pitch
        pitch /= 10.0
        offsets = _grid(np.full(2, -10 * pitch), np.full(2, 10 * pitch), pitch)
        fine = (seeds[:, None, :] + offsets[None]).reshape(-1, 2)
        fine = fine[reach.contains(fine)]
        if fine.size == 0:
            break
        uf = row.utility(fine, p_min)
        order = np.argsort(-uf, kind="stable")
        seeds = fine[order[:refine]]
        if uf[order[0]] > best_u:
            best_u, best_pos = float(uf[order[0]]), fine[order[0]].copy()
    k = int(np.argmax(u))
    if u[k] > best_u:
        best_u, best_pos = float(u[k]), cand[k].copy()
    return best_pos, best_u


def reachable_set(env: PlanningEnv, i: int) -> ReachableSet:
    """:class:`ReachableSet` of vehicle ``i`` of a snapshot-mode env from where it is now (at reset:
    its episode start) with the moving steps left; the drift disc stays around the episode start."""
    steps_left = max(env.max_cycles - env.settle_steps - env.t, 0)  # moving steps left
    return ReachableSet(
        np.array(env.positions_m[i], dtype=np.float64),
        float(steps_left * env.max_step_m),
        env.max_drift_m,
        np.asarray(env.box_m, dtype=np.float64) if env.roi else None,
        _torus(env),
        np.array(env.start_m[i], dtype=np.float64),
    )


def _torus(env: PlanningEnv) -> FloatArray | None:
    """The env's torus period (None when no axis wraps)."""
    period = np.asarray(env.period_m, dtype=np.float64)
    return period if np.isfinite(period).any() else None


#: pitch of the global grid of the observation plans (:func:`model_plan`, :func:`sensing_plan`), m
PLAN_GRID_M = 20.0


def reach_extent_m(env: PlanningEnv) -> tuple[float, float]:
    """Width and height (m) of the widest box :meth:`ReachableSet.bounds` gives a mover of a snapshot-mode
    env at reset, wherever it starts: the square of half-width ``(max_cycles - settle_steps) x max_step_m``,
    narrowed by the drift disc, the region of interest or the torus period as :func:`reachable_set` does."""
    steps = max(env.max_cycles - env.settle_steps, 0)
    radius = steps * float(env.max_step_m)
    width = np.full(2, 2.0 * radius)
    if env.max_drift_m is not None:
        width = np.minimum(width, 2.0 * env.max_drift_m)
    period = _torus(env)
    if env.roi:
        width = np.minimum(width, np.asarray(env.box_m, dtype=np.float64))
    elif period is not None and env.max_drift_m is None:
        width = np.where(np.isfinite(period) & (radius >= 0.5 * period), period, width)
    return float(width[0]), float(width[1])


def check_reach_grid(env: PlanningEnv, pitch_m: float, what: str) -> None:
    """Refuse, before any search, a reachable set whose grid of pitch ``pitch_m`` would exceed
    :data:`MAX_GRID_POINTS` (:class:`SearchGridError` with the figure and the options to lower)."""
    w, h = reach_extent_m(env)
    n = grid_points(w, h, pitch_m)
    if n > MAX_GRID_POINTS:
        steps = max(env.max_cycles - env.settle_steps, 0)
        raise SearchGridError(
            f"{what} searches the reachable square, {w:,.0f} m x {h:,.0f} m ({steps} moving steps x max_step_m "
            f"{env.max_step_m:g} m each way), on a {pitch_m:g} m grid: {grid_size_text(n)}, above the limit of "
            f"{MAX_GRID_POINTS:,} points; lower max_step_m or max_cycles, or bound the square with max_drift_m "
            "or roi=True"
        )


class ModelRow:
    """The two-distance model's view of one mover's links, with the :class:`MoverRow` interface.

    What a vehicle can compute from one-hop information (receiver positions, their main-interferer
    distance and NSV, as GBMU reads them) and the steering model: the predicted eq. 12 utility
    ``sum_j ln max(P_hat(d_j(x), l_j, NSV_j), p_min)`` at candidate positions x. The receivers and
    interferers are taken where they were observed.

    Args:
        rx_m: [R, 2] receiver positions (m, absolute).
        l_m: [R] main-interference distances (m).
        nsv: [R] NSV of each receiver.
        mask: [R] which receivers are targets.
        model: the :class:`~cv2x_marl.regression.model.TwoDistanceModel`.
    """

    def __init__(self, rx_m: FloatArray, l_m: FloatArray, nsv: NDArray[np.int64], mask: NDArray[np.bool_], model: Any):
        keep = np.asarray(mask, dtype=bool)
        self.rx_m = np.asarray(rx_m, dtype=np.float64)[keep]
        self.l_m = np.asarray(l_m, dtype=np.float64)[keep]
        self.nsv = np.asarray(nsv)[keep]
        self.model = model

    def utility(self, candidates_m: FloatArray, p_min: float, chunk: int = 8_192) -> FloatArray:
        """[M] predicted eq. 12 utility at candidates [M, 2] (m)."""
        cand = np.asarray(candidates_m, dtype=np.float64).reshape(-1, 2)
        out = np.empty(cand.shape[0])
        for lo in range(0, cand.shape[0], chunk):
            c = cand[lo : lo + chunk]
            d = np.maximum(np.hypot(c[:, None, 0] - self.rx_m[:, 0], c[:, None, 1] - self.rx_m[:, 1]), 1.0)
            p = self.model.predict(d, self.l_m, self.nsv)
            out[lo : lo + chunk] = utility_log(p, None, p_min)  # eq. 12 (its numpy reference)
        return out


def model_plan(
    inputs: GbmuInputs,
    starts_m: FloatArray,
    reaches: list[ReachableSet],
    model: TwoDistanceModel,
    p_min: float,
    grid_m: float = PLAN_GRID_M,
) -> FloatArray:
    """[B, 2] the model's best reachable position of B movers (the ``plan`` of observation v1).

    Args:
        inputs: :class:`~cv2x_marl.env.observation.GbmuInputs` of the movers, receivers relative to them.
        starts_m: [B, 2] the movers' positions when the inputs were observed (m).
        reaches: the movers' :class:`ReachableSet`.
        model: the two-distance model.
        p_min: clip inside the log.
        grid_m: pitch of the global grid (then refined twice, to a hundredth).
    """
    out = np.empty((len(reaches), 2))
    for b, reach in enumerate(reaches):
        row = ModelRow(starts_m[b] + inputs.rx_m[b], inputs.l_m[b], inputs.nsv[b], inputs.mask[b], model)
        out[b], _ = best_reachable(row, reach, p_min, grid_m=grid_m, refine=4)
    return out


def sensing_plan(
    env: PlanningEnv, movers: list[int] | NDArray[np.int64], grid_m: float = PLAN_GRID_M, refine: int = 4
) -> FloatArray:
    """[B, 2] each mover's best reachable position under its own sensing estimate (the ``-v2`` plan).

    The estimate is :meth:`cv2x_marl.sim.ground_truth.SnapshotLinks.sensed_row`: the mover's links as it
    can know them from Mode 4 sensing (RSRP of its own links, positions and resources of the others),
    with the shadowing between other vehicles unknown (0 dB). Each mover is planned alone, the others
    where they are now. Global grid of pitch ``grid_m`` over the :func:`reachable_set`, the ``refine``
    best points refined twice (:func:`best_reachable`).
    """
    pos = np.asarray(env.positions_m, dtype=np.float64)
    out = np.empty((len(movers), 2))
    for b, i in enumerate(movers):
        row = env.links.sensed_row(int(i), pos)
        out[b], _ = best_reachable(row, reachable_set(env, int(i)), env.p_min, grid_m=grid_m, refine=refine)
    return out


#: the ``sensing`` planner on observation version 3 replans every this many steps: once per sensing
#: window (10 periods), when the window's reports have been renewed
MEASURED_REPLAN_EVERY = 10


def measured_row(env: PlanningEnv, mover: int, positions_m: FloatArray | None = None) -> Any:
    """The mover's links as it estimates them from its measurements (observation version 3).

    Like :meth:`cv2x_marl.sim.ground_truth.SnapshotLinks.sensed_row`, but the own links' shadowing is what
    the measured RSRP implies at the current positions, not the truth: for each neighbour j,
    ``s_j = (EIRP - PL(x_i, x_j)) - rsrp_dbm[j, i]`` (the report of :mod:`cv2x_marl.env.measurement`, fast
    fading and report error included; 0 dB for a neighbour never heard), held fixed over the candidates (the
    vehicle cannot know the field elsewhere); every pair without the mover at its median (0 dB). LOS states
    are the snapshot's. Returns a :class:`~cv2x_marl.sim.ground_truth.MoverRow` (compiled kernels only).

    Args:
        env: a snapshot-mode env with observation version 3 (its ``measure``).
        mover: the vehicle index.
        positions_m: [N, 2] where the row puts the other vehicles (m; the coordination channel's announced moves,
            :mod:`cv2x_marl.env.turns`); the shadowing is still the one measured where they are now. None: where
            they are now.
    """
    links = env.links
    if not links.compiled:
        raise ValueError(
            "the measured estimate needs the compiled link kernels (WINNER+ B1, truth_los snapshot or always)"
        )
    measure = getattr(env, "measure", None)
    if measure is None:
        raise ValueError("the measured estimate needs observation version 3 (the env's RSRP measurements)")
    pos = np.ascontiguousarray(env.positions_m, dtype=np.float64)
    n = pos.shape[0]
    i = int(mover)
    free_dbm = mean_rx_dbm(links.config, links.road, pos[:, None, :], pos[None, :, :], links.los, np.zeros((n, n)))
    shadow = np.nan_to_num(free_dbm[:, i] - measure.rsrp_dbm[:, i], nan=0.0, posinf=0.0, neginf=0.0)  # [N]
    shadow[i] = 0.0
    gain = np.full((n, n), float(links.eirp_dbm))
    gain[i, :] = gain[:, i] = links.eirp_dbm - shadow
    if positions_m is not None:
        pos = np.ascontiguousarray(positions_m, dtype=np.float64)
    row = MoverRow(links, i, pos)
    (period, los, _gain, wb1, range2, idx, val, *_rest) = links.kernel_args
    gain = np.ascontiguousarray(gain)
    interference = kernels.mover_interference(pos, period, los, gain, wb1, range2, idx, val, i)
    row.args = row.args._replace(gain_row_db=np.ascontiguousarray(gain[i]), interference_mw=interference)
    return row


def measured_plan(
    env: PlanningEnv, movers: list[int] | NDArray[np.int64], grid_m: float = PLAN_GRID_M, refine: int = 4
) -> FloatArray:
    """[B, 2] each mover's best reachable position under its measured estimate (:func:`measured_row`),
    the others where they are now (the ``sensing`` planner on observation version 3)."""
    out = np.empty((len(movers), 2))
    for b, i in enumerate(movers):
        out[b], _ = best_reachable(measured_row(env, int(i)), reachable_set(env, int(i)), env.p_min, grid_m, refine)
    return out
