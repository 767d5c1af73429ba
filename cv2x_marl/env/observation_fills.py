"""The compiled entries of the later observation versions: the measured per-neighbour block and own entries of
version 3 (:func:`fill_measured`, :func:`fill_own_v3`) and the driving entries of ``drive_observation``
(:func:`fill_drive`). The layout and the v0 block are :mod:`cv2x_marl.env.observation`'s; the observation models
(:mod:`cv2x_marl.env.observation_models`) and the batched v3 step call these.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.env.observation import FEATURES_V3, OWN_V3, ObservationLayout
from cv2x_marl.sim.ground_truth import PairGeometry

FloatArray = NDArray[np.float64]


@njit(cache=True)
def measured_kernel(
    out: NDArray[np.float32],
    disp_m: FloatArray,
    dist2_m2: FloatArray,
    co_table: NDArray[np.int64],
    rsrp: FloatArray,
    age: FloatArray,
    slot_frac: FloatArray,
    sub_frac: FloatArray,
    rows: NDArray[np.int64],
    k: int,
    offset: int,
    scale_m: float,
    obs_clip: float,
) -> None:
    n = dist2_m2.shape[0]
    inv = 1.0 / scale_m
    g_max = co_table.shape[1]
    dist_i = np.empty(n)
    for r in range(rows.shape[0]):
        i = rows[r]
        for j in range(n):
            dist_i[j] = math.sqrt(dist2_m2[i, j])
        dist_i[i] = np.inf
        order = np.argsort(dist_i, kind="mergesort")  # the v0 block's order (same sort, same keys)
        for kk in range(k):
            j = order[kk]
            base = offset + kk * FEATURES_V3
            out[r, base + 0] = rsrp[j, i]
            out[r, base + 1] = age[j, i]
            out[r, base + 2] = slot_frac[j]
            out[r, base + 3] = sub_frac[j]
            first, second = -1, -1
            d_first, d_second = np.inf, np.inf
            for g in range(g_max):
                c = co_table[i, g]
                if c < 0:
                    break
                if c == j:
                    continue
                d = dist2_m2[j, c]
                if d < d_first:
                    second, d_second = first, d_first
                    first, d_first = c, d
                elif d < d_second:
                    second, d_second = c, d
            if first >= 0:
                out[r, base + 4] = disp_m[0, i, first] * inv
                out[r, base + 5] = disp_m[1, i, first] * inv
                out[r, base + 6] = 1.0
            if second >= 0:
                out[r, base + 7] = disp_m[0, i, second] * inv
                out[r, base + 8] = disp_m[1, i, second] * inv
                out[r, base + 9] = 1.0
            for f in range(FEATURES_V3):
                out[r, base + f] = min(max(out[r, base + f], -obs_clip), obs_clip)


def fill_measured(
    obs: NDArray[np.float32],
    layout: ObservationLayout,
    geometry: PairGeometry,
    co_table: NDArray[np.int64],
    rsrp_scaled: FloatArray,
    age_scaled: FloatArray,
    slot_frac: FloatArray,
    sub_frac: FloatArray,
    rows: NDArray[np.int64],
) -> None:
    """Write the measured per-neighbour entries of observation version 3 into ``obs`` [A, size] in place.

    Args:
        obs: [A, layout.size] observations of agents ``rows`` (the v0 block already built).
        geometry: the pair geometry the v0 block used (same neighbour order).
        co_table: :func:`co_channel_table` of the resources (the v0 block's).
        rsrp_scaled: [N(tx), N(rx)] scaled RSRP reports (:func:`cv2x_marl.env.measurement.scaled_rsrp`).
        age_scaled: [N(tx), N(rx)] report ages / window.
        slot_frac: [N] subframe / RRI of each vehicle.
        sub_frac: [N] subchannel / n_subchannels of each vehicle.
        rows: [A] the agents of ``obs``'s rows.
    """
    if layout.version != 3:
        raise ValueError("measured entries are part of observation version 3")
    measured_kernel(
        obs, geometry.disp_m, geometry.dist2_m2, co_table,
        np.ascontiguousarray(rsrp_scaled, dtype=np.float64), np.ascontiguousarray(age_scaled, dtype=np.float64),
        np.ascontiguousarray(slot_frac, dtype=np.float64), np.ascontiguousarray(sub_frac, dtype=np.float64),
        np.ascontiguousarray(rows, dtype=np.int64), layout.n_neighbours, layout.v0_size, layout.scale_m,
        layout.obs_clip,
    )  # fmt: skip


def fill_own_v3(
    obs: NDArray[np.float32],
    layout: ObservationLayout,
    u_now: FloatArray,
    u_prev: FloatArray,
    drift_m: FloatArray,
    time_left: float,
    reach_m: float,
) -> None:
    """Write the own entries of observation version 3 (:data:`OWN_V3_NAMES`) in place.

    Args:
        obs: [A, layout.size] observations.
        u_now: [A] utility per target receiver now; u_prev: [A] the step before.
        drift_m: [A, 2] displacement from the start (m).
        time_left: steps left / horizon.
        reach_m: moving steps left x ``max_step_m`` (m).
    """
    own_v3_kernel(
        obs, layout.own_v1_offset, layout.obs_clip, layout.scale_m, np.ascontiguousarray(u_now, dtype=np.float64),
        np.ascontiguousarray(u_prev, dtype=np.float64), np.ascontiguousarray(drift_m, dtype=np.float64),
        float(time_left), float(reach_m),
    )  # fmt: skip


@njit(cache=True)
def own_v3_kernel(
    obs: NDArray[np.float32],
    offset: int,
    obs_clip: float,
    scale_m: float,
    u_now: FloatArray,
    u_prev: FloatArray,
    drift_m: FloatArray,
    time_left: float,
    reach_m: float,
) -> None:
    """:func:`fill_own_v3`'s entries, computed in float64, clipped, stored as float32."""
    for r in range(obs.shape[0]):
        vals = (
            u_now[r],
            10.0 * (u_now[r] - u_prev[r]),
            drift_m[r, 0] / scale_m,
            drift_m[r, 1] / scale_m,
            time_left,
            reach_m / scale_m,
        )
        for f in range(OWN_V3):
            obs[r, offset + f] = min(max(vals[f], -obs_clip), obs_clip)


def fill_drive(
    obs: NDArray[np.float32],
    layout: ObservationLayout,
    speed_share: FloatArray,
    heading: FloatArray,
    lane: NDArray[np.int64],
    lanes_per_direction: int,
    time_left: float,
) -> None:
    """The driving entries (:data:`OWN_DRIVE_NAMES`) of every vehicle into ``obs`` [N, layout.size].

    Args:
        speed_share: [N] speed / the speed limit.
        heading: [N, 2] unit vectors of the direction of travel.
        lane: [N] lane indices (0: next to the centre line).
        lanes_per_direction: lanes of each direction of a road.
        time_left: steps left / the horizon in force.
    """
    top = lanes_per_direction - 1
    block = np.stack(
        (
            speed_share,
            heading[:, 0],
            heading[:, 1],
            lane / max(top, 1),
            (lane > 0).astype(np.float64),
            (lane < top).astype(np.float64),
            np.full(lane.shape[0], time_left),
        ),
        axis=1,
    )
    obs[:, layout.drive_offset :] = np.clip(block, -layout.obs_clip, layout.obs_clip)
