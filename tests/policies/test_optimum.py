"""The optimum mover: equal to a brute-force search, never beaten, reached exactly; the planner."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.env import MobilityEnv
from cv2x_marl.env.planning import ReachableSet, best_reachable, reachable_set
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.policies.optimum import OptimumPolicy

FAST = {"overrides": ["sim.warmup_subframes=200"]}


def test_mover_row_equals_the_full_evaluation_bit_for_bit() -> None:
    env = MobilityEnv(**FAST)
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    for i in (0, 7, 20):
        row = env.links.mover_row(i, env.positions_m)
        cands = env.positions_m[i] + rng.uniform(-300, 300, size=(25, 2))
        got = row.success(cands)
        for c, g in zip(cands, got, strict=True):
            pos = env.positions_m.copy()
            pos[i] = c
            assert np.array_equal(g, env.links.evaluate(pos)[0][i])


def test_best_reachable_equals_brute_force_on_a_small_scene() -> None:
    env = MobilityEnv(movers=[0], max_cycles=6, max_step_m=5.0, **FAST)  # 30 m square around the start
    env.reset(seed=3)
    row = env.links.mover_row(0, env.positions_m)
    reach = reachable_set(env, 0)
    pos, u = best_reachable(row, reach, env.p_min)
    assert reach.contains(pos[None])[0]
    # brute force on a 0.25 m grid over the whole square (4x finer than the search's 2.5 m / 10)
    axis = np.arange(-30.0, 30.0 + 1e-9, 0.25)
    grid = env.start_m[0] + np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    brute = row.utility(grid, env.p_min).max()
    assert u >= brute - 1e-9
    assert u == pytest.approx(row.utility(pos[None], env.p_min)[0])


def test_reachable_set_bounds() -> None:
    r = ReachableSet(np.array([10.0, 10.0]), 50.0, max_drift_m=30.0, box_m=np.array([100.0, 100.0]))
    assert r.contains(np.array([[10.0, 40.0], [35.0, 10.0]])).tolist() == [True, True]
    assert r.contains(np.array([[40.5, 10.0], [-1.0, 10.0], [32.0, 32.0]])).tolist() == [False, False, False]
    lo, hi = r.bounds()
    np.testing.assert_allclose(lo, [0.0, 0.0])
    np.testing.assert_allclose(hi, [40.0, 40.0])


def test_optimum_policy_reaches_its_target_and_is_never_beaten() -> None:
    kw = {"max_cycles": 30, **FAST}
    res = {p: evaluate("cv2x/SingleMover-v1", p, 6, 9, env_kwargs=kw, progress=False) for p in ("gbmu", "oracle")}
    opt = evaluate("cv2x/SingleMover-v1", "optimum", 6, 9, env_kwargs=kw, progress=False, vs_optimum=True)
    # the policy ends where the search said: its gain is the optimum's gain
    assert opt["mean_utility_gain"] == pytest.approx(opt["optimum_utility_gain"], rel=1e-6)
    assert opt["effectiveness"] == 1.0
    for r in res.values():
        assert r["mean_utility_gain"] <= opt["mean_utility_gain"] + 1e-9
    g = evaluate("cv2x/SingleMover-v1", "gbmu", 6, 9, env_kwargs=kw, progress=False, vs_optimum=True)
    assert g["beats_optimum"] == 0
    assert g["share_of_optimum"] == pytest.approx(g["mean_utility_gain"] / opt["mean_utility_gain"], rel=1e-6)


def test_best_response_for_several_movers() -> None:
    env = make_parallel_env("cv2x/Mobility-v1", max_cycles=4, **FAST)
    env.reset(seed=0)
    pol = OptimumPolicy(env, rounds=1, grid_m=10.0)
    acts = pol.act({a: None for a in env.agents})  # type: ignore[misc]
    targets = pol.targets_m
    assert targets is not None
    assert np.all(np.abs(targets - env.start_m).max(axis=1) <= 4 * env.max_step_m + 1e-9)
    while env.agents:
        env.step(acts)
        acts = pol.act({a: None for a in env.agents})  # type: ignore[misc]
    np.testing.assert_allclose(env.positions_m, targets, atol=1e-5)
    # in one round the last mover responds to everyone's final place: nothing in its reach is better
    last = env.n - 1
    row = env.links.mover_row(last, env.positions_m)
    _, u_best = best_reachable(row, ReachableSet(env.start_m[last], 4 * env.max_step_m), env.p_min, 10.0)
    u_end = row.utility(env.positions_m[last][None], env.p_min)[0]
    assert u_end == pytest.approx(u_best, rel=1e-6)
    assert u_end >= row.utility(env.start_m[last][None], env.p_min)[0]


def test_planner_is_not_privileged_and_moves_to_the_model_optimum() -> None:
    kw = {"max_cycles": 30, **FAST}
    r = evaluate("cv2x/SingleMover-v1", "planner", 4, 3, env_kwargs=kw, progress=False, vs_optimum=True)
    assert r["beats_optimum"] == 0
    assert -1.0 < r["mean_utility_gain"] <= r["optimum_utility_gain"] + 1e-9


def test_fused_utility_kernel_is_bit_identical() -> None:
    from cv2x_marl.sim import kernels

    env = MobilityEnv(**FAST)
    env.reset(seed=4)
    rng = np.random.default_rng(2)
    for i in (0, 11):
        for row in (env.links.mover_row(i, env.positions_m), env.links.sensed_row(i, env.positions_m)):
            cands = env.positions_m[i] + rng.uniform(-900, 900, size=(300, 2))  # near and beyond range
            want = kernels.row_utility(row.success(cands), row.target_row, env.p_min)
            assert np.array_equal(row.utility(cands, env.p_min), want)
