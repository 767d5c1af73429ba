"""cv2x/Mobility-v2 and cv2x/SingleMover-v2: the sensing estimate against an independent numpy
construction, the plan it gives, checkers, the sensing planner, the one-mover path of the SB3 adapter."""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import parallel_api_test

import cv2x_marl  # noqa: F401 - registers the ids
import cv2x_marl.env as env_module
from cv2x_marl.env import MobilityEnv
from cv2x_marl.env.defaults import V2_DEFAULTS
from cv2x_marl.env.observation import OWN_V1_NAMES
from cv2x_marl.env.planning import ReachableSet, best_reachable, reachable_set, sensing_plan
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.sim.ground_truth import SnapshotLinks

FAST = {"overrides": ["sim.warmup_subframes=200"]}


def test_v2_ids_and_checkers() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    par = pettingzoo.make("parallel", "cv2x/Mobility-v2", max_cycles=10, **FAST)
    assert par.metadata["name"] == "cv2x_mobility_v2" and par.layout.version == 2
    parallel_api_test(env_module.parallel_env_v2(max_cycles=8, **FAST), num_cycles=16)
    g = gymnasium.make("cv2x/SingleMover-v2", max_cycles=20, **FAST)
    # the v1 layout: only the meaning of the plan entries changes
    assert g.observation_space.shape == (20 * 8 + 5 + len(OWN_V1_NAMES),)
    gymnasium.utils.env_checker.check_env(g.unwrapped, skip_render_check=True)
    sb3_check_env(g.unwrapped, warn=True)
    with pytest.raises(ValueError, match=r"observation.*0 \| 1 \| 2 \| 3"):
        MobilityEnv(observation=4)
    with pytest.raises(ValueError, match=r"invalid env argument observation=2.*truth_los is geometry"):
        MobilityEnv(observation=2, truth_los="geometry")


@pytest.mark.kernel_equality
def test_sensed_row_is_the_truth_without_the_shadowing_between_others() -> None:
    """The estimate equals the numpy reference evaluation of a snapshot whose shadowing between
    pairs that do not include the mover is 0 dB, and differs from the truth only through it."""
    env = MobilityEnv(**FAST)
    env.reset(seed=2)
    snap, links = env.snapshot, env.links
    rng = np.random.default_rng(1)
    differs = 0
    for i in (0, 9):
        own = np.zeros((env.n, env.n), dtype=bool)
        own[i, :] = own[:, i] = True
        blind = dataclasses.replace(snap, shadowing_db=np.where(own, snap.shadowing_db, 0.0))
        reference = SnapshotLinks(env.config, blind, env.truth_los, compiled=False)
        cands = env.positions_m[i] + rng.uniform(-150, 150, size=(6, 2))
        got = links.sensed_row(i, env.positions_m).success(cands)
        truth = links.mover_row(i, env.positions_m).success(cands)
        for c, g, t in zip(cands, got, truth, strict=True):
            pos = env.positions_m.copy()
            pos[i] = c
            np.testing.assert_allclose(g, reference.evaluate(pos)[0][i], rtol=1e-9, atol=1e-12)
            differs += int(not np.allclose(g, t))
    assert differs > 0  # the unknown shadowing matters somewhere, or the test would prove nothing
    # without shadowing there is nothing the mover cannot measure: the estimate is the truth
    flat = SnapshotLinks(env.config, dataclasses.replace(snap, shadowing_db=np.zeros_like(snap.shadowing_db)))
    c = env.positions_m[3] + rng.uniform(-100, 100, size=(5, 2))
    assert np.array_equal(flat.sensed_row(3, env.positions_m).success(c), flat.mover_row(3, env.positions_m).success(c))


def test_v2_plan_is_the_sensing_estimate_optimum() -> None:
    env = MobilityEnv(movers=[0], max_cycles=12, **V2_DEFAULTS, **FAST)
    obs, _ = env.reset(seed=5)
    plan = env.plan_m[0]
    np.testing.assert_array_equal(plan, sensing_plan(env, [0])[0])
    own = env.layout.own_v1(obs["vehicle_0"])
    np.testing.assert_allclose(own[6:8], (plan - env.positions_m[0]) / env.layout.scale_m, atol=1e-6)
    # no point of a 2 m brute-force grid over the reachable square is better under the estimate
    row = env.links.sensed_row(0, env.positions_m)
    reach = reachable_set(env, 0)
    axis = np.arange(-60.0, 60.0 + 1e-9, 2.0)
    grid = env.start_m[0] + np.stack(np.meshgrid(axis, axis, indexing="ij"), -1).reshape(-1, 2)
    u_plan = row.utility(plan[None], env.p_min)[0]
    assert reach.contains(plan[None])[0]
    assert u_plan >= row.utility(grid, env.p_min).max() - 1e-9
    # the v1 plan is the model's: a different position on this episode
    v1 = MobilityEnv(movers=[0], max_cycles=12, observation=1, **FAST)
    v1.reset(seed=5)
    assert not np.allclose(v1.plan_m[0], plan)


def test_sensing_planner_reaches_its_plan_and_never_beats_the_optimum() -> None:
    kw = {"max_cycles": 30, **FAST}
    res = evaluate("cv2x/SingleMover-v2", "sensing", 6, 3, env_kwargs=kw, progress=False, vs_optimum=True)
    assert res["beats_optimum"] == 0
    assert 0.0 < res["mean_utility_gain"] <= res["optimum_utility_gain"] + 1e-12


def test_reachable_set_on_a_torus_searches_one_period() -> None:
    r = ReachableSet(np.array([100.0, 20.0]), 500.0, period_m=np.array([400.0, np.inf]))
    lo, hi = r.bounds()
    np.testing.assert_allclose(lo, [-100.0, -480.0])
    np.testing.assert_allclose(hi, [300.0, 520.0])
    # on the wrapped highway the links repeat with the period, so the window loses nothing
    env = MobilityEnv(movers=[0], max_cycles=210, preset="highway", **FAST)  # 1050 m > half the 2 km ring
    env.reset(seed=1)
    reach = reachable_set(env, 0)
    assert reach.period_m is not None and reach.period_m[0] == 2000.0
    row = env.links.mover_row(0, env.positions_m)
    x = env.start_m[0] + np.random.default_rng(0).uniform(-900, 900, size=(8, 2))
    shifted = x + np.array([2000.0, 0.0])
    np.testing.assert_allclose(row.utility(shifted, env.p_min), row.utility(x, env.p_min), rtol=1e-9)
    lo, hi = reach.bounds()
    assert hi[0] - lo[0] == pytest.approx(2000.0)
    _, u_window = best_reachable(row, reach, env.p_min, grid_m=25.0)
    _, u_square = best_reachable(row, dataclasses.replace(reach, period_m=None), env.p_min, grid_m=25.0)
    assert u_window == pytest.approx(u_square, rel=1e-4)


def test_plan_residual_zero_action_follows_the_plan_and_corrections_add() -> None:
    from cv2x_marl.policies.planner import PlannerPolicy

    kw = {"movers": [0], "max_cycles": 25, **V2_DEFAULTS, **FAST}
    res = MobilityEnv(action_mode="plan_residual", **kw)
    ref = MobilityEnv(**kw)
    planner = PlannerPolicy(ref, None, estimator="sensing")
    obs_ref, _ = ref.reset(seed=8)
    res.reset(seed=8)
    zero = np.zeros(2, np.float32)
    while ref.agents:
        acts = planner.act({"vehicle_0": obs_ref["vehicle_0"]})
        obs_ref, *_ = ref.step({a: acts.get(a, zero) for a in ref.agents})
        res.step({a: zero for a in res.agents})
        np.testing.assert_allclose(res.positions_m, ref.positions_m, atol=1e-9)
    np.testing.assert_allclose(res.positions_m[0], res.plan_m[0], atol=1e-9)  # reached in 25 x 5 m
    # a correction is added to the plan step, then clipped: (+1, -1) on top of the step
    res.reset(seed=8)
    base = np.clip((res.plan_m[0] - res.positions_m[0]) / res.max_step_m, -1, 1)
    start = res.positions_m[0].copy()
    correction = np.array([1.0, -1.0])
    res.step_mover(correction.astype(np.float32))
    np.testing.assert_allclose(res.positions_m[0] - start, np.clip(base + correction, -1, 1) * 5.0, atol=1e-9)
    with pytest.raises(ValueError, match="action_mode"):
        MobilityEnv(action_mode="plan_residual", **FAST)  # observation 0 has no plan


def test_replanning_uses_where_everyone_is_and_keeps_the_fast_path_exact() -> None:
    from cv2x_marl.env.single import SingleMoverEnv

    env = MobilityEnv(max_cycles=12, replan_every=5, **V2_DEFAULTS, **FAST)
    env.reset(seed=6)
    rng = np.random.default_rng(2)
    for t in range(1, 11):
        before = env.plan_m.copy()
        env.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents})
        if t % 5:
            np.testing.assert_array_equal(env.plan_m, before)
        else:  # steps 5 and 10: a new plan from the current positions, with the steps left
            reach = reachable_set(env, 3)
            np.testing.assert_array_equal(reach.start_m, env.positions_m[3])
            assert reach.radius_m == (12 - t) * env.max_step_m
            np.testing.assert_array_equal(env.plan_m, sensing_plan(env, np.arange(env.n)))
    # one mover: the fast path replans exactly as the full step does
    fast = SingleMoverEnv("cv2x/SingleMover-v2", max_cycles=12, replan_every=4, **FAST)
    full = MobilityEnv(movers=[0], max_cycles=12, replan_every=4, **V2_DEFAULTS, **FAST)
    of, _ = fast.reset(seed=3)
    og, _ = full.reset(seed=3)
    assert np.array_equal(of, og["vehicle_0"])
    zero = np.zeros(2, np.float32)
    for _ in range(12):
        act = rng.uniform(-1, 1, 2).astype(np.float32)
        o1, r1, *_ = fast.step(act)
        o2, r2, *_ = full.step({a: act if a == "vehicle_0" else zero for a in full.agents})
        assert r1 == r2["vehicle_0"] and np.array_equal(o1, o2["vehicle_0"])
    for bad in ({"replan_every": 0, **V2_DEFAULTS}, {"replan_every": 5, "observation": 1}):
        with pytest.raises(ValueError, match="replan_every"):
            MobilityEnv(**bad, **FAST)


def test_reachable_set_mid_episode_keeps_the_drift_disc_at_the_start() -> None:
    r = ReachableSet(
        np.array([20.0, 0.0]), 10.0, max_drift_m=25.0, drift_center_m=np.array([0.0, 0.0])
    )  # 10 m of steps left from x = 20, never farther than 25 m from the start at 0
    assert r.contains(np.array([[30.0, 0.0], [24.0, 0.0], [20.0, 10.0]])).tolist() == [False, True, True]
    lo, hi = r.bounds()
    np.testing.assert_allclose(lo, [10.0, -10.0])
    np.testing.assert_allclose(hi, [25.0, 10.0])
