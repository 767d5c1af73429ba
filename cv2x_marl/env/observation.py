"""Observations: the one-hop information GBMU uses, as a fixed-size float32 vector per agent.

Layout for agent i (``K = n_neighbours`` other vehicles, nearest first; ``F = 7`` features each,
then ``OWN = 5`` own features), every length in units of ``scale_m``:

    [k * F + 0, k * F + 1]  position of the k-th nearest vehicle j relative to i (x, y)
    [k * F + 2]             1 if j is a target receiver of i's packets (not in i's subframe)
    [k * F + 3]             NSV_j: vehicles on i's resource within th_I of j (excluding i)
    [k * F + 4]             1 if j has a main interferer (NSV_j > 0)
    [k * F + 5, k * F + 6]  position of j's main interferer relative to i (0, 0 when none)
    [K * F + 0, K * F + 1]  own position / region size (x, y)
    [K * F + 2, K * F + 3]  own drift from the episode's start position (x, y)
    [K * F + 4]             elapsed share of the episode, t / max_cycles

Values are clipped to ``[-obs_clip, obs_clip]`` (the Box bounds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
FEATURES = 7
OWN = 5


@dataclass(frozen=True)
class ObservationLayout:
    """Sizes and scales of the observation vector (see the module docstring)."""

    n_neighbours: int
    scale_m: float
    region_m: float
    interferer_range_m: float
    obs_clip: float = 10.0

    @property
    def size(self) -> int:
        return self.n_neighbours * FEATURES + OWN

    def neighbours(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., K, F] view of the per-neighbour block."""
        return obs[..., : self.n_neighbours * FEATURES].reshape(*obs.shape[:-1], self.n_neighbours, FEATURES)


def co_channel_table(resource: NDArray[np.int64]) -> NDArray[np.int64]:
    """[N, G] the other vehicles on each vehicle's resource, padded with -1 (G = largest group - 1)."""
    n = resource.shape[0]
    co = (resource[:, None] == resource[None, :]) & ~np.eye(n, dtype=bool)
    g = max(int(co.sum(axis=1).max()), 1)
    table = np.full((n, g), -1, dtype=np.int64)
    rows, cols = np.nonzero(co)
    rank = np.arange(rows.size) - np.searchsorted(rows, rows)
    table[rows, rank] = cols
    return table


def build_observations(
    layout: ObservationLayout,
    positions_m: FloatArray,
    resource: NDArray[np.int64],
    target: NDArray[np.bool_],
    drift_m: FloatArray,
    t_fraction: float,
    co_table: NDArray[np.int64] | None = None,
) -> NDArray[np.float32]:
    """[N, layout.size] observations of every vehicle.

    Args:
        positions_m: [N, 2] current positions.
        resource: [N] resource index of each vehicle (slot * n_subchannels + subchannel).
        target: [N(tx), N(rx)] target-receiver mask.
        drift_m: [N, 2] displacement from the start of the episode.
        t_fraction: elapsed share of the episode.
        co_table: :func:`co_channel_table` of ``resource`` (computed when None).
    """
    n = positions_m.shape[0]
    k = layout.n_neighbours
    if co_table is None:
        co_table = co_channel_table(resource)
    diff = positions_m[None, :, :] - positions_m[:, None, :]  # [i, j, 2]: j relative to i
    dist = np.sqrt(diff[..., 0] ** 2 + diff[..., 1] ** 2)
    np.fill_diagonal(dist, np.inf)
    order = np.argsort(dist, axis=1, kind="stable")[:, :k]  # [N, K] nearest first
    rows = np.arange(n)[:, None]
    # distance from every receiver j to each co-channel vehicle c of agent i: [i, j, G]
    cc = np.maximum(co_table, 0)
    d_jc = dist[:, cc].transpose(1, 0, 2)
    ok = (co_table[:, None, :] >= 0) & (d_jc <= layout.interferer_range_m)  # dist[j, j] = inf drops c = j
    d_jc = np.where(ok, d_jc, np.inf)
    nsv_all = ok.sum(axis=2)  # [i, j]
    main_all = cc[rows, np.argmin(d_jc, axis=2)]  # [i, j]
    nsv = nsv_all[rows, order]
    main = main_all[rows, order]
    has = nsv > 0
    out = np.empty((n, layout.size), dtype=np.float32)
    block = out[:, : k * FEATURES].reshape(n, k, FEATURES)
    inv = 1.0 / layout.scale_m
    block[..., 0:2] = diff[rows, order] * inv
    block[..., 2] = target[rows, order]
    block[..., 3] = nsv
    block[..., 4] = has
    block[..., 5:7] = diff[rows, main] * (inv * has[..., None])
    own = out[:, k * FEATURES :]
    own[:, 0:2] = positions_m / layout.region_m
    own[:, 2:4] = drift_m * inv
    own[:, 4] = t_fraction
    np.clip(out, -layout.obs_clip, layout.obs_clip, out=out)
    return out
