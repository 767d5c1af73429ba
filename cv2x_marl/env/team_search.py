"""The Cooperative ceiling: a centralised search of the team objective over every vehicle's reachable set.

Team objective (what ``reward="team", normalise_reward=True`` rewards, eq. 12 per transmitter):

    J(x) = (1 / N) sum_i (1 / |T_i|) sum_{j in T_i} ln max(P_ij(x), p_min)

with ``P`` the expected success of every link (:meth:`cv2x_marl.sim.ground_truth.SnapshotLinks.evaluate`:
the snapshot's resources, the WINNER+ B1 path loss, the snapshot's shadowing or the episode's shadowing
field, TR 36.885 A.1.4) and ``T_i`` the target receivers of ``i`` (without ``normalise``: ``1 / N`` alone).

Search: coordinate ascent. Each vehicle in turn moves to the position of its :func:`reachable_set` that
maximises ``J`` with the others fixed: every point of a 20 m grid over the set (and where it stands), then
5 m and 1 m grids around the best (the pitches ``grids_m``); a move is taken when it raises ``J``. Rounds
over all vehicles repeat until a round moves nobody (or ``max_rounds``). The ascent runs from several
starts (the snapshot positions; :class:`~cv2x_marl.policies.optimum.OptimumPolicy` adds the
best-response positions) in several vehicle orders, and the best end point is kept. ``J`` never falls
along an ascent, so the result is never below any start's ``J`` (in particular best response's when it
is a start): it is the best found, a lower bound on the true team optimum, not a proof of optimality.

Each candidate is evaluated incrementally (:func:`cv2x_marl.sim.kernels.team.team_move_objective`): when
only vehicle ``v`` moves, only its broadcasts, the links it receives and the links it interferes with
change.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.planning import PlanningEnv, ReachableSet, reachable_set
from cv2x_marl.env.step import utilities
from cv2x_marl.sim.ground_truth import SnapshotLinks
from cv2x_marl.sim.kernels.team import team_move_objective, team_terms

FloatArray = NDArray[np.float64]

#: pitches of the coordinate search (m): a global grid over the reachable set, then local grids
TEAM_GRIDS_M = (20.0, 5.0, 1.0)


def team_objective(links: SnapshotLinks, positions_m: FloatArray, p_min: float, normalise: bool = True) -> float:
    """``J`` at ``positions_m`` [N, 2] (m): the mean over vehicles of :func:`cv2x_marl.env.step.utilities`
    of a full :meth:`SnapshotLinks.evaluate` (the env's team reward; the search's reference)."""
    p = links.evaluate(np.asarray(positions_m, dtype=np.float64))[0]
    return float(utilities(p, links.target, p_min, normalise)[0].mean())


class TeamObjective:
    """``J`` with one vehicle at many candidate positions, the others fixed (compiled, incremental).

    Args:
        links: the snapshot's links (compiled kernels: WINNER+ B1, ``truth_los`` snapshot or always).
        p_min: clip of P inside eq. 12's log.
        normalise: the per-receiver normalisation of each vehicle's utility (``normalise_reward``).
    """

    def __init__(self, links: SnapshotLinks, p_min: float, normalise: bool = True) -> None:
        if not links.compiled:
            raise ValueError(
                "the team search needs the compiled link kernels (WINNER+ B1, truth_los snapshot or always)"
            )
        self.links = links
        self.p_min = float(p_min)
        count = links.target.sum(axis=1)
        n = links.n
        self.weight = (1.0 / (n * np.maximum(count, 1))) if normalise else np.full(n, 1.0 / n)
        self.positions_m = np.zeros((n, 2))
        self.value = np.nan
        self._state: tuple = ()
        self._gain = np.zeros((n, n))

    def set_positions(self, positions_m: FloatArray) -> float:
        """Take ``positions_m`` [N, 2] (m) as the current positions; returns ``J`` there."""
        links = self.links
        self.positions_m = np.array(positions_m, dtype=np.float64)
        (period, los, _g, wb1, range2, idx, val, noise, model, per_sinr, per, thr, sens, target) = links.kernel_args
        self._gain = links.gain_db(self.positions_m)
        rx_dbm, rx_mw, term, total = team_terms(
            self.positions_m, period, los, self._gain, wb1, range2, idx, val, noise, model, per_sinr, per, thr, sens,
            target, self.weight, self.p_min,
        )  # fmt: skip
        self._state = (rx_dbm, rx_mw, term, float(total))
        self.value = float(total)
        return self.value

    def field_rows(self, mover: int, candidates_m: FloatArray) -> FloatArray:
        """[M, N] the field of ``mover``'s links at each candidate [M, 2] (m), the others where they are
        (:meth:`ShadowField.row_db`); needs a field."""
        assert self.links.field is not None
        return self.links.field.row_db(mover, self.positions_m, candidates_m)

    def move_values(self, mover: int, candidates_m: FloatArray, field_db: FloatArray | None = None) -> FloatArray:
        """[M] ``J`` with vehicle ``mover`` at each candidate [M, 2] (m), the others where they are.

        Args:
            mover: the vehicle that moves.
            candidates_m: [M, 2] its positions (m).
            field_db: [M, N] with a field, its values on the mover's links at the candidates when already
                known (:meth:`field_rows`, :meth:`ShadowField.lattice_row_db`); None: computed here.
        """
        links = self.links
        cand = np.ascontiguousarray(np.asarray(candidates_m, dtype=np.float64).reshape(-1, 2))
        if links.field is None:
            g_out = np.ascontiguousarray(self._gain[mover][None, :])
            g_in = np.ascontiguousarray(self._gain[:, mover][None, :])
        else:  # the field of the mover's links at each candidate (symmetric: one table both ways)
            rows = self.field_rows(mover, cand) if field_db is None else field_db
            g_out = np.ascontiguousarray(links.eirp_dbm - rows)
            g_in = g_out
        (period, los, _g, wb1, range2, idx, val, noise, model, per_sinr, per, thr, sens, target) = links.kernel_args
        return team_move_objective(
            cand, int(mover), g_out, g_in, self.positions_m, period, los, wb1, range2, idx, val, noise, model,
            per_sinr, per, thr, sens, target, self.weight, self.p_min, *self._state,
        )  # fmt: skip


def difference_rewards(
    links: SnapshotLinks,
    positions_m: FloatArray,
    start_m: FloatArray,
    movers: NDArray[np.bool_],
    p_min: float,
    normalise: bool = True,
) -> FloatArray:
    """[N] each vehicle's difference reward: its marginal contribution to the team objective,
    ``D_i = J(x) - J(x with vehicle i back at its start)`` (Wolpert & Tumer, "Optimal payoff functions for
    members of collectives", 2001, with the stay-put action as the counterfactual), the env's
    ``reward="difference"``.

    ``J(x) - D_i`` does not depend on where ``i`` is, so ``D_i`` moves with vehicle ``i``'s position as ``J``
    does (the same gradient for ``i``) while the other vehicles' moves add no noise of their own to it (they
    change ``D_i`` only through their interaction with ``i``). With the ``improvement`` reward form the
    rewards of an episode sum to ``D_i`` at its end, ``D_i`` being 0 at the start.

    Args:
        links: the snapshot's links (compiled kernels, as :class:`TeamObjective`).
        positions_m: [N, 2] where the vehicles are (m).
        start_m: [N, 2] where they started the episode (m).
        movers: [N] which vehicles move (the others' ``D`` is 0).
        p_min: clip of P inside eq. 12's log.
        normalise: the per-receiver normalisation (``normalise_reward``).

    Returns:
        [N] ``D`` (the units of ``J``: eq. 12 utility per target receiver, averaged over the N vehicles).
    """
    out = np.zeros(links.n)
    moved = np.flatnonzero(movers & np.any(np.asarray(positions_m) != start_m, axis=1))
    if moved.size == 0:  # at the start (every reset): nobody has contributed anything
        return out
    objective = TeamObjective(links, p_min, normalise)
    j_now = objective.set_positions(positions_m)
    for i in moved:  # one incremental evaluation per moved vehicle (its links only)
        out[i] = j_now - objective.move_values(int(i), start_m[i][None, :])[0]
    return out


@dataclass(frozen=True)
class TeamSearchResult:
    """What :func:`team_search` found.

    Attributes:
        positions_m: [N, 2] the best positions found (m).
        objective: ``J`` there (:func:`team_objective`, a full evaluation).
        start_objectives: ``J`` at each start.
        end_objectives: ``J`` at the end of each (start, order) ascent, starts outer.
        rounds: rounds of each ascent.
    """

    positions_m: FloatArray
    objective: float
    start_objectives: tuple[float, ...]
    end_objectives: tuple[float, ...]
    rounds: tuple[int, ...]


@dataclass(frozen=True)
class _Lattice:
    """The points of a square lattice that lie in a reachable set: ``points_m`` [M, 2] are the lattice
    points ``origin_m + (ix, iy) * pitch_m`` (``shape = (nx, ny)``, order ``ix * ny + iy``) where ``keep``."""

    points_m: FloatArray
    origin_m: FloatArray
    pitch_m: float
    shape: tuple[int, int]
    keep: NDArray[np.bool_]


def _lattice_in(reach: ReachableSet, center_m: FloatArray, half_m: float, pitch_m: float) -> _Lattice:
    if np.isinf(half_m):
        lo, hi = reach.bounds()
    else:
        lo, hi = center_m - half_m, center_m + half_m
    axes = [np.arange(lo[c], hi[c] + 0.5 * pitch_m, pitch_m) for c in range(2)]
    gx, gy = np.meshgrid(*axes, indexing="ij")
    pts = np.stack((gx.ravel(), gy.ravel()), axis=1)
    keep = reach.contains(pts)
    return _Lattice(pts[keep], np.array([axes[0][0], axes[1][0]]), float(pitch_m), (axes[0].size, axes[1].size), keep)


def _grid_in(reach: ReachableSet, center_m: FloatArray, half_m: float, pitch_m: float) -> FloatArray:
    """The points of a square grid of pitch ``pitch_m`` and half-width ``half_m`` around ``center_m``
    that lie in ``reach`` (the whole set's bounding box when ``half_m`` is inf)."""
    return _lattice_in(reach, center_m, half_m, pitch_m).points_m


def _single_move(
    objective: TeamObjective,
    pos: FloatArray,
    j_now: float,
    i: int,
    reaches: dict[int, ReachableSet],
    coarse: dict[int, _Lattice],
    grids_m: Sequence[float],
    tol: float,
) -> tuple[FloatArray, float]:
    """Vehicle ``i`` to its best position for the team, the others fixed (coarse grid, then finer ones)."""
    lat = coarse[i]
    cand = np.concatenate([pos[i][None], lat.points_m])
    field_db = None
    field = objective.links.field
    if field is not None:  # the coarse lattice's field by rotation, the current position directly
        on_lattice = field.lattice_row_db(i, objective.positions_m, lat.origin_m, lat.pitch_m, lat.shape)[lat.keep]
        field_db = np.concatenate([objective.field_rows(i, pos[i][None]), on_lattice])
    vals = objective.move_values(i, cand, field_db)
    b = int(np.argmax(vals))
    x_best, j_best = cand[b].copy(), float(vals[b])
    for coarse_pitch, pitch in pairwise(grids_m):
        fine = _grid_in(reaches[i], x_best, float(coarse_pitch), float(pitch))
        if fine.size:
            vf = objective.move_values(i, fine)
            bf = int(np.argmax(vf))
            if vf[bf] > j_best:
                x_best, j_best = fine[bf].copy(), float(vf[bf])
    if j_best > j_now + tol:
        pos = pos.copy()
        pos[i] = x_best
        j_now = objective.set_positions(pos)
    return pos, j_now


def team_moves(
    env: PlanningEnv,
    sequential: bool = False,
    normalise: bool = True,
    grids_m: Sequence[float] = TEAM_GRIDS_M,
    tol: float = 1e-12,
) -> FloatArray:
    """[N, 2] each vehicle's best reachable position for the team objective ``J`` by one single move of
    :func:`team_search` (coarse grid, then finer ones), from where the vehicles are now.

    Args:
        env: a snapshot-mode env (its links, ``p_min``, positions and reachable sets now).
        sequential: False: each vehicle's move with every other where it is now (decentralised moves made at
            once); True: the vehicles in index order, each seeing the moves before it (one round of
            :func:`team_search`'s ascent from here, without pair moves).
        normalise: per-receiver normalisation (the env's ``normalise_reward``).
        grids_m: the pitches (m), coarse to fine. tol: smallest rise of ``J`` that counts as a move.
    """
    now = np.array(env.positions_m, dtype=np.float64)
    n = now.shape[0]
    reaches = {i: reachable_set(env, i) for i in range(n)}
    coarse = {i: _lattice_in(reaches[i], reaches[i].start_m, np.inf, float(grids_m[0])) for i in range(n)}
    objective = TeamObjective(env.links, env.p_min, normalise)
    out, pos = now.copy(), now.copy()
    j_now = objective.set_positions(now)
    for i in range(n):
        if not sequential:
            pos, j_now = now, objective.set_positions(now)  # a move above may have changed the state
        pos, j_now = _single_move(objective, pos, j_now, i, reaches, coarse, grids_m, tol)
        out[i] = pos[i]
    return pos if sequential else out


def team_move(
    env: PlanningEnv,
    i: int,
    positions_m: FloatArray,
    normalise: bool = True,
    grids_m: Sequence[float] = TEAM_GRIDS_M,
    tol: float = 1e-12,
) -> FloatArray:
    """[2] vehicle ``i``'s best reachable position for the team objective ``J`` with the others at ``positions_m``
    (one single move of :func:`team_search`, as :func:`team_moves`; its reachable set from where it is now).

    Args:
        env: a snapshot-mode env (its links, ``p_min``, the vehicle's reachable set now).
        i: the vehicle.
        positions_m: [N, 2] where every vehicle is taken to be (m; row ``i``: where ``i`` is now).
        normalise, grids_m, tol: as :func:`team_moves`.
    """
    pos = np.array(positions_m, dtype=np.float64)
    reach = reachable_set(env, i)
    coarse = {i: _lattice_in(reach, reach.start_m, np.inf, float(grids_m[0]))}
    objective = TeamObjective(env.links, env.p_min, normalise)
    j_now = objective.set_positions(pos)
    moved, _ = _single_move(objective, pos, j_now, i, {i: reach}, coarse, grids_m, tol)
    return moved[i].copy()


def _thin(points: FloatArray, count: int) -> FloatArray:
    """At most ``count`` of ``points`` [M, 2], evenly spaced in their order."""
    if points.shape[0] <= count:
        return points
    return points[np.linspace(0, points.shape[0] - 1, count).round().astype(np.int64)]


def _pair_move(
    objective: TeamObjective,
    pos: FloatArray,
    j_now: float,
    a: int,
    b: int,
    coarse: dict[int, _Lattice],
    count: int,
    tol: float,
) -> tuple[FloatArray, float]:
    """Vehicles ``a`` and ``b`` jointly to their best pair of thinned coarse-grid positions, if it raises ``J``."""
    grid_a = np.concatenate([pos[a][None], _thin(coarse[a].points_m, count)])
    grid_b = np.concatenate([pos[b][None], _thin(coarse[b].points_m, count)])
    trial = pos.copy()
    best = (j_now, pos[a].copy(), pos[b].copy())
    for xa in grid_a:
        trial[a] = xa
        objective.set_positions(trial)
        vals = objective.move_values(b, grid_b)
        k = int(np.argmax(vals))
        if vals[k] > best[0]:
            best = (float(vals[k]), xa.copy(), grid_b[k].copy())
    if best[0] > j_now + tol:
        pos = pos.copy()
        pos[a], pos[b] = best[1], best[2]
    return pos, objective.set_positions(pos)


def vehicle_orders(n: int, count: int) -> list[NDArray[np.int64]]:
    """``count`` deterministic visiting orders of N vehicles: index order, reversed, then from the middle
    outwards and its reverse, then rotations."""
    base = np.arange(n)
    middle = np.argsort(np.abs(base - (n - 1) / 2.0), kind="stable")
    orders = [base, base[::-1], middle, middle[::-1]]
    k = 1
    while len(orders) < count:
        orders.append(np.roll(base, k * max(n // count, 1)))
        k += 1
    return [np.asarray(o, dtype=np.int64) for o in orders[:count]]


def team_search(
    env: PlanningEnv,
    starts_m: Sequence[FloatArray] | None = None,
    n_orders: int = 2,
    grids_m: Sequence[float] = TEAM_GRIDS_M,
    max_rounds: int = 4,
    movers: Sequence[int] | None = None,
    normalise: bool = True,
    tol: float = 1e-12,
    pair_points: int = 16,
    min_round_gain: float = 1e-4,
) -> TeamSearchResult:
    """Coordinate ascent of the team objective over the movers' reachable sets (module docstring).

    Args:
        env: a snapshot-mode env at the time of the search (its links, ``p_min`` and the reachable sets
            from where the vehicles are now: :func:`~cv2x_marl.env.planning.reachable_set`).
        starts_m: [N, 2] start positions of the ascents (each inside the reachable sets); None: where
            the vehicles are now.
        n_orders: vehicle orders per start (:func:`vehicle_orders`).
        grids_m: the pitches (m), coarse to fine; each finer grid spans one coarser pitch either side.
        max_rounds: most rounds of one ascent.
        movers: the vehicles that move (None: every vehicle).
        normalise: per-receiver normalisation of each vehicle's utility (the env's ``normalise_reward``).
        tol: smallest rise of ``J`` that counts as a move.
        pair_points: when a round of single moves gains nothing, every pair of movers is searched jointly
            on their coarse grids thinned to at most this many points each (0: no pair moves), and the
            rounds go on if that gained. Single moves stall where a link is lost unless two vehicles move
            at once (eq. 12's clip at ``p_min`` is flat there); a gain that needs three at once is missed.

        min_round_gain: a round (singles, then pairs) that raises ``J`` by no more than this ends the ascent
            (``J`` is a mean of per-receiver ``ln P``: 1e-4 is about a 0.01 % change of the P's).

    Returns:
        :class:`TeamSearchResult`; its ``objective`` is never below any start's.
    """
    if env.mode != "snapshot":
        raise ValueError("the team search needs the env in snapshot mode")
    if n_orders < 1 or max_rounds < 1 or not grids_m or min(grids_m) <= 0:
        raise ValueError(
            f"n_orders and max_rounds must be >= 1 and grids_m positive, got {n_orders}, {max_rounds}, {grids_m}"
        )
    n = int(np.asarray(env.positions_m).shape[0])
    who = list(range(n)) if movers is None else [int(i) for i in movers]
    reaches = {i: reachable_set(env, i) for i in who}
    coarse = {i: _lattice_in(reaches[i], reaches[i].start_m, np.inf, float(grids_m[0])) for i in who}
    starts = (
        [np.array(env.positions_m, dtype=np.float64)]
        if starts_m is None
        else [np.array(s, dtype=np.float64) for s in starts_m]
    )
    objective = TeamObjective(env.links, env.p_min, normalise)
    pairs = [(a, b) for a in who for b in who if a < b] if pair_points > 0 else []
    best_pos, best_j = starts[0], -np.inf
    start_j, end_j, rounds_used = [], [], []
    for start in starts:
        start_j.append(objective.set_positions(start))
        for order in vehicle_orders(len(who), n_orders):
            pos = start.copy()
            j_now = objective.set_positions(pos)
            used = 0
            for _ in range(max_rounds):
                used += 1
                j_round = j_now
                for k in order:
                    pos, j_now = _single_move(objective, pos, j_now, who[int(k)], reaches, coarse, grids_m, tol)
                if j_now <= j_round + min_round_gain and pairs:  # single moves stall: joint moves of pairs
                    for a, b in pairs:
                        pos, j_now = _pair_move(objective, pos, j_now, a, b, coarse, pair_points, tol)
                if j_now <= j_round + min_round_gain:
                    break
            end_j.append(j_now)
            rounds_used.append(used)
            if j_now > best_j:
                best_pos, best_j = pos.copy(), j_now
    return TeamSearchResult(
        best_pos,
        team_objective(env.links, best_pos, env.p_min, normalise),
        tuple(start_j),
        tuple(end_j),
        tuple(rounds_used),
    )
