"""The observation kernel against a hand-built scene and an independent numpy construction; the
link-summary kernel against cv2x_marl.utility."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.env.observation import FEATURES, ObservationLayout, build_observations, co_channel_table
from cv2x_marl.sim.ground_truth import pair_geometry
from cv2x_marl.sim.kernels import link_summaries
from cv2x_marl.utility import jain_fairness, per_node_prr, utility_log


def reference_observations(
    layout: ObservationLayout,
    pos: np.ndarray,
    resource: np.ndarray,
    target: np.ndarray,
    drift: np.ndarray,
    t_fraction: float,
) -> np.ndarray:
    """Vectorised numpy construction (gathers over an [N, N] distance table)."""
    n, k = pos.shape[0], layout.n_neighbours
    co = co_channel_table(resource)
    diff = pos[None, :, :] - pos[:, None, :]  # [i, j, 2]: j relative to i
    dist = np.hypot(diff[..., 0], diff[..., 1])
    np.fill_diagonal(dist, np.inf)
    dist = np.concatenate([dist, np.full((n, 1), np.inf)], axis=1)  # index -1 (padding) reads inf
    order = np.argsort(dist[:, :n], axis=1, kind="stable")[:, :k]
    rows = np.arange(n)[:, None]
    d_jc = dist[:, co]  # [j, i, G]
    nsv_ji = (d_jc <= layout.interferer_range_m).sum(axis=2)
    main_ji = co[rows.T, d_jc.argmin(axis=2)]
    nsv = nsv_ji[order, rows]
    main = main_ji[order, rows]
    has = nsv > 0
    block = np.zeros((n, k, FEATURES))
    block[..., 0:2] = diff[rows, order] / layout.scale_m
    block[..., 2] = target[rows, order]
    block[..., 3] = nsv
    block[..., 4] = has
    block[..., 5:7] = diff[rows, main] / layout.scale_m * has[..., None]
    own = np.concatenate([pos / layout.region_m, drift / layout.scale_m, np.full((n, 1), t_fraction)], axis=1)
    out = np.concatenate([block.reshape(n, -1), own], axis=1)
    return np.clip(out, -layout.obs_clip, layout.obs_clip).astype(np.float32)


def test_hand_built_scene() -> None:
    # v0 at the origin; v1 10 m east; v2 50 m north; v3 100 m east. v0, v2, v3 share a resource
    # (hence a subframe); v1 is alone. Interferer range 60 m, lengths in units of 10 m.
    pos = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 50.0], [100.0, 0.0]])
    resource = np.array([5, 7, 5, 5])
    slot = np.array([0, 1, 0, 0])
    target = slot[:, None] != slot[None, :]
    drift = np.array([[2.0, -1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    layout = ObservationLayout(n_neighbours=3, scale_m=10.0, region_m=200.0, interferer_range_m=60.0)
    obs = build_observations(layout, pos, resource, target, drift, 0.25)
    nb = layout.neighbours(obs)
    # agent 0: neighbours v1 (10 m), v2 (50 m), v3 (100 m)
    # v1 is a target; of v0's co-channel users {v2, v3}, v2 is 51 m from v1 (within 60 m), v3 90 m
    np.testing.assert_allclose(nb[0, 0], [1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 5.0])
    # v2 and v3 share v0's subframe (not targets); seen from v2, v3 is 112 m away: NSV 0
    np.testing.assert_allclose(nb[0, 1], [0.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(nb[0, 2], [10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(obs[0, 3 * FEATURES :], [0.0, 0.0, 0.2, -0.1, 0.25])
    # agent 1 has no co-channel user: NSV 0 everywhere; every other vehicle is a target
    np.testing.assert_allclose(nb[1, :, :5], [[-1, 0, 1, 0, 0], [-1, 5, 1, 0, 0], [9, 0, 1, 0, 0]], atol=1e-6)
    np.testing.assert_allclose(obs[1, 3 * FEATURES :], [0.05, 0.0, 0.0, 0.0, 0.25])
    # agent 3: nearest is v1 (90 m; then v0 100 m, v2 112 m); of v3's co-channel users {v0, v2}, seen
    # from v1, v0 is 10 m and v2 51 m away: NSV 2, main interferer v0 (the nearer), at (-100, 0) m from v3
    np.testing.assert_allclose(nb[3, 0], [-9.0, 0.0, 1.0, 2.0, 1.0, -10.0, 0.0])
    assert obs.dtype == np.float32 and obs.shape == (4, layout.size)


@pytest.mark.kernel_equality
@pytest.mark.parametrize("k", [20, 6])
def test_kernel_matches_the_numpy_construction(k: int) -> None:
    rng = np.random.default_rng(3)
    n = 21
    layout = ObservationLayout(n_neighbours=k, scale_m=100.0, region_m=433.0, interferer_range_m=150.0, obs_clip=3.0)
    for _ in range(5):
        pos = rng.uniform(0.0, 433.0, size=(n, 2))
        resource = rng.integers(0, 6, size=n)  # large co-channel groups
        target = rng.random((n, n)) < 0.7
        drift = rng.normal(0.0, 200.0, size=(n, 2))  # some beyond the clip
        got = build_observations(layout, pos, resource, target, drift, 0.4, geometry=pair_geometry(pos))
        want = reference_observations(layout, pos, resource, target, drift, 0.4)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
        assert np.abs(got).max() == pytest.approx(3.0)


@pytest.mark.kernel_equality
def test_link_summaries_match_the_utility_module() -> None:
    rng = np.random.default_rng(0)
    p = rng.random((9, 9)) * (rng.random((9, 9)) < 0.8)  # some exact zeros
    target = rng.random((9, 9)) < 0.6
    target[4] = False  # no targets: PRR and Jain 0
    p[5] = 0.0  # all zero: Jain 0
    u, prr, jain = link_summaries(p, target, 1e-3)
    np.testing.assert_allclose(u, utility_log(p, target, 1e-3), rtol=1e-12)
    np.testing.assert_allclose(prr, np.nan_to_num(per_node_prr(p, target)), rtol=1e-12)
    np.testing.assert_allclose(jain, np.nan_to_num(jain_fairness(p, target)), rtol=1e-12)
    assert u[4] == 0.0 and prr[4] == 0.0 and jain[5] == 0.0 and u[5] == pytest.approx(np.log(1e-3) * target[5].sum())


def test_layout_and_inputs_are_checked() -> None:
    pos = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 50.0], [100.0, 0.0]])
    args = (pos, np.array([5, 7, 5, 5]), np.ones((4, 4), bool), np.zeros((4, 2)), 0.0)
    with pytest.raises(ValueError, match=r"n_neighbours must be in 1 \.\. 3 for 4 vehicles, got 4"):
        build_observations(ObservationLayout(4, 10.0, 200.0, 60.0), *args)
    with pytest.raises(ValueError, match="same 4 vehicles"):
        build_observations(ObservationLayout(3, 10.0, 200.0, 60.0), *args, geometry=pair_geometry(pos[:3]))
