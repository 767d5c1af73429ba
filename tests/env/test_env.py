"""The PettingZoo env: ecosystem conformance suites, our own checks, bad input, GBMU equivalence."""

import random
import warnings

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import api_test, max_cycles_test, parallel_api_test, render_test, seed_test
from pettingzoo.test.seed_test import parallel_seed_test

import cv2x_marl
import cv2x_marl.env as env_module
from cv2x_marl.config import preset
from cv2x_marl.env import MobilityEnv, parallel_env
from cv2x_marl.experiments.gbmu_study import _snapshots, gbmu_inputs
from cv2x_marl.policies.gbmu import climb, gbmu_direction
from cv2x_marl.policies.scripted import GbmuPolicy
from cv2x_marl.regression import TwoDistanceModel
from cv2x_marl.sim.ground_truth import MoverLinks

FAST = {"overrides": ["sim.warmup_subframes=200"]}


def test_parallel_api() -> None:
    parallel_api_test(parallel_env(max_cycles=30, **FAST), num_cycles=60)


def test_aec_api() -> None:
    api_test(env_module.env(max_cycles=10, **FAST), num_cycles=20)


def test_seed() -> None:
    seed_test(lambda: env_module.env(max_cycles=10, **FAST), num_cycles=20)
    parallel_seed_test(lambda: parallel_env(max_cycles=10, **FAST), num_cycles=20)


def test_max_cycles() -> None:
    max_cycles_test(env_module)


def test_render() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # Agg cannot open a window in human mode
        render_test(lambda render_mode=None: env_module.env(render_mode=render_mode, max_cycles=10, **FAST))
    e = parallel_env(render_mode="rgb_array", **FAST)
    e.reset(seed=0)
    img = e.render()
    assert img is not None and img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    assert img.std() > 5  # not a blank frame


def test_multi_step_determinism() -> None:
    def rollout(seed: int) -> list:
        e = parallel_env(max_cycles=40, **FAST)
        obs, _ = e.reset(seed=seed)
        rng = np.random.default_rng(99)
        trace = [np.stack(list(obs.values()))]
        while e.agents:
            acts = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in e.agents}
            obs, rew, _, _, _ = e.step(acts)
            trace.append(np.r_[np.stack(list(obs.values())).ravel(), list(rew.values())])
        return trace

    a, b, c = rollout(4), rollout(4), rollout(5)
    assert len(a) == 41
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[10], c[10])


def test_registry_and_single_mover_checkers() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    assert isinstance(pettingzoo.make("parallel", "cv2x/Mobility-v0", **FAST), MobilityEnv)
    assert pettingzoo.make("aec", "cv2x/Mobility-v0", **FAST).metadata["name"] == "cv2x_mobility_v0"
    g = gymnasium.make("cv2x/SingleMover-v0", max_cycles=20, **FAST)
    gymnasium.utils.env_checker.check_env(g.unwrapped, skip_render_check=True)
    sb3_check_env(g.unwrapped, warn=True)
    assert cv2x_marl.__version__


def test_spaces_are_shared_objects() -> None:
    e = parallel_env(**FAST)
    assert e.observation_space("vehicle_0") is e.observation_space("vehicle_5")
    assert e.action_space("vehicle_0") is e.action_space("vehicle_20")
    obs, _ = e.reset(seed=0)
    assert all(e.observation_space(a).contains(o) for a, o in obs.items())
    assert e.state().shape == e.state_space.shape and e.state_space.contains(e.state())


def test_caller_global_rng_untouched() -> None:
    np.random.seed(7)  # noqa: NPY002 - the caller's global state, set on purpose
    random.seed(7)
    before = (np.random.get_state()[1].copy(), random.getstate())  # noqa: NPY002
    e = parallel_env(max_cycles=5, **FAST)
    e.reset(seed=1)
    while e.agents:
        e.step({a: e.action_space(a).sample() for a in e.agents})
    e.reset()  # unseeded reset draws its seed from OS entropy, not from the global state
    assert np.array_equal(before[0], np.random.get_state()[1])  # noqa: NPY002
    assert before[1] == random.getstate()


def test_rewards_are_eq12_of_the_link_model() -> None:
    e = parallel_env(max_cycles=5, **FAST)
    e.reset(seed=3)
    _, rew, _, _, info = e.step({a: np.array([0.3, -0.2], np.float32) for a in e.agents})
    p = e.links.success(e.positions_m)
    u = np.where(e.links.target, np.log(np.maximum(p, 1e-3)), 0.0).sum(axis=1)
    assert rew["vehicle_4"] == pytest.approx(u[4])
    assert info["vehicle_4"]["utility"] == pytest.approx(u[4])
    assert info["vehicle_4"]["offset_x_m"] == pytest.approx(1.5) and info["vehicle_4"]["offset_y_m"] == pytest.approx(
        -1.0
    )
    for kind, expect in (("team", u.mean()), ("mixed", 0.25 * u[4] + 0.75 * u.mean())):
        e2 = parallel_env(max_cycles=5, reward=kind, local_ratio=0.25, **FAST)
        e2.reset(seed=3)
        _, r2, _, _, _ = e2.step({a: np.array([0.3, -0.2], np.float32) for a in e2.agents})
        assert r2["vehicle_4"] == pytest.approx(expect)


def test_bad_actions_and_arguments() -> None:
    e = parallel_env(max_cycles=5, **FAST)
    e.reset(seed=0)
    acts = {a: np.zeros(2, np.float32) for a in e.agents}
    with pytest.raises(ValueError, match="vehicle_3"):
        e.step({**acts, "vehicle_3": np.array([np.nan, 0.0])})
    with pytest.raises(KeyError, match="vehicle_99"):
        e.step({**acts, "vehicle_99": np.zeros(2)})
    missing = dict(acts)
    del missing["vehicle_2"]
    with pytest.raises(KeyError, match="vehicle_2"):
        e.step(missing)
    _, _, _, _, info = e.step({**acts, "vehicle_1": np.array([3.0, 0.0], np.float32)})
    assert info["vehicle_1"]["clipped"] == 1.0 and info["vehicle_1"]["offset_x_m"] == pytest.approx(5.0)
    assert info["vehicle_0"]["clipped"] == 0.0
    with pytest.raises(ValueError, match=r"vehicle_4 must have shape \(2,\)"):
        e.step({**acts, "vehicle_4": np.zeros(3)})
    with pytest.raises(ValueError, match="vehicle_6 must have shape"):
        e.step({**acts, "vehicle_6": np.zeros(1)})
    with pytest.raises(ValueError, match="vehicle_5 must be numeric"):
        e.step({**acts, "vehicle_5": "left"})
    # any array with two numbers is an action: (1, 2) rows, one agent or all of them
    e.reset(seed=0)
    _, r_flat, *_ = e.step(acts)
    e.reset(seed=0)
    _, r_row, *_ = e.step({**acts, "vehicle_7": np.array([[0.0, 0.0]])})
    _, r_all, *_ = e.step({a: np.zeros((2, 1)) for a in e.agents})
    assert r_row["vehicle_7"] == pytest.approx(r_all["vehicle_7"]) == pytest.approx(r_flat["vehicle_7"])
    with pytest.raises(TypeError, match="dict agent -> action"):
        e.step([np.zeros(2)] * 21)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="max_step_m"):
        parallel_env(max_step_m=-1)
    with pytest.raises(ValueError, match=r"mode.*snapshot \| traffic"):
        parallel_env(mode="warp")
    with pytest.raises(ValueError, match=r"sps\.keep_probability"):
        parallel_env(overrides=["sps.keep_probability=2"])


def test_truncation_and_bounds() -> None:
    e = parallel_env(max_cycles=3, max_drift_m=4.0, **FAST)
    e.reset(seed=0)
    for k in range(3):
        _, _, term, trunc, _ = e.step({a: np.ones(2, np.float32) for a in e.agents})
        assert all(trunc.values()) == (k == 2) and not any(term.values())
    assert e.agents == []
    assert np.all(np.hypot(*(e.positions_m - e.start_m).T) <= 4.0 + 1e-9)


def test_traffic_mode() -> None:
    e = parallel_env(mode="traffic", max_cycles=6, **FAST)
    e.reset(seed=2)
    start = e.positions_m.copy()
    odo = e.sim.state.odometer_m.copy()
    while e.agents:
        _obs, rew, _, _, _info = e.step({a: np.array([1.0, 0.0], np.float32) for a in e.agents})
        assert all(np.isfinite(list(rew.values())))
    driven = e.sim.state.odometer_m - odo
    np.testing.assert_allclose(driven, e.sim.state.speed_mps * 0.6)  # six 100-ms periods on the roads
    assert not np.allclose(e.positions_m, start)
    assert np.all(np.hypot(*e.offsets_m.T) <= 10.0 + 1e-9)  # default traffic drift bound


def test_gbmu_through_the_env_reproduces_the_study() -> None:
    cfg = preset("paper")
    seed, k = 11, 300
    model = TwoDistanceModel.paper_table2()
    snap = _snapshots(cfg, [seed], progress=False)
    links = MoverLinks.from_snapshots(cfg, snap, [0])
    inputs = gbmu_inputs(snap, [0], links, 200.0)
    study = climb(links.start_m, gbmu_direction(inputs, model), 1.0, 0.0, k)
    env = parallel_env(movers=[0], max_cycles=k, max_step_m=1.0)
    obs, _ = env.reset(seed=seed)
    policy = GbmuPolicy(model, env.layout, env.max_step_m, delta=1.0)
    zero = np.zeros(2, np.float32)
    info = {}
    while env.agents:
        act = policy.act({"vehicle_0": obs["vehicle_0"]})
        obs, _, _, _, info = env.step({a: act.get(a, zero) for a in env.agents})
    np.testing.assert_allclose(env.positions_m[0], study.final_m[0], atol=1e-3)
    u_study = float(np.where(links.target[0], np.log(np.maximum(links.success(study.final_m)[0], 1e-3)), 0).sum())
    assert info["vehicle_0"]["utility"] == pytest.approx(u_study, rel=1e-4)


def test_action_dict_order_does_not_matter() -> None:
    rng = np.random.default_rng(4)
    acts = {f"vehicle_{i}": rng.uniform(-1.2, 1.2, 2).astype(np.float32) for i in range(21)}
    shuffled = dict(reversed(list(acts.items())))
    out = []
    for a in (acts, shuffled):
        e = parallel_env(max_cycles=5, **FAST)
        e.reset(seed=9)
        out.append(e.step(a))
    for name in acts:
        np.testing.assert_array_equal(out[0][0][name], out[1][0][name])
        assert out[0][1][name] == out[1][1][name] and out[0][4][name] == out[1][4][name]
    assert out[0][4]["vehicle_0"]["offset_x_m"] != 0.0  # the actions did move the vehicles
