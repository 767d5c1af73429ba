"""cv2x/Mobility-v1 and cv2x/SingleMover-v1: checkers, the new observation entries against an
independent numpy construction, improvement rewards, the settle phase, the one-mover fast path
(bit-identical to the full step), seeding that follows Gymnasium's convention."""

from __future__ import annotations

import functools

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import parallel_api_test
from pettingzoo.test.seed_test import parallel_seed_test

import cv2x_marl  # noqa: F401 - registers the ids
import cv2x_marl.env as env_module
from cv2x_marl.env import MobilityEnv
from cv2x_marl.env.defaults import V1_DEFAULTS
from cv2x_marl.env.observation import OWN_V1_NAMES
from cv2x_marl.env.single import SingleMoverEnv
from cv2x_marl.regression import TwoDistanceModel

FAST = {"overrides": ["sim.warmup_subframes=200"]}
#: the single env of the id (one class, the id an argument)
SingleMoverEnvV1 = functools.partial(SingleMoverEnv, "cv2x/SingleMover-v1")


def test_v1_ids_and_checkers() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    par = pettingzoo.make("parallel", "cv2x/Mobility-v1", max_cycles=20, **FAST)
    assert par.metadata["name"] == "cv2x_mobility_v1" and par.layout.version == 1
    parallel_api_test(env_module.parallel_env_v1(max_cycles=15, **FAST), num_cycles=30)
    parallel_seed_test(lambda: env_module.parallel_env_v1(max_cycles=10, **FAST), num_cycles=20)
    g = gymnasium.make("cv2x/SingleMover-v1", max_cycles=20, **FAST)
    assert g.observation_space.shape == (20 * 8 + 5 + len(OWN_V1_NAMES),)
    gymnasium.utils.env_checker.check_env(g.unwrapped, skip_render_check=True)
    sb3_check_env(g.unwrapped, warn=True)
    # v0 stays loadable with its own shapes
    assert gymnasium.make("cv2x/SingleMover-v0", **FAST).observation_space.shape == (145,)


def _reference_v1(env: MobilityEnv, model: TwoDistanceModel, obs: dict) -> None:
    """Rebuild each agent's v1 entries from the env's positions with plain numpy and compare."""
    pos, k, lay = env.positions_m, env.layout.n_neighbours, env.layout
    res = env.resource
    n_target = env.target.sum(axis=1)
    u_per_rx = np.where(env.target, np.log(np.maximum(env.link_p, env.p_min)), 0.0).sum(axis=1) / n_target
    for i, a in enumerate(env.agents):
        o = obs[a]
        d = np.hypot(*(pos - pos[i]).T)
        d[i] = np.inf
        order = np.argsort(d, kind="stable")[:k]
        co = [c for c in range(env.n) if c != i and res[c] == res[i]]
        want = []
        for j in order:
            dj = {c: np.hypot(*(pos[c] - pos[j])) for c in co if c != j}
            nsv = sum(v <= lay.interferer_range_m for v in dj.values())
            l_m = min(dj.values()) if nsv else lay.interferer_range_m
            want.append(model.predict(max(d[j], 1.0), l_m, nsv))
        np.testing.assert_allclose(lay.model_success(o), want, rtol=2e-6, atol=1e-7)
        np.testing.assert_allclose(lay.true_success(o), env.link_p[i, order], rtol=2e-6, atol=1e-7)
        own = lay.own_v1(o)
        assert own[0] == pytest.approx(u_per_rx[i], rel=1e-5)
        assert own[2] == pytest.approx(u_per_rx[i] - env.own.u_start[i], abs=1e-5)
        np.testing.assert_allclose(own[6:8], (env.plan_m[i] - pos[i]) / lay.scale_m, atol=1e-5)
        left = env.max_cycles - env.settle_steps - env.t
        assert own[8] == pytest.approx(left * env.max_step_m / lay.scale_m)


@pytest.mark.kernel_equality
def test_v1_observation_entries_equal_a_numpy_construction() -> None:
    env = MobilityEnv(observation=1, privileged=True, max_cycles=10, **FAST)
    obs, _ = env.reset(seed=4)
    model = TwoDistanceModel.paper_table2()
    _reference_v1(env, model, obs)
    rng = np.random.default_rng(1)
    u_hist = [env.layout.own_v1(obs["vehicle_3"])[0]]
    best_pos = env.positions_m[3].copy()
    for _ in range(4):
        obs, *_ = env.step({a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents})
        _reference_v1(env, model, obs)
        own = env.layout.own_v1(obs["vehicle_3"])
        if own[0] > max(u_hist):
            best_pos = env.positions_m[3].copy()
        assert own[1] == pytest.approx(10 * (own[0] - u_hist[-1]), abs=1e-4)
        assert own[3] == pytest.approx(max([*u_hist, own[0]]) - own[0], abs=1e-5)
        np.testing.assert_allclose(own[4:6], (best_pos - env.positions_m[3]) / 100.0, atol=1e-5)
        u_hist.append(own[0])


@pytest.mark.parametrize("reward", ["individual", "team", "mixed"])
def test_improvement_rewards_sum_to_final_minus_start(reward: str) -> None:
    env = MobilityEnv(reward=reward, reward_form="improvement", max_cycles=12, **FAST)
    ref = MobilityEnv(reward=reward, reward_form="utility", max_cycles=12, **FAST)
    env.reset(seed=2)
    ref.reset(seed=2)
    rng = np.random.default_rng(0)
    total = np.zeros(env.n)
    start = ref.rewarder.base(ref, ref.utility).copy()
    while env.agents:
        act = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}
        r, r_ref = env.step(act)[1], ref.step(act)[1]
        total += np.array(list(r.values()))
    final = np.array(list(r_ref.values()))
    np.testing.assert_allclose(total, final - start, rtol=1e-9, atol=1e-9)


def test_settle_phase_freezes_positions() -> None:
    env = MobilityEnv(movers=[0], settle_steps=3, max_cycles=8, **FAST)
    env.reset(seed=0)
    for t in range(8):
        before = env.positions_m[0].copy()
        env.step({a: np.ones(2, np.float32) for a in env.agents})
        moved = not np.allclose(env.positions_m[0], before)
        assert moved == (t < 5)
    with pytest.raises(ValueError, match="settle_steps"):
        MobilityEnv(settle_steps=8, max_cycles=8)


@pytest.mark.parametrize("version", [0, 1])
def test_one_mover_fast_path_is_bit_identical(version: int) -> None:
    cls = SingleMoverEnvV1 if version else SingleMoverEnv
    fast = cls(max_cycles=40, **FAST)
    full = MobilityEnv(movers=[0], max_cycles=40, **FAST, **(V1_DEFAULTS if version else {}))
    assert fast.fast
    of, _ = fast.reset(seed=7)
    og, _ = full.reset(seed=7)
    assert np.array_equal(of, og["vehicle_0"])
    rng = np.random.default_rng(5)
    zero = np.zeros(2, np.float32)
    for _ in range(40):
        act = rng.uniform(-1.4, 1.4, 2).astype(np.float32)  # some clipped
        o1, r1, term, trunc, i1 = fast.step(act)
        o2, r2, _, tr2, i2 = full.step({a: act if a == "vehicle_0" else zero for a in full.agents})
        assert r1 == r2["vehicle_0"]  # bit-identical, not approximately equal
        assert np.array_equal(o1, o2["vehicle_0"])
        assert i1 == i2["vehicle_0"] and trunc == tr2["vehicle_0"] and not term


def test_seeded_first_reset_fixes_the_episode_sequence() -> None:
    for make in (
        lambda: MobilityEnv(max_cycles=2, **FAST),
        lambda: env_module.parallel_env_v1(max_cycles=2, **FAST),
    ):
        seqs = []
        for _ in range(2):
            e = make()
            e.reset(seed=11)
            seqs.append([e.reset()[0]["vehicle_0"].tobytes() for _ in range(3)] + [e.seed_used])
        assert seqs[0] == seqs[1]
        e = make()
        e.reset(seed=12)
        assert e.reset()[0]["vehicle_0"].tobytes() != seqs[0][0]
    for cls in (SingleMoverEnv, SingleMoverEnvV1):
        a, b = cls(**FAST), cls(**FAST)
        a.reset(seed=3)
        b.reset(seed=3)
        assert all(np.array_equal(a.reset()[0], b.reset()[0]) for _ in range(2))


def test_bad_v1_arguments_name_the_argument() -> None:
    for kwargs, name in (
        ({"observation": 4}, "observation"),
        ({"observation": True}, "observation"),
        ({"privileged": True}, "privileged"),
        ({"reward_form": "delta"}, "reward_form"),
        ({"settle_steps": -1}, "settle_steps"),
        ({"observation": 1, "model": "/nonexistent/model.json"}, "model"),
    ):
        with pytest.raises(ValueError, match=name):
            MobilityEnv(**kwargs)
    e = MobilityEnv(**FAST)
    for seed in (1.5, -1, True, "3"):
        with pytest.raises(ValueError, match="seed"):
            e.reset(seed=seed)  # type: ignore[arg-type]


def test_oracle_step_does_not_depend_on_reward_normalisation() -> None:
    from cv2x_marl.policies.scripted import OraclePolicy

    acts = []
    for normalise in (False, True):
        e = MobilityEnv(movers=[0], normalise_reward=normalise, **FAST)
        obs, _ = e.reset(seed=6)
        acts.append(OraclePolicy(e).act({"vehicle_0": obs["vehicle_0"]})["vehicle_0"])
    assert np.abs(acts[0]).max() > 1e-3  # it does move
    np.testing.assert_array_equal(acts[0], acts[1])
