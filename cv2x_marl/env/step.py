"""The env's per-step arithmetic, compiled once and shared by every step path.

:meth:`MobilityEnv.step <cv2x_marl.env.mobility_env.MobilityEnv.step>` (every vehicle),
:meth:`~cv2x_marl.env.mobility_env.MobilityEnv.step_mover` (one mover) and the K batched copies of
:func:`cv2x_marl.env.mover_kernels.mover_steps` call these functions and nothing else for the arithmetic
of a step, so their results are equal by construction (same functions, same order of floating-point
operations), not by keeping three copies in step:

- :func:`move_vehicle`: the action clip, the plan residual, the settle phase, the step scale, the
  drift bound (:func:`drift_factor`) and the region bound of one vehicle (snapshot mode);
  :func:`move_vehicles` applies it to every vehicle, :func:`traffic_offsets` is its traffic-mode
  counterpart (offsets off the road positions);
- :func:`utility_of`: eq. 12 utility, PRR and Jain's index of one transmitter's links
  (:func:`cv2x_marl.utility.link_summary`) and the per-receiver normalisation; :func:`utilities`
  for every vehicle;
- :func:`move_geometry`: row and column of the pair geometry after one vehicle moved;
- :func:`step_reward` / :func:`step_rewards`: the ``utility`` or ``improvement`` reward form;
- :func:`own_state_update` / :func:`own_v1_entries`: observation version 1's own state of an agent
  and its nine own entries (:data:`~cv2x_marl.env.observation.OWN_V1_NAMES`);
- :func:`decode_actions`: the actions a step received, checked and laid out by vehicle index;
  :func:`speed_commands`: speed and lane actions as target speeds and lane commands.

Lengths in m, utilities in nats (eq. 12's natural log).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.env.observation import OWN_V1
from cv2x_marl.sim import mobility
from cv2x_marl.sim.kernels import moved_signal_dbm, success_at_level
from cv2x_marl.utility import link_summary

FloatArray = NDArray[np.float64]


@njit(cache=True)
def drift_factor(d0_m: float, d1_m: float, max_drift_m: float) -> float:
    """Scale that brings a displacement ``(d0_m, d1_m)`` within ``max_drift_m`` of its origin (1 inside)."""
    return min(1.0, max_drift_m / max(np.hypot(d0_m, d1_m), 1e-12))


@njit(cache=True)
def move_vehicle(
    a0: float,
    a1: float,
    x_m: float,
    y_m: float,
    start_x_m: float,
    start_y_m: float,
    plan_x_m: float,
    plan_y_m: float,
    step_m: float,
    max_step_m: float,
    residual: bool,
    settle: bool,
    max_drift_m: float,
    roi: bool,
    box_x_m: float,
    box_y_m: float,
) -> tuple[float, float]:
    """Where one vehicle's action takes it in snapshot mode.

    The action ``(a0, a1)`` (``Box(-1, 1)``) plus, with ``residual``, the straight step towards the
    plan as an action (``clip((plan - position) / max_step_m, -1, 1)``), clipped to [-1, 1] and times
    ``step_m`` (``max_step_m`` for a mover, 0 for a vehicle that stays put); no move while ``settle``.
    Then the drift bound (within ``max_drift_m`` of the start; ``inf``: none) and, with ``roi``, the
    region bound ``[0, box]``.

    Returns:
        the new position ``(x_m, y_m)``.
    """
    if residual:
        a0 = a0 + min(max((plan_x_m - x_m) / max_step_m, -1.0), 1.0)
        a1 = a1 + min(max((plan_y_m - y_m) / max_step_m, -1.0), 1.0)
    off0 = min(max(a0, -1.0), 1.0) * step_m
    off1 = min(max(a1, -1.0), 1.0) * step_m
    if settle:
        off0 = 0.0
        off1 = 0.0
    x = x_m + off0
    y = y_m + off1
    if max_drift_m < np.inf:
        d0 = x - start_x_m
        d1 = y - start_y_m
        f = drift_factor(d0, d1, max_drift_m)
        x = start_x_m + d0 * f
        y = start_y_m + d1 * f
    if roi:
        x = min(max(x, 0.0), box_x_m)
        y = min(max(y, 0.0), box_y_m)
    return x, y


@njit(cache=True)
def is_clipped(a0: float, a1: float) -> bool:
    """Whether an action left the box ``[-1, 1]^2`` (the ``clipped`` info)."""
    return a0 < -1.0 or a0 > 1.0 or a1 < -1.0 or a1 > 1.0


@njit(cache=True)
def move_vehicles(
    actions: FloatArray,
    positions_m: FloatArray,
    start_m: FloatArray,
    plan_m: FloatArray,
    step_m: FloatArray,
    max_step_m: float,
    residual: bool,
    settle: bool,
    max_drift_m: float,
    roi: bool,
    box_m: FloatArray,
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """:func:`move_vehicle` for every vehicle: ``actions``, ``positions_m``, ``start_m``, ``plan_m``
    [N, 2], ``step_m`` [N]. Returns the new positions [N, 2], the applied offsets [N, 2] (new minus
    old) and which actions left the box [N]."""
    n = positions_m.shape[0]
    new = np.empty((n, 2))
    applied = np.empty((n, 2))
    clipped = np.empty(n, dtype=np.bool_)
    for i in range(n):
        a0 = actions[i, 0]
        a1 = actions[i, 1]
        clipped[i] = is_clipped(a0, a1)
        x, y = move_vehicle(
            a0, a1, positions_m[i, 0], positions_m[i, 1], start_m[i, 0], start_m[i, 1], plan_m[i, 0], plan_m[i, 1],
            step_m[i], max_step_m, residual, settle, max_drift_m, roi, box_m[0], box_m[1],
        )  # fmt: skip
        new[i, 0] = x
        new[i, 1] = y
        applied[i, 0] = x - positions_m[i, 0]
        applied[i, 1] = y - positions_m[i, 1]
    return new, applied, clipped


@njit(cache=True)
def traffic_offsets(
    actions: FloatArray, offsets_m: FloatArray, step_m: FloatArray, settle: bool, max_drift_m: float
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Traffic mode (``traffic_action="offset"``): the radio offsets [N, 2] off the road positions after
    the actions [N, 2] (clip, step scale ``step_m`` [N], settle phase as :func:`move_vehicle`), bounded
    to ``max_drift_m`` from the road position (``inf``: none). Returns the new offsets, the applied
    change [N, 2] and which actions left the box [N]."""
    n = offsets_m.shape[0]
    total = np.empty((n, 2))
    applied = np.empty((n, 2))
    clipped = np.empty(n, dtype=np.bool_)
    for i in range(n):
        a0 = actions[i, 0]
        a1 = actions[i, 1]
        clipped[i] = is_clipped(a0, a1)
        off0 = min(max(a0, -1.0), 1.0) * step_m[i]
        off1 = min(max(a1, -1.0), 1.0) * step_m[i]
        if settle:
            off0 = 0.0
            off1 = 0.0
        t0 = offsets_m[i, 0] + off0
        t1 = offsets_m[i, 1] + off1
        if max_drift_m < np.inf:
            f = drift_factor(t0, t1, max_drift_m)
            t0 *= f
            t1 *= f
        total[i, 0] = t0
        total[i, 1] = t1
        applied[i, 0] = t0 - offsets_m[i, 0]
        applied[i, 1] = t1 - offsets_m[i, 1]
    return total, applied, clipped


@njit(cache=True)
def utility_of(
    p_row: FloatArray, target_row: NDArray[np.bool_], p_min: float, normalise: bool
) -> tuple[float, float, float, int]:
    """Eq. 12 utility (divided by the number of target receivers with ``normalise``), PRR and Jain's
    index of one transmitter's links ``p_row`` [N] (:func:`cv2x_marl.utility.link_summary`); also the
    number of target receivers."""
    u, prr, jain, count = link_summary(p_row, target_row, p_min)
    if normalise:
        u = u / max(count, 1)
    return u, prr, jain, count


@njit(cache=True)
def utilities(
    p: FloatArray, target: NDArray[np.bool_], p_min: float, normalise: bool
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.int64]]:
    """:func:`utility_of` for every transmitter of ``p``, ``target`` [N, N]: utilities, PRR, Jain's
    index and target counts, each [N]."""
    n = p.shape[0]
    u = np.empty(n)
    prr = np.empty(n)
    jain = np.empty(n)
    count = np.empty(n, dtype=np.int64)
    for i in range(n):
        u[i], prr[i], jain[i], count[i] = utility_of(p[i], target[i], p_min, normalise)
    return u, prr, jain, count


@njit(cache=True)
def per_receiver(u: float, count: int, normalise: bool) -> float:
    """A utility per target receiver (the scale of the v1 observation), whatever ``normalise``."""
    return u if normalise else u / max(count, 1)


@njit(cache=True)
def move_geometry(
    i: int, positions_m: FloatArray, period_m: FloatArray, disp_m: FloatArray, dist2_m2: FloatArray
) -> None:
    """Update row and column ``i`` of the pair geometry (``disp_m`` [2, N, N], ``dist2_m2`` [N, N], in
    place) after vehicle ``i`` moved to ``positions_m[i]`` (m; ``period_m`` [2]: the torus, inf where
    the area does not wrap)."""
    n = positions_m.shape[0]
    x = positions_m[i, 0]
    y = positions_m[i, 1]
    for j in range(n):
        dx = positions_m[j, 0] - x
        dy = positions_m[j, 1] - y
        if period_m[0] < np.inf:
            dx -= period_m[0] * np.rint(dx / period_m[0])
        if period_m[1] < np.inf:
            dy -= period_m[1] * np.rint(dy / period_m[1])
        if j == i:
            dx = 0.0
            dy = 0.0
        disp_m[0, i, j] = dx
        disp_m[1, i, j] = dy
        dist2_m2[i, j] = dx * dx + dy * dy
    for j in range(n):
        disp_m[0, j, i] = -disp_m[0, i, j]  # -0.0 on the diagonal
        disp_m[1, j, i] = -disp_m[1, i, j]
        dist2_m2[j, i] = dist2_m2[i, j]


@njit(cache=True)
def step_reward(base: float, base_prev: float, improvement: bool) -> tuple[float, float]:
    """The reward of a step from the agent's ``base`` reward after it (the ``reward`` combination of
    utilities): ``base`` itself (``utility`` form) or its change ``base - base_prev`` (``improvement``).
    Returns the reward and the new ``base_prev``."""
    if improvement:
        return base - base_prev, base
    return base, base_prev


@njit(cache=True)
def step_rewards(base: FloatArray, base_prev: FloatArray, improvement: bool) -> FloatArray:
    """:func:`step_reward` of every agent ([N]; ``base_prev`` updated in place)."""
    out = np.empty(base.shape[0])
    for i in range(base.shape[0]):
        out[i], base_prev[i] = step_reward(base[i], base_prev[i], improvement)
    return out


@njit(cache=True)
def own_state_update(u_new: float, u_now: float, u_best: float) -> tuple[float, float, float, bool]:
    """Observation version 1's own state after a step with utility ``u_new`` (per receiver).

    Returns:
        ``(u_prev, u_now, u_best, better)``: the previous utility, the new one, the best so far, and
        whether this step is the new best (then the best position becomes the current one).
    """
    better = u_new > u_best
    return u_now, u_new, u_new if better else u_best, better


@njit(cache=True)
def own_state_updates(
    u: FloatArray,
    count: NDArray[np.int64],
    normalise: bool,
    u_now: FloatArray,
    u_prev: FloatArray,
    u_best: FloatArray,
    best_m: FloatArray,
    positions_m: FloatArray,
) -> None:
    """:func:`own_state_update` of every agent (utilities ``u`` and target counts ``count`` [N]), in place."""
    for i in range(u.shape[0]):
        u_prev[i], u_now[i], u_best[i], better = own_state_update(
            per_receiver(u[i], count[i], normalise), u_now[i], u_best[i]
        )
        if better:
            best_m[i, 0] = positions_m[i, 0]
            best_m[i, 1] = positions_m[i, 1]


@njit(cache=True)
def reach_m(t: int, max_cycles: int, settle_steps: int, max_step_m: float) -> float:
    """How far an agent can still move (m): the moving steps left times ``max_step_m``."""
    return max(max_cycles - settle_steps - t, 0) * max_step_m


@njit(cache=True)
def own_v1_entries(
    out: NDArray[np.float32],
    lo: int,
    obs_clip: float,
    scale_m: float,
    reach: float,
    u_now: float,
    u_prev: float,
    u_start: float,
    u_best: float,
    best_x_m: float,
    best_y_m: float,
    plan_x_m: float,
    plan_y_m: float,
    x_m: float,
    y_m: float,
) -> None:
    """Write one agent's :data:`~cv2x_marl.env.observation.OWN_V1` own entries (utility now, 10 x its
    change, change since the start, gap to the best, offsets to the best position and to the plan,
    reach; lengths over ``scale_m``), clipped to ``obs_clip``, into ``out[lo : lo + OWN_V1]``."""
    inv = 1.0 / scale_m
    own = (
        u_now,
        10.0 * (u_now - u_prev),
        u_now - u_start,
        u_best - u_now,
        (best_x_m - x_m) * inv,
        (best_y_m - y_m) * inv,
        (plan_x_m - x_m) * inv,
        (plan_y_m - y_m) * inv,
        reach * inv,
    )
    for f in range(OWN_V1):
        out[lo + f] = min(max(own[f], -obs_clip), obs_clip)


@njit(cache=True)
def own_v1_block(
    obs: NDArray[np.float32],
    lo: int,
    obs_clip: float,
    scale_m: float,
    reach: float,
    u_now: FloatArray,
    u_prev: FloatArray,
    u_start: FloatArray,
    u_best: FloatArray,
    best_m: FloatArray,
    plan_m: FloatArray,
    positions_m: FloatArray,
) -> None:
    """:func:`own_v1_entries` of every agent into ``obs`` [N, size] (in place)."""
    for i in range(obs.shape[0]):
        own_v1_entries(
            obs[i], lo, obs_clip, scale_m, reach, u_now[i], u_prev[i], u_start[i], u_best[i], best_m[i, 0],
            best_m[i, 1], plan_m[i, 0], plan_m[i, 1], positions_m[i, 0], positions_m[i, 1],
        )  # fmt: skip


# -- the batched one-mover copies (env/mover_batch.py, env/mover_batch_v3.py) ------------------------
#: columns of the per-copy scalar state ``MoverBatch.scalars`` [K, N_SCALARS]
U, U0, PRR, PRR0, JAIN, BASE_PREV, U_NOW, U_PREV, U_START, U_BEST = range(10)
N_SCALARS = 10


@njit(cache=True)
def mover_row_into(
    x: float,
    y: float,
    positions_m: FloatArray,
    i: int,
    target_row: NDArray[np.bool_],
    p_row: FloatArray,
    los_row: NDArray[np.bool_],
    gain_row_db: FloatArray,
    level_db: FloatArray,
    period_m: FloatArray,
    wb1: FloatArray,
    range2_m2: float,
    link_model: int,
    per_sinr_db: FloatArray,
    per: FloatArray,
    threshold_db: float,
    sensitivity_dbm: float,
) -> None:
    """Into ``p_row`` [N]: the success of mover ``i``'s links with it at ``(x, y)`` (m), 0 where the
    receiver is not a target: :func:`cv2x_marl.sim.kernels.mover_row_success`'s per-link code (the
    signal from the moved transmitter, the interference level ``level_db`` [N] of each receiver)."""
    for j in range(p_row.shape[0]):
        if target_row[j]:
            s_dbm = moved_signal_dbm(x, y, positions_m, i, j, period_m, los_row, gain_row_db, wb1, range2_m2)
            p_row[j] = success_at_level(s_dbm, level_db[j], link_model, per_sinr_db, per, threshold_db, sensitivity_dbm)
        else:
            p_row[j] = 0.0


@njit(cache=True)
def record_mover_step(
    i: int,
    x: float,
    y: float,
    x_old: float,
    y_old: float,
    clipped: bool,
    positions_m: FloatArray,
    p_row: FloatArray,
    target_row: NDArray[np.bool_],
    scalars: FloatArray,
    best_m: FloatArray,
    disp_m: FloatArray,
    dist2_m2: FloatArray,
    period_m: FloatArray,
    p_min: float,
    normalise: bool,
    improvement: bool,
    own_state: bool,
    info: FloatArray,
) -> float:
    """What one copy's step records once the mover's links ``p_row`` [N] are known, as ``step_mover``:
    eq. 12 utility, PRR and Jain into ``scalars`` [N_SCALARS], the pair-geometry update, the reward
    (returned), with ``own_state`` the v1 own state (best utility and where, ``best_m`` [2]), and the
    info row ``info`` [8] (``INFO_KEYS``)."""
    u, prr, jain, count = utility_of(p_row, target_row, p_min, normalise)
    scalars[U] = u
    scalars[PRR] = prr
    scalars[JAIN] = jain
    move_geometry(i, positions_m, period_m, disp_m, dist2_m2)
    reward, scalars[BASE_PREV] = step_reward(u, scalars[BASE_PREV], improvement)
    if own_state:
        scalars[U_PREV], scalars[U_NOW], scalars[U_BEST], better = own_state_update(
            per_receiver(u, count, normalise), scalars[U_NOW], scalars[U_BEST]
        )
        if better:
            best_m[0] = x
            best_m[1] = y
    info[0] = u
    info[1] = scalars[U0]
    info[2] = prr
    info[3] = scalars[PRR0]
    info[4] = jain
    info[5] = x - x_old
    info[6] = y - y_old
    info[7] = 1.0 if clipped else 0.0
    return reward


def speed_commands(
    act: FloatArray, mover_mask: NDArray[np.bool_], limit_mps: float, active: bool
) -> tuple[FloatArray, NDArray[np.int64]]:
    """``traffic_action="speed"``: the movers' actions [N, 2] as target speeds [N] (m/s; NaN: no command,
    the vehicles that do not move, and every vehicle when not ``active``: the settle phase) and lane
    commands [N] (+1 one lane left, -1 right, 0 keep): ``action[0]`` in [-1, 1] maps linearly onto
    [0, ``limit_mps``], ``action[1]`` > 0.5 / < -0.5 asks for a lane to the left / right (the action
    clipped to the box first)."""
    n = act.shape[0]
    target = np.full(n, np.nan)
    lanes = np.zeros(n, dtype=np.int64)
    if active:
        a = np.minimum(np.maximum(act, -1.0), 1.0)
        target[mover_mask] = 0.5 * (a[mover_mask, 0] + 1.0) * limit_mps
        lanes[mover_mask] = np.where(a[mover_mask, 1] > 0.5, 1, np.where(a[mover_mask, 1] < -0.5, -1, 0))
    return target, lanes


def speed_change_commands(
    act: FloatArray,
    mover_mask: NDArray[np.bool_],
    speed_mps: FloatArray,
    limit_mps: float,
    accel_mps2: float,
    decel_mps2: float,
    period_s: float,
    active: bool,
) -> tuple[FloatArray, NDArray[np.int64]]:
    """``speed_command="change"``: the movers' actions [N, 2] as target speeds [N] (m/s; NaN as
    :func:`speed_commands`) and lane commands [N]: ``action[0]`` in [-1, 1] (clipped) changes the own speed
    ``speed_mps`` [N] by ``a accel_mps2 period_s`` (a > 0) or ``a decel_mps2 period_s`` (a < 0), within
    [0, ``limit_mps``], so a zero action holds the speed exactly; ``action[1]`` as :func:`speed_commands`."""
    target, lanes = speed_commands(act, mover_mask, limit_mps, active)
    if active:
        a = np.minimum(np.maximum(act[mover_mask, 0], -1.0), 1.0)
        change = np.where(a > 0.0, a * accel_mps2, a * decel_mps2) * period_s
        target[mover_mask] = np.minimum(np.maximum(speed_mps[mover_mask] + change, 0.0), limit_mps)
    return target, lanes


def check_action_agents(actions: Any, live: set[str], agents: list[str]) -> None:
    """Refuse a step's ``actions`` unless they are a dict with one entry per live agent (``live``; ``agents``: the live
    agents in order, for the messages): every action kind checks this first.

    Raises:
        TypeError: ``actions`` is not a dict.
        KeyError: an unknown or finished agent, or a live agent without an action (named).
    """
    if not isinstance(actions, dict):
        raise TypeError(f"actions must be a dict agent -> action, got {type(actions).__name__}")
    if actions.keys() != live:
        unknown = [a for a in actions if a not in live]
        if unknown:
            shown = f"{agents[0]} .. {agents[-1]}" if agents else "none"
            raise KeyError(f"unknown or finished agent(s) {unknown}; live agents: {shown}")
        missing = [a for a in agents if a not in actions]
        raise KeyError(f"missing action(s) for {missing[:5]}{' ...' if len(missing) > 5 else ''}")


def decode_actions(
    actions: Any,
    live: set[str],
    agents: list[str],
    possible_agents: list[str],
    agent_index: dict[str, int],
) -> FloatArray:
    """The actions a ``step`` received, checked, as [N, 2] by vehicle index (0 for vehicles without an
    action: the finished ones).

    Args:
        actions: agent name -> action (shape (2,), finite numbers).
        live: the names that must act now (every live agent, no other).
        agents: the live agents in order (for the messages).
        possible_agents: every agent in vehicle order (N).
        agent_index: agent name -> vehicle index.

    Raises:
        TypeError: ``actions`` is not a dict.
        KeyError: an unknown or finished agent, or a live agent without an action (named).
        ValueError: an action that is not numeric, not of shape (2,) or not finite (named with its agent).
    """
    check_action_agents(actions, live, agents)
    try:
        arr = np.array(list(actions.values()), dtype=np.float64).reshape(len(actions), 2)
    except (ValueError, TypeError):  # ragged, wrong size or not numeric: find the culprit
        rows = []
        for a, v in actions.items():
            try:
                row = np.asarray(v, dtype=np.float64)
            except (ValueError, TypeError):
                raise ValueError(f"action of {a} must be numeric with shape (2,), got {v!r}") from None
            if row.size != 2:
                raise ValueError(f"action of {a} must have shape (2,), got shape {row.shape}") from None
            rows.append(row.reshape(2))
        arr = np.array(rows)
    if not np.isfinite(arr).all():
        k = int(np.flatnonzero(~np.isfinite(arr).all(axis=1))[0])
        name = list(actions)[k]
        raise ValueError(f"action of {name} is not finite: {arr[k].tolist()}")
    n = len(possible_agents)
    if len(actions) == n and list(actions) == possible_agents:
        return arr  # the usual case: every agent, in order
    act = np.zeros((n, 2))
    act[[agent_index[a] for a in actions]] = arr
    return act


def drive_state(sim: Any, lanes_per_direction: int) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Speeds [N] (m/s), headings [N, 2] (unit vectors) and lanes [N] (0: next to the centre line) of a traffic-mode
    simulator's vehicles: the lane model's state, or on SUMO lockstep SUMO's speed, angle and lane index (SUMO's
    rightmost lane 0 is lane ``lanes_per_direction - 1`` here; on a junction's internal lanes their index, clipped
    to the road's lanes)."""
    st = sim.state
    if isinstance(st, mobility.VehicleState):
        return st.speed_mps, mobility.headings(st), st.lane
    from cv2x_marl.sim import sumo  # libsumo: a heavy optional dependency

    lock = sumo.lockstep_of(sim)
    top = lanes_per_direction - 1
    return st.speed_mps, lock.heading, np.clip(top - lock.lane_index, 0, top)
