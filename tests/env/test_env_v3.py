"""cv2x/SingleMover-v3, cv2x/Mobility-v3 and cv2x/Cooperative-v0: ids, checkers, seeding, layout, rewards."""

from __future__ import annotations

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import api_test, parallel_api_test
from pettingzoo.test.seed_test import parallel_seed_test

import cv2x_marl  # noqa: F401 - registers the ids
import cv2x_marl.env as env_module
from cv2x_marl.env import MobilityEnv
from cv2x_marl.env.observation import FEATURES, FEATURES_V3, OWN, OWN_V3_NAMES, decode_observations
from cv2x_marl.env.registry import ENV_IDS, env_version, make_parallel_env
from cv2x_marl.sim.ground_truth import SnapshotLinks

FAST = {"overrides": ["sim.warmup_subframes=200"]}


def test_ids_registered() -> None:
    for i in ("cv2x/SingleMover-v3", "cv2x/Mobility-v3", "cv2x/Cooperative-v0"):
        assert i in ENV_IDS
    assert env_version("cv2x/Cooperative-v0") == "cooperative-v0"
    coop = make_parallel_env("cv2x/Cooperative-v0", max_cycles=5, **FAST)
    assert coop.reward_kind == "team" and coop.layout.version == 3 and coop.mover_mask.all()
    assert make_parallel_env("cv2x/SingleMover-v3", max_cycles=5, **FAST).fast_mover == 0  # tests/env/test_v3_fast.py


def test_checkers_and_seeding() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    g = gymnasium.make("cv2x/SingleMover-v3", max_cycles=12, **FAST)
    assert g.observation_space.shape == (20 * (FEATURES + FEATURES_V3) + OWN + len(OWN_V3_NAMES),)
    gymnasium.utils.env_checker.check_env(g.unwrapped, skip_render_check=True)
    sb3_check_env(g.unwrapped, warn=True)
    runs = []
    for _ in range(2):  # same seed, same episode
        e = gymnasium.make("cv2x/SingleMover-v3", max_cycles=12, **FAST)
        o, _ = e.reset(seed=4)
        out = [o]
        for a in np.random.default_rng(1).uniform(-1, 1, (5, 2)).astype(np.float32):
            o, r, *_ = e.step(a)
            out += [o, np.array([r])]
        runs.append(np.concatenate([x.ravel() for x in out]))
    np.testing.assert_array_equal(runs[0], runs[1])
    for name in ("cv2x/Mobility-v3", "cv2x/Cooperative-v0"):
        par = pettingzoo.make("parallel", name, max_cycles=6, **FAST)  # pettingzoo >= 1.27 (pyproject's floor)
        assert par.layout.version == 3
    parallel_api_test(env_module.parallel_env_v3(max_cycles=6, **FAST), num_cycles=12)
    parallel_api_test(env_module.parallel_env_cooperative(max_cycles=6, **FAST), num_cycles=12)
    api_test(env_module.env_cooperative(max_cycles=4, **FAST), num_cycles=8)
    parallel_seed_test(lambda: env_module.parallel_env_v3(max_cycles=6, **FAST), num_cycles=8)
    parallel_seed_test(lambda: env_module.parallel_env_cooperative(max_cycles=6, **FAST), num_cycles=8)


def test_layout_plan_free_and_entries_against_numpy() -> None:
    par = env_module.parallel_env_v3(max_cycles=30, **FAST)
    obs, _ = par.reset(seed=2)
    lay = par.layout
    with pytest.raises(ValueError, match="versions 1 and 2"):
        lay.own_v1(obs["vehicle_0"])
    with pytest.raises(ValueError, match="version 1"):
        lay.model_success(obs["vehicle_0"])
    ref = MobilityEnv(max_cycles=30, **FAST)  # v0: the same scene, the same v0 block at reset
    obs0, _ = ref.reset(seed=2)
    for a in par.agents:
        np.testing.assert_array_equal(obs[a][: lay.v0_size], obs0[a])
    decode_observations(np.stack([obs[a][: lay.v0_size] for a in par.agents]), lay)  # GBMU's decoding
    rng = np.random.default_rng(3)
    for _ in range(4):
        obs, *_ = par.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in par.agents})
    pos, res = par.positions_m, par.resource
    n_sub, rri = par.config.sps.n_subchannels, par.config.traffic.rri_ms
    for i in (0, 5, 13):
        o = obs[f"vehicle_{i}"]
        d = np.hypot(*(pos - pos[i]).T)
        d[i] = np.inf
        order = np.argsort(d, kind="stable")[: lay.n_neighbours]
        meas = lay.measured(o)
        np.testing.assert_allclose(meas[:, 2], (res[order] // n_sub) / rri, atol=1e-7)
        np.testing.assert_allclose(meas[:, 3], (res[order] % n_sub) / n_sub, atol=1e-7)
        for k, j in enumerate(order):
            co = [c for c in range(par.n) if res[c] == res[i] and c not in (i, j)]
            co = sorted(co, key=lambda c: (np.sum((pos[c] - pos[j]) ** 2), c))[:2]
            want = np.zeros(6)
            for s, c in enumerate(co):
                want[3 * s : 3 * s + 3] = [*np.clip((pos[c] - pos[i]) / lay.scale_m, -10, 10), 1.0]
            np.testing.assert_allclose(meas[k, 4:], want, atol=1e-5)
        own = lay.own_v3(o)
        assert own[0] == pytest.approx(par.own.u_now[i], rel=1e-6)
        assert own[1] == pytest.approx(10 * (par.own.u_now[i] - par.own.u_prev[i]), rel=1e-5, abs=1e-6)
        np.testing.assert_allclose(own[2:4], (pos[i] - par.start_m[i]) / lay.scale_m, rtol=1e-5, atol=1e-7)
        assert own[4] == pytest.approx(26 / 30) and own[5] == pytest.approx(26 * 5.0 / 100.0)


def test_time_left_follows_a_time_limit() -> None:
    from cv2x_marl.env.single import follow_time_limit

    g = follow_time_limit(gymnasium.make("cv2x/SingleMover-v3", max_cycles=50, max_episode_steps=20, **FAST))
    assert g.unwrapped.time_limit == 20
    o, _ = g.reset(seed=1)
    lay = g.unwrapped.par.layout
    assert lay.own_v3(o)[4] == pytest.approx(1.0) and lay.own_v3(o)[5] == pytest.approx(20 * 5.0 / 100)
    for _ in range(5):
        o, *_ = g.step(np.zeros(2, np.float32))
    assert lay.own_v3(o)[4] == pytest.approx(15 / 20) and lay.own_v3(o)[5] == pytest.approx(15 * 5.0 / 100)
    plain = gymnasium.make("cv2x/SingleMover-v3", max_cycles=50, **FAST)
    o, _ = plain.reset(seed=1)
    o, *_ = plain.step(np.zeros(2, np.float32))
    assert lay.own_v3(o)[4] == pytest.approx(49 / 50)


def test_shadow_field_equal_to_snapshot_at_start() -> None:
    par = env_module.parallel_env_v3(max_cycles=10, **FAST)
    par.reset(seed=7)
    assert par.links.field is not None
    plain = SnapshotLinks(par.config, par.snapshot, par.truth_los)
    np.testing.assert_allclose(par.links.evaluate(par.start_m)[0], plain.evaluate(par.start_m)[0], atol=1e-12)
    moved = par.start_m.copy()
    moved[0] += 60.0
    assert not np.allclose(par.links.rx_dbm(moved)[0, 1:], plain.rx_dbm(moved)[0, 1:])


def test_cooperative_team_reward_and_state() -> None:
    par = env_module.parallel_env_cooperative(max_cycles=6, **FAST)
    _, infos = par.reset(seed=3)
    u_before = np.array([infos[a]["utility"] for a in par.agents])
    prr_before = par.prr.copy()
    act = {a: np.array([0.6, -0.4], np.float32) for a in par.agents}
    _, rew, _, _, infos = par.step(act)
    u_after = np.array([infos[a]["utility"] for a in par.possible_agents])
    r = np.array(list(rew.values()))
    np.testing.assert_allclose(r, u_after.mean() - u_before.mean(), rtol=1e-12)  # per-receiver utilities
    s = par.state()
    n = par.n
    assert s.shape == par.state_space.shape == (6 * n + 2 * n * n,)
    np.testing.assert_allclose(
        s[6 * n : 6 * n + n * n],
        np.clip((np.nan_to_num(par.measure.rsrp_dbm, nan=-100.0).ravel() + 100) / 20, -10, 10),
        rtol=1e-6,
    )
    prr_env = env_module.parallel_env_cooperative(max_cycles=6, team_objective="prr", **FAST)
    prr_env.reset(seed=3)
    np.testing.assert_allclose(prr_env.prr, prr_before)
    _, rew, *_ = prr_env.step(act)
    np.testing.assert_allclose(np.array(list(rew.values())), prr_env.prr.mean() - prr_before.mean(), rtol=1e-12)


def test_refusals() -> None:
    with pytest.raises(ValueError, match="invalid env argument observation=3"):
        MobilityEnv(observation=3, mode="traffic", **FAST)
    with pytest.raises(ValueError, match="invalid env argument shadow_field=True"):
        MobilityEnv(shadow_field=True, mode="traffic", **FAST)
    with pytest.raises(ValueError, match="invalid env argument action_mode='plan_residual'"):
        MobilityEnv(observation=3, action_mode="plan_residual", **FAST)
    with pytest.raises(ValueError, match="invalid env argument sensing_window=0"):
        MobilityEnv(observation=3, sensing_window=0, **FAST)


def test_measured_row_equals_sensed_row_with_exact_measurements() -> None:
    """With reports equal to the true mean power (no fading, no error, no field), the measured estimate is
    the v2 sensing estimate (own links true, other pairs at 0 dB)."""
    from cv2x_marl.env.planning import measured_plan, measured_row, reachable_set

    par = env_module.parallel_env_v3(max_cycles=20, shadow_field=False, **FAST)
    par.reset(seed=5)
    par.measure.rsrp_dbm = par.links.rx_dbm(par.positions_m)
    cand = par.positions_m[3] + np.random.default_rng(0).uniform(-60, 60, (50, 2))
    for i in (0, 3):
        got = measured_row(par, i).utility(cand, par.p_min)
        want = par.links.sensed_row(i, par.positions_m).utility(cand, par.p_min)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    plan = measured_plan(par, [0])
    assert reachable_set(par, 0).contains(plan)[0]
    row = measured_row(par, 0)
    assert row.utility(plan, par.p_min)[0] >= row.utility(par.positions_m[:1], par.p_min)[0]


def test_sensing_planner_on_v3_replans_from_measurements() -> None:
    from cv2x_marl.env.planning import MEASURED_REPLAN_EVERY, measured_plan
    from cv2x_marl.policies.planner import PlannerPolicy

    par = env_module.parallel_env_v3(max_cycles=12, movers=[0], **FAST)
    obs, _ = par.reset(seed=6)
    pol = PlannerPolicy(par, None, estimator="sensing")
    pol.reset()
    targets = []
    for _ in range(12):
        act = pol.act(obs)
        if par.t % MEASURED_REPLAN_EVERY == 0:
            targets.append(pol.targets_m["vehicle_0"].copy())
            np.testing.assert_allclose(targets[-1], measured_plan(par, [0])[0])
        want = np.clip((pol.targets_m["vehicle_0"] - par.positions_m[0]) / par.max_step_m, -1, 1)
        np.testing.assert_allclose(act["vehicle_0"], want, rtol=1e-6)
        obs, *_ = par.step(act)
    assert len(targets) == 2


def test_reset_cache_is_bit_identical_on_v3() -> None:
    fresh = env_module.parallel_env_cooperative(max_cycles=5, **FAST)
    cached = env_module.parallel_env_cooperative(max_cycles=5, reset_cache=2, **FAST)
    acts = {a: np.array([0.3, -0.7], np.float32) for a in fresh.possible_agents}
    for _ in range(2):  # the second reset of ``cached`` reuses the start (links and field)
        o1, _ = fresh.reset(seed=9)
        o2, _ = cached.reset(seed=9)
        for a in o1:
            np.testing.assert_array_equal(o1[a], o2[a])
        s1, s2 = fresh.step(acts), cached.step(acts)
        for a in o1:
            np.testing.assert_array_equal(s1[0][a], s2[0][a])
            assert s1[1][a] == s2[1][a]


def test_vector_entry_point_matches_single_envs() -> None:
    vec = gymnasium.make_vec(
        "cv2x/SingleMover-v3", num_envs=2, vectorization_mode="vector_entry_point", max_cycles=4, **FAST
    )
    assert vec.batched  # the compiled v3 step (tests/env/test_v3_fast.py)
    singles = [gymnasium.make("cv2x/SingleMover-v3", max_cycles=4, **FAST) for _ in range(2)]
    o, _ = vec.reset(seed=20)
    for k, s in enumerate(singles):
        np.testing.assert_array_equal(o[k], s.reset(seed=20 + k)[0])
    acts = np.random.default_rng(2).uniform(-1, 1, (3, 2, 2)).astype(np.float32)
    for a in acts:
        o, r, *_ = vec.step(a)
        for k, s in enumerate(singles):
            ok, rk, *_ = s.step(a[k])
            np.testing.assert_array_equal(o[k], ok)
            assert r[k] == rk
