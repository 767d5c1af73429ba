"""The compiled one-mover step of K env copies, with named arguments: what
:class:`~cv2x_marl.env.mover_batch.MoverBatch` calls.

The arguments travel as named tuples (numba takes them as records, read by field name): the copies' stacks
(:class:`CopyStacks`), the link model (:class:`LinkConstants`), the step's options (:class:`StepConstants`), the
observation's layout and model (:class:`ObservationConstants`) and the outputs (:class:`StepOutputs`). Every step
kind shares :func:`move_mover` (the action, the bounds) and :func:`observe_mover` (the v0 block);
:func:`mover_steps` is the step of observation versions 0-2, :func:`cv2x_marl.env.mover_batch_v3.mover_steps_v3`
that of version 3. Each calls the functions :meth:`MobilityEnv.step_mover` calls (:mod:`cv2x_marl.env.step`, the
observation kernels), in the same order, so the results are bit-identical to it (``tests/env/test_vector.py``,
``tests/env/test_v3_fast.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.env import step
from cv2x_marl.env.observation import observation_kernel

FloatArray = NDArray[np.float64]


class CopyStacks(NamedTuple):
    """The per-step state of K copies of N vehicles (G co-channel slots), updated in place.

    Attributes:
        mover, t: [K] each copy's mover and steps taken.
        positions_m, start_m: [K, N, 2] positions now and at the start (m).
        plan_m, best_m: [K, 2] the mover's plan and best position (m).
        disp_m, dist2_m2: [K, 2, N, N], [K, N, N] the pair geometry.
        co_table: [K, N, G] the co-channel table; target, p: [K, N, N] target receivers and link success.
        los_row, gain_row_db, level_db: [K, N] the mover's link constants.
        scalars: [K, N_SCALARS] utilities, PRR, Jain's index, reward base and own state
            (:data:`cv2x_marl.env.step.N_SCALARS`).
    """

    mover: NDArray[np.int64]
    t: NDArray[np.int64]
    positions_m: FloatArray
    start_m: FloatArray
    plan_m: FloatArray
    best_m: FloatArray
    disp_m: FloatArray
    dist2_m2: FloatArray
    co_table: NDArray[np.int64]
    target: NDArray[np.bool_]
    p: FloatArray
    los_row: NDArray[np.bool_]
    gain_row_db: FloatArray
    level_db: FloatArray
    scalars: FloatArray


class LinkConstants(NamedTuple):
    """The link model every copy shares (:class:`~cv2x_marl.sim.ground_truth.SnapshotLinks`' kernel arguments):
    the torus period [2] (m), the WINNER+ B1 constants, the interferer range squared (m^2), the link model's code,
    its PER table (SINR [S] dB, PER [S]), threshold (dB) and sensitivity (dBm)."""

    period_m: FloatArray
    wb1: FloatArray
    range2_m2: float
    link_model: int
    per_sinr_db: FloatArray
    per: FloatArray
    threshold_db: float
    sensitivity_dbm: float


class StepConstants(NamedTuple):
    """The options of a step: the action's scale (m), the episode's length and settle phase (steps), the drift bound
    (m, inf: none), the road box (``roi``, [2] m), the plan residual, the reward's per-receiver utilities and
    improvement form, eq. 12's ``p_min`` and the observation version."""

    max_step_m: float
    max_cycles: int
    settle_steps: int
    max_drift_m: float
    roi: bool
    box_m: FloatArray
    residual: bool
    normalise: bool
    improvement: bool
    p_min: float
    version: int


class ObservationConstants(NamedTuple):
    """The observation's layout (:class:`~cv2x_marl.env.observation.ObservationLayout`: neighbours, scale and region
    (m), interferer range (m), clip, size, the model's extra entries per neighbour, the own entries' offset) and the
    two-distance model of versions 1 and 2 (coefficients [3, ...], logistic or linear, its ``p_min``)."""

    k_neighbours: int
    scale_m: float
    region_m: float
    interferer_range_m: float
    obs_clip: float
    size: int
    extra: int
    own_v1_offset: int
    alpha: FloatArray
    beta: FloatArray
    gamma: FloatArray
    logistic: bool
    model_p_min: float


class StepOutputs(NamedTuple):
    """What a step writes: observations [K, size] float32, rewards [K], truncations [K], info rows [K, 8]
    (:data:`~cv2x_marl.env.infos.INFO_KEYS`)."""

    obs: NDArray[np.float32]
    reward: FloatArray
    done: NDArray[np.bool_]
    info: FloatArray


@njit(cache=True)
def move_mover(
    k: int, actions: FloatArray, s: CopyStacks, c: StepConstants
) -> tuple[int, float, float, float, float, bool]:
    """Copy ``k``'s action and bounds (:func:`~cv2x_marl.env.step.move_vehicle`, as ``step_mover``): the mover moves
    and the copy's clock advances. Returns ``(mover, x, y, x_old, y_old, clipped)``."""
    i = s.mover[k]
    pos = s.positions_m[k]
    x_old = pos[i, 0]
    y_old = pos[i, 1]
    clipped = step.is_clipped(actions[k, 0], actions[k, 1])
    x, y = step.move_vehicle(
        actions[k, 0], actions[k, 1], x_old, y_old, s.start_m[k, i, 0], s.start_m[k, i, 1], s.plan_m[k, 0],
        s.plan_m[k, 1], c.max_step_m, c.max_step_m, c.residual, s.t[k] >= c.max_cycles - c.settle_steps,
        c.max_drift_m, c.roi, c.box_m[0], c.box_m[1],
    )  # fmt: skip
    pos[i, 0] = x
    pos[i, 1] = y
    s.t[k] += 1
    return i, x, y, x_old, y_old, clipped


@njit(cache=True)
def observe_mover(
    k: int, s: CopyStacks, c: StepConstants, o: ObservationConstants, rows: NDArray[np.int64], drift: FloatArray
) -> NDArray[np.float32]:
    """The mover's v0 block (and versions 1-2's link success) [1, size], as ``MobilityEnv.build`` of its row
    (``rows`` [1] holds the mover; ``drift`` [N, 2] is scratch, left holding the drifts)."""
    pos = s.positions_m[k]
    for j in range(pos.shape[0]):
        drift[j, 0] = pos[j, 0] - s.start_m[k, j, 0]
        drift[j, 1] = pos[j, 1] - s.start_m[k, j, 1]
    return observation_kernel(
        s.disp_m[k], s.dist2_m2[k], s.co_table[k], s.target[k], pos, drift, s.t[k] / c.max_cycles, o.k_neighbours,
        o.scale_m, o.region_m, o.interferer_range_m, o.obs_clip, rows, o.size, o.extra, o.alpha, o.beta, o.gamma,
        o.logistic, o.model_p_min, s.p[k],
    )  # fmt: skip


@njit(cache=True)
def mover_steps(
    active: NDArray[np.bool_],
    actions: FloatArray,
    s: CopyStacks,
    links: LinkConstants,
    c: StepConstants,
    o: ObservationConstants,
    out: StepOutputs,
) -> None:
    """Step every ``active`` copy k (observation versions 0-2): what ``MobilityEnv.step_mover(actions[k])`` does,
    in place (``actions`` [K, 2]; the stacks ``s`` and outputs ``out`` as their classes say)."""
    n = s.positions_m.shape[1]
    rows = np.zeros(1, dtype=np.int64)
    drift = np.empty((n, 2))
    for k in range(actions.shape[0]):
        if not active[k]:
            continue
        i, x, y, x_old, y_old, clipped = move_mover(k, actions, s, c)
        pos = s.positions_m[k]
        # the mover's links, then eq. 12, the summaries, the reward, the own state and the info row
        step.mover_row_into(
            x, y, pos, i, s.target[k, i], s.p[k, i], s.los_row[k], s.gain_row_db[k], s.level_db[k], links.period_m,
            links.wb1, links.range2_m2, links.link_model, links.per_sinr_db, links.per, links.threshold_db,
            links.sensitivity_dbm,
        )  # fmt: skip
        out.reward[k] = step.record_mover_step(
            i, x, y, x_old, y_old, clipped, pos, s.p[k, i], s.target[k, i], s.scalars[k], s.best_m[k], s.disp_m[k],
            s.dist2_m2[k], links.period_m, c.p_min, c.normalise, c.improvement, c.version >= 1, out.info[k],
        )  # fmt: skip
        out.done[k] = s.t[k] >= c.max_cycles
        rows[0] = i
        ob = observe_mover(k, s, c, o, rows, drift)
        for f in range(o.size):
            out.obs[k, f] = ob[0, f]
        if c.version >= 1:
            step.own_v1_entries(
                out.obs[k], o.own_v1_offset, o.obs_clip, o.scale_m,
                step.reach_m(s.t[k], c.max_cycles, c.settle_steps, c.max_step_m), s.scalars[k, step.U_NOW],
                s.scalars[k, step.U_PREV], s.scalars[k, step.U_START], s.scalars[k, step.U_BEST], s.best_m[k, 0],
                s.best_m[k, 1], s.plan_m[k, 0], s.plan_m[k, 1], x, y,
            )  # fmt: skip
