"""The one-mover fast path of :class:`~cv2x_marl.env.mobility_env.MobilityEnv`: a step computed for one vehicle.

When one vehicle moves and the reward is its own (snapshot mode, ``SingleMover`` envs), :func:`step_mover` gives
what :meth:`MobilityEnv.step` returns for that vehicle, bit for bit, computed for it alone with the same step
functions (:mod:`cv2x_marl.env.step`; the batched copies of :mod:`cv2x_marl.env.mover_batch` call them too): its
links through :meth:`SnapshotLinks.mover_row` (the interference on them does not change while the others stand
still), its row of the pair geometry and its observation (the observation model's ``*_mover`` methods). With the
shadowing field or observation version 3 its row and column (what it hears: P and received power, for its
measurements) read the field once (:class:`~cv2x_marl.env.mover_links.MoverLinksStep`); the measurement stream
draws every pair's period as :meth:`MobilityEnv.step` does. The other vehicles' rewards, observations and
measurements are not kept current, so after this call use only ``step_mover`` until the next reset.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env import step as step_core
from cv2x_marl.env.infos import INFO_KEYS
from cv2x_marl.env.mover_links import MoverLinksStep

if TYPE_CHECKING:
    from cv2x_marl.env.episode import EpisodeEnv


def fast_mover(env: EpisodeEnv) -> int | None:
    """The vehicle whose step :func:`step_mover` computes alone, or None when it does not apply (it needs
    snapshot mode, one mover and the individual reward; with observation version 3 or the shadowing field
    also the compiled link kernels: WINNER+ B1, ``truth_los`` snapshot or always)."""
    movers = np.flatnonzero(env.mover_mask)
    ok = env.mode == "snapshot" and movers.size == 1 and env.reward_kind == "individual"
    if env.observer.needs_rx or env.options.shadow_field:
        ok = ok and env.config.channel.pathloss == "winner_b1" and env.truth_los != "geometry"
    return int(movers[0]) if ok else None


def _action(env: EpisodeEnv, i: int, action: Any) -> NDArray[np.float64]:
    """The mover's action as a float [2], refused (naming the agent) when not numeric, of another shape or not
    finite."""
    name = env.possible_agents[i]
    try:
        act = np.asarray(action, dtype=np.float64).reshape(2)
    except (ValueError, TypeError):
        raise ValueError(f"action of {name} must be numeric with shape (2,), got {action!r}") from None
    if not np.isfinite(act).all():
        raise ValueError(f"action of {name} is not finite: {act.tolist()}")
    return act


def _move_links(env: EpisodeEnv, i: int) -> None:
    """The mover's links after its move: its row of ``link_p`` (and with the field or version 3, its column and
    received powers), then the observation model's measurements."""
    pos, column = env.positions_m, env.observer.needs_rx
    if env.mover_links is None or env.mover_links.mover != i:
        env.mover_rows = np.array([i], dtype=np.int64)
        if column or env.links.field is not None:  # its row and (v3) its column, the field read once
            env.mover_links = MoverLinksStep(env.links, i, pos, column=column)
        else:
            env.mover_links = env.links.mover_row(i, pos)
    if isinstance(env.mover_links, MoverLinksStep):
        env.mover_links.step(pos, env.link_p, env.rx_dbm if column else None)
    else:
        env.link_p[i] = env.mover_links.success(pos[i : i + 1])[0]
    env.observer.after_links_mover(env, env.mover_rows)


def step_mover(env: EpisodeEnv, action: Any) -> tuple[NDArray[np.float32], float, bool, dict[str, float]]:
    """One step in which only :attr:`MobilityEnv.fast_mover` moves.

    Returns:
        Its observation [size], reward, truncation and info (:data:`INFO_KEYS`).
    """
    i = env.fast_mover
    if i is None:
        raise RuntimeError("step_mover needs snapshot mode, exactly one mover and reward='individual'")
    if not env.agents:
        raise RuntimeError("step() called on a finished episode: call reset()")
    act = _action(env, i, action)
    clipped = bool(step_core.is_clipped(act[0], act[1]))
    pos, residual = env.positions_m, env.dynamics.residual
    old_x, old_y = pos[i]
    plan_x, plan_y = env.plan_m[i] if residual else (old_x, old_y)
    pos[i] = step_core.move_vehicle(
        act[0], act[1], old_x, old_y, env.start_m[i, 0], env.start_m[i, 1], plan_x, plan_y, env.max_step_m,
        env.max_step_m, residual, env.t >= env.max_cycles - env.settle_steps, env.drift_m, env.roi, env.box_m[0],
        env.box_m[1],
    )  # fmt: skip
    env.t += 1
    env.tracks.append(pos.copy())
    _move_links(env, i)
    u, env.prr[i], env.jain[i], count = step_core.utility_of(
        env.link_p[i], env.target[i], env.p_min, env.normalise_reward
    )
    env.utility[i] = u
    assert env.geometry is not None
    step_core.move_geometry(i, pos, env.period_m, env.geometry.disp_m, env.geometry.dist2_m2)
    reward = env.rewarder.step_mover(env, i, u)
    env.observer.after_reward_mover(env, i, u, count)
    done = env.t >= env.max_cycles
    obs = env.build(env.mover_rows)
    env.observer.fill_mover(env, obs, i)
    x, y = pos[i]
    vals = (u, env.u0[i], env.prr[i], env.prr0[i], env.jain[i], x - old_x, y - old_y, clipped)
    info = dict(zip(INFO_KEYS, (float(v) for v in vals), strict=True))
    if done:
        env.finish()
    return obs[0], reward, done, info
