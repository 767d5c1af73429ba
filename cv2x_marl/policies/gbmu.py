"""GBMU, the paper's gradient-based mobility updating (Sec. 5, steps 1-5), over arrays.

GBMU knows, for each target receiver j of the mover i (one-hop information, Sec. 5):
the position of j, the distance ``l_j`` from j to its main interferer (from the interferer's
position), ``NSV_j``, and the fitted two-distance model. Steps, batched over B movers:

1. ``G_ij = alpha_j / (d_ij P_ij)`` (eq. 16), computed as ``ln(10) dP/dd / P`` so it is exact
   for any model family (for eq. 15 with log10 it is the paper's expression verbatim);
2. ``t_j = (Pos_i - Pos_j) / d_ij``;
3. ``Pos_ij = Pos_i + delta t_j G_ij``;
4. ``Pos_i <- mean_j Pos_ij``;
5. stop when ``||Pos_i(k+1) - Pos_i(k)|| < Th_pos`` (or at the iteration cap).

Steps 3-4 are ``Pos_i += delta mean_j(t_j G_ij)``: gradient ascent on the model's eq. 12 utility
with step ``delta / |R_i|`` (since ``dd_ij / dPos_i = t_j``). The greedy variant uses eq. 9
(``G = ln(10) dP/dd``, no 1/P); the oracle climbs the true eq. 12 utility of the simulator's link
model with the same step rule, its gradient by central finite differences.

Beyond the paper (issue 15), the step size of step 3 can follow a schedule (:class:`StepSchedule`)
instead of the paper's constant ``delta``:

* ``constant`` (the paper, default): ``delta_k = delta``; bit-identical to the code before schedules.
* ``decay``: ``delta_k = delta / (1 + k / k0)``, k = 0, 1, ... the iteration: a Robbins-Monro
  sequence (Robbins and Monro, 1951: ``sum delta_k = inf``, ``sum delta_k^2 < inf``), which damps
  the oscillation of a constant step around the model's peak while still covering any distance.
* ``backtracking``: Armijo's rule (Armijo, 1966; Nocedal and Wright, *Numerical Optimization*,
  Alg. 3.1): try ``t = delta``, halve ``t`` until the steering model's predicted utility rises by
  at least ``c t grad U . d`` (``c = 1e-4``), at most ``max_halvings`` times, else stay put (which
  step 5 then reads as convergence). With a box on the move (the env's action box) the trial move
  is projected onto it first (Armijo's rule along the projection arc, Bertsekas, *Nonlinear
  Programming*, Sec. 2.3). It never accepts a move that lowers the predicted utility.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env.observation import GbmuInputs
from cv2x_marl.regression.model import TwoDistanceModel
from cv2x_marl.utility import utility_log

FloatArray = NDArray[np.float64]
LN10 = math.log(10.0)
#: step-size schedules of GBMU's step 3 (:class:`StepSchedule`)
SCHEDULES: tuple[str, ...] = ("constant", "decay", "backtracking")


def gbmu_direction(
    inputs: GbmuInputs,
    model: TwoDistanceModel,
    fairness: bool = True,
    min_distance_m: float = 1.0,
) -> Callable[[FloatArray], FloatArray]:
    """Step function ``pos [B, 2] -> mean_j t_j G_ij [B, 2]`` of GBMU (or greedy, ``fairness=False``)."""
    k = np.minimum(inputs.nsv, model.nsv_cap)
    a = model.alpha[k]
    const = model.beta[k] * np.log10(np.where(inputs.mask, inputs.l_m, 1.0)) + model.gamma[k]
    w = inputs.mask / np.maximum(inputs.mask.sum(axis=1, keepdims=True), 1)
    logistic = model.kind == "logistic"
    p_min = model.p_min

    def direction(pos: FloatArray) -> FloatArray:
        diff = pos[:, None, :] - inputs.rx_m
        d = np.maximum(np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2), min_distance_m)
        eta = a * np.log10(d) + const
        if logistic:
            p_raw = 1.0 / (1.0 + np.exp(-eta))
            dpdd_ln10 = p_raw * (1.0 - p_raw) * a / d  # ln(10) dP/dd
        else:
            p_raw = eta
            dpdd_ln10 = a / d
        g = dpdd_ln10 / np.clip(p_raw, p_min, 1.0) if fairness else dpdd_ln10
        coef = w * g / d  # t_j = diff / d
        return np.einsum("br,brc->bc", coef, diff)

    return direction


def oracle_direction(
    success: Callable[[FloatArray], FloatArray],
    mask: NDArray[np.bool_],
    p_min: float = 1e-3,
    h_m: float = 5.0,
) -> Callable[[FloatArray], FloatArray]:
    """Step function of the oracle: ``grad U_true / |R|`` by central differences of the link model.

    The PER table makes the true utility piecewise flat (P is 0 below -2 dB and 0.999 above
    12 dB), so an infinitesimal gradient stalls on plateaus; the default secant over +-5 m
    smooths over them. The oracle is still a local climber: an upper reference for local
    moves, not a bound on what a far move can reach.
    """
    n_rx = np.maximum(mask.sum(axis=1), 1)[:, None]

    def utility(pos: FloatArray) -> FloatArray:
        return utility_log(success(pos), mask, p_min)

    def direction(pos: FloatArray) -> FloatArray:
        grad = np.empty_like(pos)
        for c in range(2):
            e = np.zeros(2)
            e[c] = h_m
            grad[:, c] = (utility(pos + e) - utility(pos - e)) / (2 * h_m)
        return grad / n_rx

    return direction


@dataclass(frozen=True)
class StepSchedule:
    """How GBMU's step size ``delta_k`` of step 3 evolves with the iteration k (module docstring).

    Attributes:
        kind: ``constant`` (the paper), ``decay`` or ``backtracking``.
        decay_k0: iterations after which the decaying step has halved (``decay``; > 0).
        armijo_c: sufficient-increase constant of Armijo's rule, in (0, 1) (``backtracking``).
        shrink: factor applied to a refused trial step, in (0, 1) (``backtracking``).
        max_halvings: refused trials before the mover stays put (``backtracking``; >= 0).
    """

    kind: str = "constant"
    decay_k0: float = 100.0
    armijo_c: float = 1e-4
    shrink: float = 0.5
    max_halvings: int = 30

    def __post_init__(self) -> None:
        if self.kind not in SCHEDULES:
            raise ValueError(f"step_schedule must be one of {', '.join(SCHEDULES)}, got {self.kind!r}")
        if not (math.isfinite(self.decay_k0) and self.decay_k0 > 0):
            raise ValueError(f"decay_k0 must be a finite number > 0, got {self.decay_k0!r}")
        if not 0.0 < self.armijo_c < 1.0:
            raise ValueError(f"armijo_c must lie in (0, 1), got {self.armijo_c!r}")
        if not 0.0 < self.shrink < 1.0:
            raise ValueError(f"shrink must lie in (0, 1), got {self.shrink!r}")
        if self.max_halvings < 0:
            raise ValueError(f"max_halvings must be >= 0, got {self.max_halvings!r}")

    def step_size(self, delta: float, k: int | NDArray[np.int64]) -> float | FloatArray:
        """``delta_k`` of iteration ``k`` (0-based) before any backtracking: ``delta`` for ``constant``
        and ``backtracking`` (its first trial), ``delta / (1 + k / k0)`` for ``decay``."""
        if self.kind == "decay":
            return delta / (1.0 + np.asarray(k, dtype=np.float64) / self.decay_k0)
        return delta


@dataclass(frozen=True)
class SteeringUtility:
    """The steering model's predicted utility of B movers, the function GBMU ascends.

    ``U(x) = sum_j ln max(P_hat(d_j(x), l_j, NSV_j), p_min)`` (eq. 12 with eq. 15 or its logistic
    version) with ``fairness``, ``U(x) = sum_j P_hat`` (eq. 9) without; ``d_j`` floored at
    ``min_distance_m`` as in :func:`gbmu_direction`. Where no clip is active,
    ``grad U = gradient_per_direction * gbmu_direction`` (``|R_i| / ln 10``), which Armijo's
    test uses.
    """

    inputs: GbmuInputs
    model: TwoDistanceModel
    fairness: bool = True
    min_distance_m: float = 1.0

    def __call__(self, pos_m: FloatArray) -> FloatArray:
        """[B] predicted utility with the movers at ``pos_m`` [B, 2] (m)."""
        inp = self.inputs
        diff = np.asarray(pos_m, dtype=np.float64)[:, None, :] - inp.rx_m
        d = np.maximum(np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2), self.min_distance_m)
        p = self.model.predict(d, np.where(inp.mask, inp.l_m, 1.0), inp.nsv)
        per_link = np.log(np.maximum(p, self.model.p_min)) if self.fairness else p
        return np.where(inp.mask, per_link, 0.0).sum(axis=1)

    @property
    def gradient_per_direction(self) -> FloatArray:
        """[B] factor from :func:`gbmu_direction`'s step to ``grad U``: ``max(|R_i|, 1) / ln 10``."""
        return np.maximum(self.inputs.mask.sum(axis=1), 1) / LN10


def armijo_move(
    pos_m: FloatArray,
    direction_m: FloatArray,
    delta: float,
    utility: SteeringUtility,
    schedule: StepSchedule,
    project: Callable[[FloatArray], FloatArray] | None = None,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Armijo backtracking along GBMU's direction, batched over B movers (module docstring).

    Trial moves ``m = project(t d)`` with ``t = delta, delta shrink, ...``; a mover accepts the first
    with ``U(x + m) >= U(x) + c grad U . m``. Since ``grad U . m >= 0`` for the trial moves (a box
    projection keeps the sign of each component), an accepted move never lowers ``U``.

    Args:
        pos_m: [B, 2] the movers' positions (m).
        direction_m: [B, 2] :func:`gbmu_direction` at ``pos_m``.
        delta: first trial step.
        utility: the steering model's :class:`SteeringUtility`.
        schedule: ``armijo_c``, ``shrink`` and ``max_halvings``.
        project: maps trial moves [B, 2] onto the allowed set (e.g. the action box); None: no bound.

    Returns:
        ``(move_m [B, 2], accepted [B])``; a mover that accepted no trial gets a zero move.
    """
    b = pos_m.shape[0]
    u0 = utility(pos_m)
    grad_scale = utility.gradient_per_direction
    t = np.full(b, float(delta))
    move = np.zeros_like(pos_m)
    accepted = np.zeros(b, dtype=bool)
    for _ in range(schedule.max_halvings + 1):
        trial = t[:, None] * direction_m
        if project is not None:
            trial = project(trial)
        slope = grad_scale * np.einsum("bc,bc->b", direction_m, trial)
        ok = ~accepted & (utility(pos_m + trial) >= u0 + schedule.armijo_c * slope)
        move[ok] = trial[ok]
        accepted |= ok
        if accepted.all():
            break
        t *= schedule.shrink
    return move, accepted


@dataclass
class ClimbResult:
    """Outcome of :func:`climb` for B movers.

    Attributes:
        final_m: [B, 2] final positions.
        iterations: [B] iterations each mover ran before stopping (Th_pos) or the cap.
        converged: [B] stopped by Th_pos.
        trajectory_m: [T, B, 2] positions at the recorded iterations (``record_every``).
        recorded_iterations: [T] the iteration numbers recorded (0 = start).
    """

    final_m: FloatArray
    iterations: NDArray[np.int64]
    converged: NDArray[np.bool_]
    trajectory_m: FloatArray
    recorded_iterations: NDArray[np.int64]
    extra: dict[str, FloatArray] = field(default_factory=dict)


def climb(
    start_m: FloatArray,
    direction: Callable[[FloatArray], FloatArray],
    delta: float = 1.0,
    th_pos_m: float = 1e-4,
    max_iterations: int = 10_000,
    record_every: int = 0,
    progress: Callable[[int], object] | None = None,
    schedule: StepSchedule | None = None,
    utility: SteeringUtility | None = None,
) -> ClimbResult:
    """Iterate ``Pos += delta * direction(Pos)`` (steps 3-4) until the move is below Th_pos (step 5).

    Movers that have stopped stay put while the others go on; the loop ends when all have
    stopped or at ``max_iterations``.

    Args:
        schedule: the step-size schedule (:class:`StepSchedule`); None or ``constant``: the paper's
            constant ``delta`` (bit-identical to the code before schedules). ``decay`` uses
            ``delta / (1 + k / k0)`` at iteration k = 0, 1, ...; ``backtracking`` Armijo's rule
            from ``delta`` (:func:`armijo_move`), which needs ``utility``.
        utility: the steering model's :class:`SteeringUtility` (``backtracking`` only).
    """
    if delta <= 0 or th_pos_m < 0 or max_iterations < 0:
        raise ValueError("delta must be > 0, th_pos_m >= 0 and max_iterations >= 0")
    kind = "constant" if schedule is None else schedule.kind
    if kind == "backtracking" and utility is None:
        raise ValueError("the backtracking step schedule needs the steering model's utility (utility=)")
    pos = np.array(start_m, dtype=np.float64, copy=True)
    b = pos.shape[0]
    active = np.ones(b, dtype=bool)
    iterations = np.zeros(b, dtype=np.int64)
    traj = [pos.copy()]
    rec = [0]
    for k in range(1, max_iterations + 1):
        if kind == "constant":
            step = delta * direction(pos)
        elif kind == "decay":
            assert schedule is not None
            step = float(schedule.step_size(delta, k - 1)) * direction(pos)
        else:
            assert schedule is not None and utility is not None
            step, _ = armijo_move(pos, direction(pos), delta, utility, schedule)
        move = np.hypot(step[:, 0], step[:, 1])
        moving = active & (move >= th_pos_m)
        pos[moving] += step[moving]
        iterations[moving] = k
        active = moving
        if record_every and (k % record_every == 0 or not active.any()):
            traj.append(pos.copy())
            rec.append(k)
        if progress is not None and k % 100 == 0:
            progress(100)
        if not active.any():
            break
    converged = ~active
    return ClimbResult(pos, iterations, converged, np.array(traj), np.array(rec))
