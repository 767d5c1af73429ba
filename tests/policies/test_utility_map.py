"""The learned utility map: features against hand-computed values, the search against closed forms, the
file format, the policy's steps, and the torch twin the trainer fits."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from cv2x_marl.env.observation import ObservationLayout
from cv2x_marl.policies.utility_map import (
    LINK_FEATURES,
    STATIC_FEATURES,
    UtilityMap,
    UtilityMapPolicy,
    candidate_features,
    check_map_env,
    is_map_file,
    static_features,
)

LAYOUT = ObservationLayout(n_neighbours=20, scale_m=100.0, region_m=450.0, interferer_range_m=200.0, version=3)


def scene_obs(reach_m: float = 500.0, drift_m: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """One v3 observation: neighbour 0 a target at (100, 0) m with a main interferer at (120, 50) m, a
    co-channel vehicle at (100, -30) m and an RSRP of 0.5; neighbour 1 not a target at (-200, 0) m, never heard."""
    obs = np.zeros((1, LAYOUT.size))
    obs[0, 0:7] = [1.0, 0.0, 1.0, 1.0, 1.0, 1.2, 0.5]
    obs[0, 7:9] = [-2.0, 0.0]
    meas = LAYOUT.v0_size
    obs[0, meas + 0] = 0.5
    obs[0, meas + 4 : meas + 7] = [1.0, -0.3, 1.0]
    obs[0, LAYOUT.size - 6] = -6.9  # the own utility observed where the mover stands: ln(p_min), the worst
    obs[0, LAYOUT.size - 4 : LAYOUT.size - 2] = np.asarray(drift_m) / 100.0
    obs[0, LAYOUT.size - 1] = reach_m / 100.0
    return obs


def distance_map(slope: float = 10.0) -> UtilityMap:
    """A one-layer map whose link utility only falls with the link's length: z = slope * log_distance."""
    w = np.zeros((len(LINK_FEATURES), 1))
    w[LINK_FEATURES.index("log_distance"), 0] = slope
    return UtilityMap([[(w, np.zeros(1))]])


def test_static_features_hand_computed() -> None:
    static, rel_m, target = static_features(scene_obs(), LAYOUT)
    assert static.shape == (1, 20, STATIC_FEATURES)
    third = 1.0 / 3.0
    want = [1.0, math.log10(math.hypot(20.0, 50.0)) * third, 1.0, math.log10(30.0) * third, 0.0, 0.0, 0.25, 1.0, 0.5]
    want += [2.0 * third]
    # corridor offsets min(|dx|, |dy|) against j: the interferer (20, 50) m -> 20 m; co1 (0, -30) m and the mover
    # (-100, 0) m -> 0 m (clipped to 1 m: log 0); no co2
    want += [math.log10(20.0) * third, 0.0, 0.0, 0.0]
    np.testing.assert_allclose(static[0, 0], want, rtol=1e-12)
    far = [0, 0, 0, 0, 0, 0, 0, 0, 0, math.log10(200.0) * third, 0, 0, 0, 0]
    np.testing.assert_allclose(static[0, 1], far, rtol=1e-12)
    np.testing.assert_array_equal(rel_m[0, :2], [[100.0, 0.0], [-200.0, 0.0]])
    np.testing.assert_array_equal(target[0, :2], [1.0, 0.0])


def test_candidate_features_hand_computed() -> None:
    rel_m = np.array([[[100.0, 0.0]]])
    dyn = candidate_features(rel_m, np.array([[[30.0, 40.0], [100.0, 0.0]]]))
    third = 1.0 / 3.0
    want = [math.log10(math.hypot(70.0, 40.0)) * third, math.log10(40.0) * third, math.log10(70.0) * third, 0.5]
    np.testing.assert_allclose(dyn[0, 0, 0], want, rtol=1e-12)
    np.testing.assert_allclose(dyn[0, 1, 0], [0.0, 0.0, 0.0, 1.0], atol=1e-15)  # at the receiver: clipped to 1 m


def test_utility_is_the_target_mean_of_the_link_utilities() -> None:
    umap = distance_map(slope=1.0)
    obs = scene_obs()
    u = umap.utility(obs, LAYOUT, np.array([[[0.0, 0.0], [30.0, 40.0]]]))
    for m, d in enumerate((100.0, math.hypot(70.0, 40.0))):  # only neighbour 0 is a target
        z = math.log10(d) / 3.0
        assert u[0, m] == pytest.approx(math.log(1e-3) / (1.0 + math.exp(-z)), rel=1e-12)


def test_plan_finds_the_receiver_of_a_distance_only_map() -> None:
    """A map that only rewards short links is best at the one target receiver: the search's coarse grid
    (50 m pitch over +-500 m) has (100, 0), and nothing scores higher."""
    plan = distance_map().plan(scene_obs(), LAYOUT, np.array([500.0]))
    np.testing.assert_allclose(plan, [[100.0, 0.0]], atol=1e-9)


def test_staying_scores_the_observed_utility() -> None:
    """The map's best point at the receiver scores ln(p_min) * sigmoid(0) = -3.45; an observed -1 where the
    mover stands beats it, an observed -6 does not."""
    obs = scene_obs()
    best = distance_map().utility(obs, LAYOUT, np.array([[[100.0, 0.0]]]))[0, 0]
    assert best == pytest.approx(math.log(1e-3) / 2.0, rel=1e-12)
    obs[0, LAYOUT.size - 6] = -1.0
    np.testing.assert_array_equal(distance_map().plan(obs, LAYOUT, np.array([500.0])), [[0.0, 0.0]])
    # a kept target where the mover stands is judged the same way: kept at -1, left at -6
    umap = distance_map()
    umap.switch_margin = 0.5
    np.testing.assert_array_equal(umap.plan(obs, LAYOUT, np.array([500.0]), np.zeros((1, 2))), [[0.0, 0.0]])
    obs[0, LAYOUT.size - 6] = -6.0
    np.testing.assert_allclose(umap.plan(obs, LAYOUT, np.array([500.0]), np.zeros((1, 2))), [[100.0, 0.0]])


def test_plan_refines_between_grid_points_and_stays_in_reach() -> None:
    obs = scene_obs()
    obs[0, 0:2] = [1.3, -0.2]  # the target at (130, -20) m, between coarse points
    plan = distance_map().plan(obs, LAYOUT, np.array([500.0]))[0]
    assert np.hypot(*(plan - [130.0, -20.0])) <= 50.0 / 3.0 * math.sqrt(2) / 2 + 1e-9
    far = distance_map().plan(obs, LAYOUT, np.array([40.0]))[0]  # out of reach: the square's corner towards it
    np.testing.assert_allclose(far, [40.0, -20.0], atol=1e-9)


def test_save_load_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    umap = UtilityMap(
        [
            [(rng.normal(size=(18, 8)), rng.normal(size=8)), (rng.normal(size=(8, 1)), rng.normal(size=1))],
            [(rng.normal(size=(18, 4)), rng.normal(size=4)), (rng.normal(size=(4, 1)), rng.normal(size=1))],
        ],
        p_min=0.01,
        grid=11,
        refine=5,
        top=2,
        replan_every=4,
        switch_margin=0.25,
        info={"seed": 3},
    )
    umap.save(tmp_path / "model.npz")
    assert is_map_file(tmp_path / "model.npz")
    back = UtilityMap.load(tmp_path / "model.npz")
    got = (back.p_min, back.grid, back.refine, back.top, back.replan_every, back.switch_margin, back.info)
    assert got == (0.01, 11, 5, 2, 4, 0.25, {"seed": 3})
    offsets = rng.uniform(-300, 300, size=(1, 9, 2))
    obs = scene_obs()
    np.testing.assert_array_equal(back.utility(obs, LAYOUT, offsets), umap.utility(obs, LAYOUT, offsets))
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    assert not is_map_file(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match=r"cannot load the utility map .*bad\.npz"):
        UtilityMap.load(tmp_path / "bad.npz")


def test_bad_maps_refused() -> None:
    with pytest.raises(ValueError, match="read 18 features"):
        UtilityMap([[(np.zeros((3, 1)), np.zeros(1))]])
    with pytest.raises(ValueError, match="grid must be an integer >= 1, got 0"):
        UtilityMap([[(np.zeros((18, 1)), np.zeros(1))]], grid=0)
    with pytest.raises(ValueError, match="switch_margin must be a number >= 0, got -1"):
        UtilityMap([[(np.zeros((18, 1)), np.zeros(1))]], switch_margin=-1.0)


def fake_env(**kw: object) -> SimpleNamespace:
    base = dict(layout=LAYOUT, max_step_m=5.0, mode="snapshot", max_drift_m=None, roi=False, period_m=[np.inf, np.inf])
    return SimpleNamespace(**{**base, **kw})


def test_policy_drives_to_its_plan_and_keeps_it_between_searches() -> None:
    obs = scene_obs(reach_m=20.0)
    obs[0, 0:2] = [0.12, -0.04]  # the target receiver at (12, -4) m: a point of the 2 m grid over +-20 m
    policy = UtilityMapPolicy(distance_map(), fake_env())
    policy.reset()
    a0 = policy.act({"v0": obs[0].astype(np.float32)})["v0"]
    np.testing.assert_allclose(a0, [1.0, -0.8], rtol=1e-6)
    moved = obs.copy()
    moved[0, LAYOUT.size - 4 : LAYOUT.size - 2] = [0.05, -0.04]  # drifted (5, -4) m; the plan is kept
    a1 = policy.act({"v0": moved[0].astype(np.float32)})["v0"]
    np.testing.assert_allclose(a1, [1.0, 0.0], atol=1e-6)  # (12 - 5, -4 + 4) / 5, clipped


def test_policy_actions_do_not_depend_on_the_other_agents() -> None:
    rng = np.random.default_rng(1)
    umap = UtilityMap([[(rng.normal(size=(18, 16)), rng.normal(size=16)), (rng.normal(size=(16, 1)), np.zeros(1))]])
    obs = {f"v{n}": rng.uniform(-2, 2, size=LAYOUT.size).astype(np.float32) for n in range(3)}
    together = UtilityMapPolicy(umap, fake_env())
    together.reset()
    both = together.act(obs)
    for a, o in obs.items():
        alone = UtilityMapPolicy(umap, fake_env())
        alone.reset()
        np.testing.assert_array_equal(alone.act({a: o})[a], both[a])


@pytest.mark.parametrize(
    ("kw", "needs"),
    [
        ({"mode": "traffic"}, "snapshot mode"),
        ({"max_drift_m": 50.0}, "no max_drift_m"),
        ({"period_m": [500.0, np.inf]}, "do not wrap"),
        ({"layout": ObservationLayout(20, 100.0, 450.0, 200.0, version=2)}, "observation version 3"),
    ],
)
def test_envs_the_map_cannot_plan_in_are_refused(kw: dict[str, object], needs: str) -> None:
    with pytest.raises(ValueError, match=needs):
        check_map_env(fake_env(**kw))


def test_torch_twin_equals_the_numpy_map() -> None:
    torch = pytest.importorskip("torch")
    from cv2x_marl.rl.utility_map import _Network, pair_features

    nets = [_Network((16, 8), 1e-3, torch.Generator().manual_seed(s)) for s in (0, 1)]
    umap = UtilityMap([net.weights() for net in nets])
    obs = scene_obs()
    obs[0, 14:21] = [0.5, 0.5, 1.0, 2.0, 1.0, 0.4, 0.9]  # a second target
    offsets = np.array([[[30.0, 40.0]]])
    want = umap.utility(obs, LAYOUT, offsets)[0, 0]
    static, rel_m, target = static_features(obs, LAYOUT)
    t = lambda a: torch.from_numpy(np.asarray(a, dtype=np.float32))  # noqa: E731
    dyn = pair_features(t(rel_m), t(offsets[:, 0]))
    np.testing.assert_allclose(
        dyn.numpy(), candidate_features(rel_m, offsets)[:, 0].astype(np.float32), rtol=1e-6, atol=1e-7
    )
    got = sum(float(net.utility(t(static), dyn, t(target))[0].detach()) for net in nets) / 2  # the members' mean
    assert got == pytest.approx(want, rel=1e-5)  # float32 against float64
