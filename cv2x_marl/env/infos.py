"""What the env reports besides observations and rewards: every agent's info dict and the global state.

Every info value is a float; the keys are :data:`INFO_KEYS`, with ``episode_metrics`` also
:data:`EPISODE_INFO_KEYS` and, with ``drive_observation`` too, :data:`DRIVE_INFO_KEYS`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.env import step as step_core

if TYPE_CHECKING:
    from cv2x_marl.env.episode import EpisodeEnv

#: keys of every agent's info dict (all floats; ``clipped`` is 1.0 when the action left the box)
INFO_KEYS = ("utility", "utility_start", "prr", "prr_start", "jain", "offset_x_m", "offset_y_m", "clipped")
#: the infos' keys added by ``episode_metrics`` (the means over the episode's steps so far), and with
#: ``drive_observation`` (the vehicle's speed and lane now)
EPISODE_INFO_KEYS, DRIVE_INFO_KEYS = ("utility_mean", "prr_mean", "jain_mean"), ("speed_mps", "lane")


def infos_of(env: EpisodeEnv, applied: NDArray[np.float64], clipped: NDArray[np.bool_]) -> dict[str, dict[str, float]]:
    """Numeric infos of every agent (all agents are live whenever infos are built): applied offsets [N, 2] (m),
    ``clipped`` [N]; the utilities, PRR and Jain's index now and at the start; the episode's means."""
    cols = [env.utility, env.u0, env.prr, env.prr0, env.jain, applied[:, 0], applied[:, 1], clipped]
    if env.options.episode_metrics:  # the means over the steps so far (at reset: the start's)
        steps = max(env.t, 1)
        sums = (env.u_sum, env.prr_sum, env.jain_sum)
        cols += [x / steps for x in sums] if env.t else [env.utility, env.prr, env.jain]
        if env.layout.drive:
            speed, _, lane = step_core.drive_state(env.sim, env.config.road.lanes_per_direction)
            cols += [speed, lane]
    table = np.stack(cols, axis=1).tolist()
    keys = env.info_keys
    return {a: dict(zip(keys, row, strict=True)) for a, row in zip(env.possible_agents, table, strict=True)}


def global_state(env: EpisodeEnv) -> NDArray[np.float32]:
    """Global state for centralised critics: positions / region, drifts / scale, slot / RRI and subchannel /
    n_subchannels of every vehicle [6N], then the observation model's pair entries (version 3: every
    vehicle's RSRP reports, scaled as in the observation, and their ages / window, [N(tx) x N(rx)] each)."""
    if not hasattr(env, "positions_m"):
        raise RuntimeError("state() called before reset(): call reset() first")
    slot, sub = np.divmod(env.resource, env.config.sps.n_subchannels)
    parts = [
        (env.positions_m / env.layout.region_m).ravel(),
        ((env.positions_m - env.start_m) / env.layout.scale_m).ravel(),
        slot / env.config.traffic.rri_ms,
        sub / env.config.sps.n_subchannels,
        *env.observer.state_parts(env),
    ]
    return np.clip(np.concatenate(parts), -env.layout.obs_clip, env.layout.obs_clip).astype(np.float32)
