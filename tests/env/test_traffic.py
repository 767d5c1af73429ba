"""cv2x/Traffic-v0: speed and lane commands on the lane model, episode-mean metrics, its policies and ceiling."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.config import RoadConfig
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments import evaluate as ev
from cv2x_marl.policies import traffic
from cv2x_marl.policies.registry import make_policy
from cv2x_marl.sim import mobility
from cv2x_marl.sim.road import Road

LIMIT = 16.67  # the paper preset's vehicles.speed_max_mps
DT = 0.1  # one 100-ms period
TWO_LANES = ["road.lanes_per_direction=2"]
TINY = traffic.SearchSettings(segments=2, population=4, elites=2, iterations=1)


def test_drive_hand_computed_step() -> None:
    road = Road.from_config(RoadConfig(kind="grid", length_m=450.0, n_roads_per_axis=4, lanes_per_direction=2))
    n = 6
    st = mobility.VehicleState(
        axis=np.zeros(n, dtype=np.int8),
        direction=np.ones(n, dtype=np.int8),
        road=np.zeros(n, dtype=np.int64),
        lane=np.array([0, 0, 1, 1, 0, 1]),
        s_m=np.linspace(10.0, 60.0, n),
        speed_mps=np.array([10.0, 0.2, 16.6, 5.0, 7.0, 3.0]),
        odometer_m=np.zeros(n),
    )
    target = np.array([LIMIT, 0.0, 30.0, 5.1, np.nan, 0.0])
    lanes = np.array([1, -1, -1, 1, 1, 0])  # left, right, right (none there), left, (no command), keep
    out = mobility.drive(road, st, target, lanes, 2.6, 3.4, DT, LIMIT)
    # 10 + 2.6 x 0.1; 0.2 - 3.4 x 0.1 < 0 -> the target 0; 30 clipped to the limit, 16.6 + 0.26 > limit;
    # 5.1 within 0.26 of 5; no command: unchanged; 3 - 0.34
    np.testing.assert_allclose(out.speed_mps, [10.26, 0.0, LIMIT, 5.1, 7.0, 2.66], rtol=0, atol=1e-12)
    assert out.speed_mps[4] == st.speed_mps[4]  # bit for bit
    assert out.lane.tolist() == [0, 1, 1, 0, 0, 1]  # lane 0 has no lane to its left, lane 1 none to its right
    np.testing.assert_array_equal(out.s_m, st.s_m)  # positions move in advance(), at the new speed
    moved = mobility.advance(road, RoadConfig(kind="grid"), out, DT, np.random.default_rng(0))
    np.testing.assert_allclose(moved.s_m - st.s_m, out.speed_mps * DT, atol=1e-12)  # no crossing passed here
    with pytest.raises(ValueError, match="lane_change must hold"):
        mobility.drive(road, st, target, np.full(n, 2), 2.6, 3.4, DT, LIMIT)


def _run(env: Any, actions: np.ndarray) -> list[tuple[Any, ...]]:
    out = []
    for a in actions:
        ob, r, term, trunc, info = env.step(a)
        out.append((ob, r, term, trunc, info))
    return out


def test_traffic_env_speed_limits_accel_bounds_and_lanes() -> None:
    env = gym.make("cv2x/Traffic-v0", overrides=TWO_LANES, max_cycles=30)
    par = env.unwrapped.par
    ob, info = env.reset(seed=11)
    rng = np.random.default_rng(3)
    actions = rng.uniform(-1.0, 1.0, (30, 2)).astype(np.float32)
    actions[:10, 0] = 1.0  # full speed first, then full stop, then random
    actions[10:20, 0] = -1.0
    others = par.sim.state.speed_mps[1:].copy()
    v, lane = info["speed_mps"], info["lane"]
    lanes_seen = {lane}
    for a in actions:
        ob, _, _, _, info = env.step(a)
        goal = min(max(0.5 * (float(a[0]) + 1.0) * LIMIT, 0.0), LIMIT)
        expected = min(max(goal, v - 3.4 * DT), v + 2.6 * DT)
        assert info["speed_mps"] == pytest.approx(expected, abs=1e-9)
        assert 0.0 <= info["speed_mps"] <= LIMIT
        want = lane - (1 if a[1] > 0.5 else -1 if a[1] < -0.5 else 0)
        assert info["lane"] == (want if 0 <= want <= 1 else lane)
        v, lane = info["speed_mps"], info["lane"]
        lanes_seen.add(lane)
        drive = par.layout.own_drive(ob)
        assert drive[0] == pytest.approx(v / LIMIT, rel=1e-6) and drive[3] == lane
        assert drive[4] == (lane > 0) and drive[5] == (lane < 1)
    assert lanes_seen == {0.0, 1.0}
    np.testing.assert_array_equal(par.sim.state.speed_mps[1:], others)  # the other vehicles: constant speeds


def test_episode_metrics_are_the_average_of_the_step_infos() -> None:
    env = gym.make("cv2x/Traffic-v0", max_cycles=7)
    _, first = env.reset(seed=4)
    assert first["utility_mean"] == first["utility"] and first["prr_mean"] == first["prr"]
    assert first["jain_mean"] == first["jain"]
    steps = _run(env, np.tile(np.array([0.3, 0.0], np.float32), (7, 1)))
    infos = [s[4] for s in steps]
    assert steps[-1][3] is True
    for key in ("utility", "prr", "jain"):  # every step's mean so far: the average of the periods' values
        for t in range(1, 8):
            want = np.mean([i[key] for i in infos[:t]])
            assert infos[t - 1][f"{key}_mean"] == pytest.approx(want, rel=1e-12)
    assert len({i["jain"] for i in infos}) > 1  # the periods differ: the last one is not the mean
    assert [s[1] for s in steps] == [i["utility"] for i in infos]  # reward: the period's utility per receiver
    # evaluate's rows: jain_mean is the episode's mean (jain_end the last period's), jain_fairness their mean
    par = make_parallel_env("cv2x/Traffic-v0", max_cycles=7)
    obs, _ = par.reset(seed=4)
    policy = make_policy("static", par)
    policy.reset(4)
    jains = []
    while par.agents:
        obs, _, _, _, inf = par.step({**{a: np.zeros(2, np.float32) for a in par.agents}, **policy.act(obs)})
        jains.append(inf["vehicle_0"]["jain"])
    summary, rows = ev.evaluate_rows("cv2x/Traffic-v0", "static", 0, 0, env_kwargs={"max_cycles": 7},
                                     progress=False, seeds=[4])  # fmt: skip
    assert rows[0]["jain_mean"] == pytest.approx(sum(jains) / 7, rel=1e-12) and rows[0]["jain_end"] == jains[-1]
    assert summary["jain_fairness"] == rows[0]["jain_mean"]


def test_seeding_same_trajectory_and_the_checker() -> None:
    from gymnasium.utils.env_checker import check_env

    acts = np.random.default_rng(0).uniform(-1, 1, (6, 2)).astype(np.float32)
    runs = []
    for _ in range(2):
        env = gym.make("cv2x/Traffic-v0", max_cycles=6)
        ob, _ = env.reset(seed=21)
        runs.append([ob, *[(s[0], s[1], s[4]) for s in _run(env, acts)]])
    for a, b in zip(runs[0], runs[1], strict=True):
        assert repr(a) == repr(b)
    check_env(gym.make("cv2x/Traffic-v0", max_cycles=6).unwrapped)


def test_policies_without_a_road_version_are_refused() -> None:
    env = make_parallel_env("cv2x/Traffic-v0", max_cycles=4)
    for name in ("greedy", "oracle", "planner", "best-response"):
        with pytest.raises(ValueError, match=rf"policy '{name}' moves vehicles by position offsets and has no road"):
            make_policy(name, env)
    with pytest.raises(ValueError, match="policy 'planner' cannot run on task traffic"):
        ev.evaluate("cv2x/Traffic-v0", "planner", 1, 0, progress=False)
    assert isinstance(make_policy("static", env), traffic.HoldSpeedPolicy)
    assert isinstance(make_policy("gbmu", env), traffic.RoadGbmuPolicy)
    with pytest.raises(ValueError, match="invalid env argument movers: Traffic-v0 always moves vehicle 0"):
        gym.make("cv2x/Traffic-v0", movers=[1])
    with pytest.raises(ValueError, match="invalid env argument drive_observation=True"):
        make_parallel_env("cv2x/SingleMover-v3", drive_observation=True)


def test_ceiling_at_least_every_scripted_method_and_evaluate_scores(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(traffic, "DEFAULT_SEARCH", TINY)
    opts = {"max_cycles": 8}
    env = make_parallel_env("cv2x/Traffic-v0", **opts)
    seeds = [5, 9]
    for seed in seeds:
        env.reset(seed=seed)
        res = traffic.traffic_search(env, make_policy)
        assert res.evaluated == len(TINY.seeded) + TINY.population * TINY.iterations
        for method in ("static", "random", "gbmu", "sensing"):
            r = traffic.rollout(env, lambda e, m=method: make_policy(m, e))
            assert res.scripted[method] == r.utility_mean  # the seeded candidate is the method's own episode
            assert res.best.utility_mean >= r.utility_mean
        replay = traffic.rollout(env, actions=res.best.actions)  # the best found replays exactly
        assert replay.utility_mean == res.best.utility_mean
    # evaluate: the episode means, the gains against static's means on the same episode, the ceiling's share
    out = {}
    for method in ("static", "gbmu", "optimum"):
        summary, rows = ev.evaluate_rows(
            "cv2x/Traffic-v0", method, 0, 0, env_kwargs=opts, progress=False, seeds=seeds, vs_optimum=True
        )
        out[method] = rows
        assert summary["gains_of"] == "each mover's episode means against static's on the same episode"
        for r in rows:
            assert r["utility_end"] <= r["utility_optimum"]
            env.reset(seed=r["seed"])
            assert r["utility_start"] == traffic.rollout(env, lambda e: make_policy("static", e)).utility_mean
            assert r["utility_optimum"] == traffic.traffic_search(env, make_policy).best.utility_mean
            assert r["utility_gain"] == pytest.approx((r["utility_end"] - r["utility_start"]) / abs(r["utility_start"]))
    assert all(r["utility_gain"] == 0.0 for r in out["static"])
    assert [r["utility_end"] for r in out["optimum"]] == [r["utility_optimum"] for r in out["optimum"]]


def test_parallel_variant_every_vehicle_drives() -> None:
    """``cv2x/Traffic-v0`` in PettingZoo with ``movers=None``: every vehicle commands its own speed, each rewarded
    with its own period's eq. 12 utility per target receiver (an independent numpy sum over the period's links)."""
    import pettingzoo

    from cv2x_marl.sim.metrics import CAUSE_CODE

    env = pettingzoo.make("parallel", "cv2x/Traffic-v0", max_cycles=3, movers=None)
    assert env.metadata["name"] == "cv2x_traffic_v0" and env.mover_mask.all()
    env.reset(seed=2)
    v0 = env.sim.state.speed_mps.copy()
    goals = np.linspace(-1.0, 1.0, env.n)
    _, rew, _, _, info = env.step({a: np.array([g, 0.0], np.float32) for a, g in zip(env.agents, goals, strict=True)})
    target = 0.5 * (goals.astype(np.float32).astype(np.float64) + 1.0) * LIMIT
    np.testing.assert_allclose(env.sim.state.speed_mps, np.clip(target, v0 - 0.34, v0 + 0.26), atol=1e-12)
    tx, _, p, cause = env.sim.last_links
    ok = cause != CAUSE_CODE["half_duplex"]
    for i, a in enumerate(env.possible_agents):
        mine = ok & (tx == i)
        want = np.log(np.maximum(p[mine], env.p_min)).sum() / max(int(mine.sum()), 1)
        assert rew[a] == info[a]["utility"] == pytest.approx(want, rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("version", ["v0", "v1"])
def test_pettingzoo_id_api_seeding_and_the_gymnasium_task(version: str) -> None:
    """The PettingZoo id passes PettingZoo's API and seeding tests (vehicle 0 driving, and every vehicle), and
    with its default movers (vehicle 0) is the Gymnasium id's task: the same observations and rewards."""
    import pettingzoo
    from pettingzoo.test import api_test, parallel_api_test
    from pettingzoo.test.seed_test import parallel_seed_test

    from cv2x_marl import env as env_module

    env_id = f"cv2x/Traffic-{version}"
    factory = env_module.parallel_env_traffic if version == "v0" else env_module.parallel_env_traffic_v1
    par = pettingzoo.make("parallel", env_id, max_cycles=5)
    assert np.flatnonzero(par.mover_mask).tolist() == [0] and par.drives
    assert par.metadata["name"] == f"cv2x_traffic_{version}"
    assert par.layout.version == (0 if version == "v0" else 4)
    assert np.flatnonzero(make_parallel_env(env_id, movers=None).mover_mask).size == par.n
    gym_env = gym.make(env_id, max_cycles=5)
    obs, _ = par.reset(seed=8)
    ob, _ = gym_env.reset(seed=8)
    np.testing.assert_array_equal(obs["vehicle_0"], ob)
    rng = np.random.default_rng(5)
    for _ in range(5):
        acts = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in par.agents}  # the others' are ignored
        obs, rew, _, _, _ = par.step(acts)
        ob, r, *_ = gym_env.step(acts["vehicle_0"])
        np.testing.assert_array_equal(obs["vehicle_0"], ob)
        assert rew["vehicle_0"] == r
    parallel_api_test(factory(max_cycles=5), num_cycles=10)
    parallel_api_test(factory(max_cycles=5, movers=None), num_cycles=10)
    parallel_seed_test(lambda: factory(max_cycles=5, movers=None), num_cycles=8)
    api_test(pettingzoo.make("aec", env_id, max_cycles=3), num_cycles=6)
