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
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.sim.evaluate import PairGeometry, pair_geometry, row_index_table

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
    return row_index_table((resource[:, None] == resource[None, :]) & ~np.eye(resource.shape[0], dtype=bool))


@njit(cache=True)
def _observation_kernel(
    disp_m: FloatArray,
    dist2_m2: FloatArray,
    co_table: NDArray[np.int64],
    target: NDArray[np.bool_],
    positions_m: FloatArray,
    drift_m: FloatArray,
    t_fraction: float,
    k: int,
    scale_m: float,
    region_m: float,
    interferer_range_m: float,
    obs_clip: float,
) -> NDArray[np.float32]:
    n = positions_m.shape[0]
    size = k * FEATURES + OWN
    out = np.zeros((n, size), dtype=np.float32)
    dist = np.sqrt(dist2_m2)
    for i in range(n):
        dist[i, i] = np.inf  # a vehicle is not its own neighbour
    inv = 1.0 / scale_m
    g_max = co_table.shape[1]
    for i in range(n):
        order = np.argsort(dist[i], kind="mergesort")  # stable: ties keep the index order
        for kk in range(k):
            j = order[kk]
            base = kk * FEATURES
            out[i, base + 0] = disp_m[0, i, j] * inv
            out[i, base + 1] = disp_m[1, i, j] * inv
            out[i, base + 2] = 1.0 if target[i, j] else 0.0
            # NSV_j and the main interferer: i's co-channel vehicles c != j, seen from j
            nsv = 0
            best = np.inf
            main = -1
            for g in range(g_max):
                c = co_table[i, g]
                if c < 0:
                    break
                if c == j:
                    continue
                d = dist[j, c]
                if d <= interferer_range_m:
                    nsv += 1
                if d < best:
                    best = d
                    main = c
            out[i, base + 3] = nsv
            if nsv > 0:
                out[i, base + 4] = 1.0
                out[i, base + 5] = disp_m[0, i, main] * inv
                out[i, base + 6] = disp_m[1, i, main] * inv
        own = k * FEATURES
        out[i, own + 0] = positions_m[i, 0] / region_m
        out[i, own + 1] = positions_m[i, 1] / region_m
        out[i, own + 2] = drift_m[i, 0] * inv
        out[i, own + 3] = drift_m[i, 1] * inv
        out[i, own + 4] = t_fraction
        for f in range(size):
            out[i, f] = min(max(out[i, f], -obs_clip), obs_clip)
    return out


def build_observations(
    layout: ObservationLayout,
    positions_m: FloatArray,
    resource: NDArray[np.int64],
    target: NDArray[np.bool_],
    drift_m: FloatArray,
    t_fraction: float,
    co_table: NDArray[np.int64] | None = None,
    geometry: PairGeometry | None = None,
) -> NDArray[np.float32]:
    """[N, layout.size] observations of every vehicle (layout in the module docstring).

    One compiled pass (numba) over the agents: a stable sort of each agent's row by distance, then
    the K nearest vehicles' features; ``tests/env/test_observation.py`` checks it against an
    independent numpy construction and a hand-built scene.

    Args:
        positions_m: [N, 2] current positions (m).
        resource: [N] resource index of each vehicle (slot * n_subchannels + subchannel).
        target: [N(tx), N(rx)] target-receiver mask.
        drift_m: [N, 2] displacement from the start of the episode (m).
        t_fraction: elapsed share of the episode.
        co_table: :func:`co_channel_table` of ``resource`` (computed when None).
        geometry: :func:`cv2x_marl.sim.evaluate.pair_geometry` of ``positions_m`` (computed when
            None; pass the road-folded one on a wrapping road).
    """
    n = positions_m.shape[0]
    if not 1 <= layout.n_neighbours <= n - 1:
        raise ValueError(f"layout.n_neighbours must be in 1 .. {n - 1} for {n} vehicles, got {layout.n_neighbours}")
    if co_table is None:
        co_table = co_channel_table(resource)
    if geometry is None:
        geometry = pair_geometry(positions_m)
    if geometry.dist2_m2.shape != (n, n) or target.shape != (n, n) or co_table.shape[0] != n:
        raise ValueError(f"geometry, target and co_table must describe the same {n} vehicles as positions_m")
    return _observation_kernel(
        geometry.disp_m,
        geometry.dist2_m2,
        co_table,
        np.ascontiguousarray(target),
        np.ascontiguousarray(positions_m, dtype=np.float64),
        np.ascontiguousarray(drift_m, dtype=np.float64),
        float(t_fraction),
        layout.n_neighbours,
        layout.scale_m,
        layout.region_m,
        layout.interferer_range_m,
        layout.obs_clip,
    )
