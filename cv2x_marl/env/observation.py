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

Version 1 (``cv2x/Mobility-v1``, ``cv2x/SingleMover-v1``) appends, after these ``7 K + 5``
values (so the v0 part and GBMU's decoding stay as they are):

    [7K + 5 + k]            model-predicted success of the link to neighbour k (eq. 15 two-distance
                            model at d_ik, l_k, NSV_k: what GBMU's steering model predicts)
    [8K + 5 + k]            (``privileged`` only) the true expected success P_ik of the link model
    then ``OWN_V1 = 9`` own values (see :data:`OWN_V1_NAMES`): the mover's measured utility and
    its change, the best utility so far and where it was, the model's best reachable position
    and how far the mover can still go.

Version 2 (``cv2x/Mobility-v2``, ``cv2x/SingleMover-v2``) has the layout and entries of version 1;
only the plan (``plan_dx``, ``plan_dy``) changes: it is the best reachable position under the
mover's own sensing estimate of its links (measured RSRP of its links, the others' positions and
resources; :meth:`cv2x_marl.sim.ground_truth.SnapshotLinks.sensed_row`) instead of the two-distance model.

Version 3 (``cv2x/Mobility-v3``, ``cv2x/SingleMover-v3``, ``cv2x/Cooperative-v0``) is plan-free: no plan,
no model prediction, no true P. After the v0 block (unchanged, so GBMU's decoding stays as it is) come
``F3 = 10`` measured values per neighbour k (the same neighbour, nearest first, as the v0 block's k):

    [7K + 5 + 10k + 0]      RSRP of the link from j measured at i (:mod:`cv2x_marl.env.measurement`:
                            averaged over the sensing window, fast fading and report error included),
                            scaled ``(rsrp_dbm + 100) / 20``; 0 when never heard
    [7K + 5 + 10k + 1]      age of that measurement: periods since j's last decoded packet / window
    [7K + 5 + 10k + 2]      j's subframe (from its SCI) / RRI (ms)
    [7K + 5 + 10k + 3]      j's subchannel / n_subchannels
    [7K + 5 + 10k + 4, 5]   position relative to i of the co-channel vehicle (on i's resource, as the
                            v0 NSV; not i, not j) nearest to j (0, 0 when none)
    [7K + 5 + 10k + 6]      1 if that vehicle exists
    [7K + 5 + 10k + 7, 8]   the same for the second nearest
    [7K + 5 + 10k + 9]      1 if that vehicle exists

then ``OWN_V3 = 6`` own values (:data:`OWN_V3_NAMES`): the utility per target receiver (as v1's
``utility``), its change over the last step x 10, the drift from the start (x, y, in ``scale_m``), the
time left (steps left / the horizon in force: ``max_cycles`` or a shorter Gymnasium ``TimeLimit``) and
the reach left (moving steps left x ``max_step_m`` / ``scale_m``). Every entry is refreshed every step.

With ``drive`` (``cv2x/Traffic-v0``: the env option ``drive_observation``) ``OWN_DRIVE = 7`` driving
entries (:data:`OWN_DRIVE_NAMES`) close the vector: the own speed / the speed limit, the heading (x, y: a
unit vector along the own lane), the lane index / max(lanes per direction - 1, 1), 1 if a lane exists to
the left / to the right, and the time left (steps left / the horizon in force).

Version 4 (``cv2x/Traffic-v1``: traffic mode with the driving entries; :mod:`cv2x_marl.env.traffic_measurement`)
is what a Mode 4 vehicle has after its sensing window on the road: after the v0 block (unchanged) come
``F4 = 8`` values per neighbour k (the v0 block's k-th):

    [7K + 5 + 8k + 0]       RSRP of the link from j measured at i over the packets i actually decoded in
                            the sensing window (the simulator's outcomes; fading and report error of
                            :mod:`cv2x_marl.env.measurement`), scaled ``(rsrp_dbm + 100) / 20``; 0: never heard
    [7K + 5 + 8k + 1]       age of that measurement: periods since j's last decoded packet / window
    [7K + 5 + 8k + 2]       1 if i has heard j (a report exists)
    [7K + 5 + 8k + 3, 4]    j's subframe / RRI and subchannel / n_subchannels from its last decoded SCI
                            (0 when never heard; stale with the age)
    [7K + 5 + 8k + 5]       1 if that SCI announced a reselection (no reservation: ``sps.reservation_signalling
                            =standard``; always 0 with ``always``)
    [7K + 5 + 8k + 6]       1 if that subframe is i's next one (half duplex: neither hears the other)
    [7K + 5 + 8k + 7]       1 if that resource is i's next one (co-channel: the packets collide)

then ``OWN_V4 = 6`` own values (:data:`OWN_V4_NAMES`): the own next resource (subframe / RRI, subchannel /
n_subchannels), the reselection counter / its largest value, 1 if the own next SCI announces a reselection,
the utility per target receiver and its change over the last step x 10; the driving entries close the vector.

Values are clipped to ``[-obs_clip, obs_clip]`` (the Box bounds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from cv2x_marl.sim.ground_truth import PairGeometry, pair_geometry, row_index_table

FloatArray = NDArray[np.float64]
FEATURES = 7
OWN = 5
#: the own entries appended by observation version 1, in order (lengths in units of ``scale_m``;
#: utilities per target receiver, i.e. the mean of ``ln max(P, p_min)`` over the targets)
OWN_V1_NAMES = (
    "utility",  # own measured utility now
    "utility_change_x10",  # 10 x (now - previous step)
    "utility_gain",  # now - start of the episode
    "best_minus_now",  # best utility seen this episode - now (>= 0)
    "best_dx",  # position where the best was seen, relative to now (x, y)
    "best_dy",
    "plan_dx",  # the planned best reachable position, relative to now (x, y): v1 model, v2 sensing
    "plan_dy",
    "reach",  # steps left x max_step_m: how far the mover can still go
)
OWN_V1 = len(OWN_V1_NAMES)
#: measured values per neighbour of observation version 3 (module docstring)
FEATURES_V3 = 10
#: the own entries of observation version 3, in order
OWN_V3_NAMES = ("utility", "utility_change_x10", "drift_x", "drift_y", "time_left", "reach")
OWN_V3 = len(OWN_V3_NAMES)
#: measured values per neighbour of observation version 4 (module docstring)
FEATURES_V4_NAMES = ("rsrp", "age", "heard", "slot", "subchannel", "release", "same_subframe", "same_resource")
FEATURES_V4 = len(FEATURES_V4_NAMES)
#: the own entries of observation version 4, in order (the driving entries follow)
OWN_V4_NAMES = ("slot", "subchannel", "counter", "release", "utility", "utility_change_x10")
OWN_V4 = len(OWN_V4_NAMES)
#: entries of a vehicle's candidate list (the action space's size, ``Discrete(N_CANDIDATES)``): the 3GPP rule's
#: list at a selection window of 100 candidates (``ceil(0.2 M)``, TS 36.213 14.1.1.6 step 8)
N_CANDIDATES = 20
#: what observation version 5 carries per candidate, in order
CANDIDATE_NAMES = (
    "valid",  # 1: an entry of the list (a survivor of the exclusion)
    "standard_list",  # 1: among the entries the standard draws from (step 8's list)
    "rssi",  # S-RSSI averaged over the sensing window, dB above the noise / 20
    "sci_rsrp",  # RSRP of the strongest SCI reserving it, (dBm + 100) / 20; 0: none decoded
    "reserved",  # 1: an SCI reserving it was decoded
    "users",  # neighbours whose last decoded SCI reserves it / 4
    "user_dx",  # the nearest of them, relative position from its CAM / scale_m (0, 0: none)
    "user_dy",
    "user_rsrp",  # its measured RSRP, scaled as above (0: none)
    "subframe_users",  # neighbours whose last decoded SCI is in the candidate's subframe / 4 (half duplex)
    "delay",  # subframes from the packet's generation to the candidate / the selection window's end
    "subchannel",  # sub-channel / n_subchannels
)
FEATURES_CANDIDATE = len(CANDIDATE_NAMES)
#: the own entries of version 5 after version 4's (:data:`~cv2x_marl.env.observation.OWN_V4_NAMES`)
OWN_V5_EXTRA = ("decides", "list_size")
#: observation version 5's own block: version 4's own entries, :data:`OWN_V5_EXTRA`, the candidate block
OWN_V5 = OWN_V4 + len(OWN_V5_EXTRA) + N_CANDIDATES * FEATURES_CANDIDATE


#: the blocks each observation version adds after the v0 block: version -> (values per neighbour, own entries);
#: :func:`cv2x_marl.env.observation_models.register_observation` adds a version's row (``privileged`` adds
#: one value per neighbour to versions 1 and 2)
VERSION_BLOCKS: dict[int, tuple[int, int]] = {0: (0, 0), 1: (1, OWN_V1), 2: (1, OWN_V1), 3: (FEATURES_V3, OWN_V3),
                                              4: (FEATURES_V4, OWN_V4), 5: (FEATURES_V4, OWN_V5)}  # fmt: skip
#: the built-in observation versions (:data:`VERSION_BLOCKS` holds every registered one)
VERSIONS = (0, 1, 2, 3, 4, 5)
#: the driving entries closing the observation with ``drive`` (module docstring)
OWN_DRIVE_NAMES = ("speed", "heading_x", "heading_y", "lane", "lane_left", "lane_right", "time_left")
OWN_DRIVE = len(OWN_DRIVE_NAMES)


@dataclass(frozen=True)
class ObservationLayout:
    """Sizes and scales of the observation vector (see the module docstring)."""

    n_neighbours: int
    scale_m: float
    region_m: float
    interferer_range_m: float
    obs_clip: float = 10.0
    version: int = 0
    privileged: bool = False
    drive: bool = False

    @property
    def per_neighbour_extra(self) -> int:
        """Values per neighbour after the v0 block: model P (v1), true P (v1, privileged); the
        :data:`FEATURES_V3` measured values (v3)."""
        return VERSION_BLOCKS[self.version][0] + int(self.privileged and self.version in (1, 2))

    @property
    def model_extra(self) -> int:
        """Per-neighbour model / truth values the compiled kernel writes (versions 1 and 2)."""
        return self.per_neighbour_extra if self.version in (1, 2) else 0

    @property
    def v0_size(self) -> int:
        return self.n_neighbours * FEATURES + OWN

    @property
    def own_v1_offset(self) -> int:
        """Index of the first :data:`OWN_V1_NAMES` entry (version 1)."""
        return self.v0_size + self.n_neighbours * self.per_neighbour_extra

    @property
    def size(self) -> int:
        return self.own_v1_offset + VERSION_BLOCKS[self.version][1] + (OWN_DRIVE if self.drive else 0)

    @property
    def drive_offset(self) -> int:
        """Index of the first :data:`OWN_DRIVE_NAMES` entry (``drive``)."""
        if not self.drive:
            raise ValueError("the driving entries are part of layouts with drive=True")
        return self.size - OWN_DRIVE

    def own_drive(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., OWN_DRIVE] the driving entries (:data:`OWN_DRIVE_NAMES`)."""
        k = self.drive_offset
        return obs[..., k : k + OWN_DRIVE]

    def measured(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., K, F] view of the measured per-neighbour block (version 3: ``F = FEATURES_V3``; version 4:
        ``FEATURES_V4``)."""
        if self.version not in (3, 4):
            raise ValueError("measured neighbour entries are part of observation versions 3 and 4")
        k0, k, f = self.v0_size, self.n_neighbours, self.per_neighbour_extra
        return obs[..., k0 : k0 + k * f].reshape(*obs.shape[:-1], k, f)

    def own_v4(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., OWN_V4] the own entries of version 4 (:data:`OWN_V4_NAMES`)."""
        if self.version != 4:
            raise ValueError("OWN_V4 entries are part of observation version 4")
        return obs[..., self.own_v1_offset : self.own_v1_offset + OWN_V4]

    def own_v3(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., OWN_V3] the own entries of version 3 (:data:`OWN_V3_NAMES`)."""
        if self.version != 3:
            raise ValueError("OWN_V3 entries are part of observation version 3")
        return obs[..., self.own_v1_offset : self.own_v1_offset + OWN_V3]

    def model_success(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., K] the model-predicted success of each neighbour link (version 1)."""
        if self.version not in (1, 2):
            raise ValueError("model-predicted success is part of observation version 1")
        k0 = self.v0_size
        return obs[..., k0 : k0 + self.n_neighbours]

    def true_success(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., K] the true success of each neighbour link (version 1, ``privileged``)."""
        if not self.privileged:
            raise ValueError("true link success is observed only with privileged=True")
        k0 = self.v0_size + self.n_neighbours
        return obs[..., k0 : k0 + self.n_neighbours]

    def own_v1(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., OWN_V1] the own entries of version 1 (:data:`OWN_V1_NAMES`)."""
        if self.version not in (1, 2):
            raise ValueError("OWN_V1 entries are part of observation versions 1 and 2")
        return obs[..., self.own_v1_offset : self.own_v1_offset + OWN_V1]

    def neighbours(self, obs: NDArray[np.floating]) -> NDArray[np.floating]:
        """[..., K, F] view of the per-neighbour block."""
        return obs[..., : self.n_neighbours * FEATURES].reshape(*obs.shape[:-1], self.n_neighbours, FEATURES)


def co_channel_table(resource: NDArray[np.int64]) -> NDArray[np.int64]:
    """[N, G] the other vehicles on each vehicle's resource, padded with -1 (G = largest group - 1)."""
    return row_index_table((resource[:, None] == resource[None, :]) & ~np.eye(resource.shape[0], dtype=bool))


@njit(cache=True)
def observation_kernel(
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
    rows: NDArray[np.int64],
    size: int,
    extra: int,
    alpha: FloatArray,
    beta: FloatArray,
    gamma: FloatArray,
    logistic: bool,
    model_p_min: float,
    p_true: FloatArray,
) -> NDArray[np.float32]:
    n = positions_m.shape[0]
    out = np.zeros((rows.shape[0], size), dtype=np.float32)
    inv = 1.0 / scale_m
    g_max = co_table.shape[1]
    cap = alpha.shape[0] - 1
    dist_i = np.empty(n)
    for r in range(rows.shape[0]):
        i = rows[r]
        for j in range(n):
            dist_i[j] = math.sqrt(dist2_m2[i, j])
        dist_i[i] = np.inf  # a vehicle is not its own neighbour
        order = np.argsort(dist_i, kind="mergesort")  # stable: ties keep the index order
        for kk in range(k):
            j = order[kk]
            base = kk * FEATURES
            out[r, base + 0] = disp_m[0, i, j] * inv
            out[r, base + 1] = disp_m[1, i, j] * inv
            out[r, base + 2] = 1.0 if target[i, j] else 0.0
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
                d = math.sqrt(dist2_m2[j, c])
                if d <= interferer_range_m:
                    nsv += 1
                if d < best:
                    best = d
                    main = c
            out[r, base + 3] = nsv
            if nsv > 0:
                out[r, base + 4] = 1.0
                out[r, base + 5] = disp_m[0, i, main] * inv
                out[r, base + 6] = disp_m[1, i, main] * inv
            if extra > 0:  # version 1: the two-distance model's P (eq. 15), as GBMU reads it
                l_m = max(best, 1e-3) if nsv > 0 else interferer_range_m
                row = min(nsv, cap)
                eta = alpha[row] * math.log10(max(dist_i[j], 1.0)) + beta[row] * math.log10(l_m) + gamma[row]
                pm = 1.0 / (1.0 + math.exp(-eta)) if logistic else eta
                out[r, k * FEATURES + OWN + kk] = min(max(pm, model_p_min), 1.0)
                if extra > 1:
                    out[r, k * FEATURES + OWN + k + kk] = p_true[i, j]
        own = k * FEATURES
        out[r, own + 0] = positions_m[i, 0] / region_m
        out[r, own + 1] = positions_m[i, 1] / region_m
        out[r, own + 2] = drift_m[i, 0] * inv
        out[r, own + 3] = drift_m[i, 1] * inv
        out[r, own + 4] = t_fraction
        for f in range(size):
            out[r, f] = min(max(out[r, f], -obs_clip), obs_clip)
    return out


_NO_MODEL = (np.zeros(1), np.zeros(1), np.zeros(1))


def build_observations(
    layout: ObservationLayout,
    positions_m: FloatArray,
    resource: NDArray[np.int64],
    target: NDArray[np.bool_],
    drift_m: FloatArray,
    t_fraction: float,
    co_table: NDArray[np.int64] | None = None,
    geometry: PairGeometry | None = None,
    rows: NDArray[np.int64] | None = None,
    model: Any = None,
    p_true: FloatArray | None = None,
) -> NDArray[np.float32]:
    """[N, layout.size] observations of every vehicle (or of ``rows``; layout in the module docstring).

    Version 1 layouts get their per-neighbour entries here (the model's P, the true P when
    privileged); the own version-1 entries (:data:`OWN_V1_NAMES`) are state the env keeps and are
    left 0 for it to fill.

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
        geometry: :func:`cv2x_marl.sim.ground_truth.pair_geometry` of ``positions_m`` (computed when
            None; pass the road-folded one on a wrapping road).
        rows: [A] the agents whose observations to build (default: all, in index order).
        model: the :class:`~cv2x_marl.regression.model.TwoDistanceModel` (version 1).
        p_true: [N(tx), N(rx)] true link success (version 1, privileged).
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
    if rows is None:
        rows = np.arange(n, dtype=np.int64)
    extra = layout.model_extra
    if extra and model is None:
        raise ValueError("observation version 1 needs the two-distance model (model=...)")
    if extra > 1 and (p_true is None or p_true.shape != (n, n)):
        raise ValueError(f"a privileged layout needs p_true of shape ({n}, {n})")
    alpha, beta, gamma = _NO_MODEL if model is None else (model.alpha, model.beta, model.gamma)
    return observation_kernel(
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
        np.ascontiguousarray(rows, dtype=np.int64),
        layout.size,
        extra,
        np.ascontiguousarray(alpha, dtype=np.float64),
        np.ascontiguousarray(beta, dtype=np.float64),
        np.ascontiguousarray(gamma, dtype=np.float64),
        model is not None and model.kind == "logistic",
        1e-3 if model is None else float(model.p_min),
        np.zeros((1, 1)) if p_true is None else np.ascontiguousarray(p_true, dtype=np.float64),
    )


@dataclass(frozen=True)
class GbmuInputs:
    """What the mover is allowed to know, for B movers with up to R receivers each.

    Attributes:
        rx_m: [B, R, 2] receiver positions.
        l_m: [B, R] distance from each receiver to its main interferer (th_I when NSV = 0).
        nsv: [B, R] NSV of each receiver.
        mask: [B, R] which receivers are targets.
    """

    rx_m: FloatArray
    l_m: FloatArray
    nsv: NDArray[np.int64]
    mask: NDArray[np.bool_]

    def __post_init__(self) -> None:
        b, r = self.mask.shape
        if self.rx_m.shape != (b, r, 2) or self.l_m.shape != (b, r) or self.nsv.shape != (b, r):
            raise ValueError("rx_m must be [B, R, 2] and l_m, nsv, mask [B, R]")
        if np.any(self.l_m[self.mask] <= 0):
            raise ValueError("main-interference distances must be > 0 m")


def decode_observations(obs: np.ndarray, layout: ObservationLayout) -> GbmuInputs:
    """GBMU's inputs from stacked observations [B, size]: the mover sits at the origin."""
    nb = layout.neighbours(np.asarray(obs, dtype=np.float64))  # [B, K, F]
    rel = nb[..., 0:2] * layout.scale_m
    int_rel = nb[..., 5:7] * layout.scale_m
    has = nb[..., 4] > 0.5
    l_m = np.where(has, np.hypot(*(rel - int_rel).transpose(2, 0, 1)), layout.interferer_range_m)
    return GbmuInputs(
        rel.astype(np.float64),
        np.maximum(l_m, 1e-3).astype(np.float64),
        np.rint(nb[..., 3]).astype(np.int64),
        nb[..., 2] > 0.5,
    )
