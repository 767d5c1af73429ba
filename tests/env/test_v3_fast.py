"""Fast v3 paths (issue 27): the shadowing field read once per step, and the one-mover step for v3.

Reference values: the separate numpy-reference calls (``SnapshotLinks.evaluate`` / ``rx_dbm``) and the
full ``MobilityEnv.step`` (every vehicle's links and measurements); every comparison is exact
(``np.array_equal``), since the fast paths use the same compiled arithmetic on the same inputs, except
where the compiled received power meets numpy's (``rx_dbm``): numba's ``log10`` against numpy's (SIMD on
some CPUs) differ in the last ulps, so those compare to :data:`RX_ATOL_DB` and are ``kernel_equality``
tests (rerun by ``make test-portable``).
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env.defaults import V3_DEFAULTS
from cv2x_marl.env.mobility_env import INFO_KEYS, MobilityEnv
from cv2x_marl.env.mover_batch import MoverBatch, batch_problem
from cv2x_marl.env.mover_links import MoverLinksStep
from cv2x_marl.env.single import SingleMoverEnv
from cv2x_marl.sim import kernels

FAST = {"overrides": ["sim.warmup_subframes=200"]}
#: the single env of the id (one class, the id an argument)
SingleMoverEnvV3 = functools.partial(SingleMoverEnv, "cv2x/SingleMover-v3")
#: compiled vs numpy received power (dB): a few ulps of log10 on values of about 100 dB are about 1e-13 dB
RX_ATOL_DB = 1e-9


def _v3(**kw: Any) -> MobilityEnv:
    return MobilityEnv(movers=[0], **{**V3_DEFAULTS, **FAST, **kw})


def _moved(env: MobilityEnv, rng: np.random.Generator, spread_m: float = 40.0) -> np.ndarray:
    """Positions with about half the vehicles moved (a normal offset of ``spread_m``)."""
    moving = rng.random((env.n, 1)) < 0.5
    return env.start_m + rng.normal(0.0, spread_m, env.start_m.shape) * moving


@pytest.mark.kernel_equality
@pytest.mark.parametrize("kw", [{}, {"shadow_field": False}, {"overrides": ["road.wrap_distances=true"]}])
def test_evaluate_rx_equals_the_separate_calls_bit_for_bit(kw: dict[str, Any]) -> None:
    env = _v3(**{**kw, "overrides": [*FAST["overrides"], *kw.get("overrides", [])]})
    env.reset(seed=4)
    links = env.links
    rng = np.random.default_rng(1)
    for _ in range(5):
        pos = _moved(env, rng)
        p, geometry, rx = links.evaluate_rx(pos)
        p_ref, geometry_ref = links.evaluate(pos)
        assert np.array_equal(p, p_ref)
        assert np.array_equal(geometry.disp_m, geometry_ref.disp_m)
        ref = links.rx_dbm(pos)  # the numpy reference: EIRP - PL - shadowing
        assert np.array_equal(np.isneginf(rx), np.isneginf(ref))
        np.testing.assert_allclose(rx, ref, rtol=0, atol=RX_ATOL_DB)
        assert np.isneginf(np.diag(rx)).all()


@pytest.mark.kernel_equality
def test_pair_rx_dbm_equals_the_numpy_reference_with_a_cut_off() -> None:
    env = _v3(overrides=[*FAST["overrides"], "link.max_range_m=250"])
    env.reset(seed=2)
    pos = _moved(env, np.random.default_rng(3), 120.0)
    links = env.links
    shadow = links.field.shadow_db(pos)
    a = links.kernel_args
    rx = kernels.pair_rx_dbm(pos, a.period_m, a.los, shadow, float(links.eirp_dbm), a.wb1, a.range2_m2)
    ref = links.rx_dbm(pos)
    assert np.isneginf(ref).sum() > env.n  # the cut-off is exercised
    assert np.array_equal(np.isneginf(rx), np.isneginf(ref))
    np.testing.assert_allclose(rx, ref, rtol=0, atol=RX_ATOL_DB)


def test_mover_links_step_equals_the_full_evaluation() -> None:
    """Row and column of the mover (P and received power) against ``evaluate_rx`` with the mover moved."""
    env = _v3(max_step_m=30.0)
    env.reset(seed=6)
    pos = env.positions_m.copy()
    p, _, rx = env.links.evaluate_rx(pos)
    rng = np.random.default_rng(5)
    for mover in (0, 7, 20):
        step = MoverLinksStep(env.links, mover, pos, column=True)
        for _ in range(8):
            pos[mover] += rng.normal(0.0, 30.0, 2)
            step.step(pos, p, rx)
            p_ref, _, rx_ref = env.links.evaluate_rx(pos)
            assert np.array_equal(p[mover], p_ref[mover])
            assert np.array_equal(p[:, mover], p_ref[:, mover])
            assert np.array_equal(rx[:, mover], rx_ref[:, mover])
        assert p[mover].any() and p[:, mover].any()  # links that decode


def _episodes_fast_vs_full(seed: int, episodes: int = 2, **kw: Any) -> int:
    fast, full = _v3(**kw), _v3(**kw)
    assert fast.fast_mover == 0
    rng = np.random.default_rng(seed)
    compared = 0
    for e in range(episodes):
        o1, i1 = fast.reset(seed=seed + 100 * e)
        o2, i2 = full.reset(seed=seed + 100 * e)
        assert np.array_equal(o1["vehicle_0"], o2["vehicle_0"]) and i1 == i2
        while fast.agents:
            act = rng.uniform(-1.5, 1.5, 2)
            ob, reward, done, info = fast.step_mover(act)
            actions = {a: np.zeros(2) for a in full.agents}
            actions["vehicle_0"] = act
            obs, rewards, terms, truncs, infos = full.step(actions)
            assert np.array_equal(ob, obs["vehicle_0"]) and ob.dtype == obs["vehicle_0"].dtype
            assert reward == rewards["vehicle_0"] and done == truncs["vehicle_0"] and not terms["vehicle_0"]
            assert info == infos["vehicle_0"] and list(info) == list(INFO_KEYS)
            # the mover's measurements (what it observes) are the full step's
            assert np.array_equal(fast.measure.rsrp_dbm[:, 0], full.measure.rsrp_dbm[:, 0], equal_nan=True)
            assert np.array_equal(fast.measure.age[:, 0], full.measure.age[:, 0])
            compared += 1
    return compared


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_step_mover_equals_step_bit_for_bit_over_whole_episodes(seed: int) -> None:
    assert _episodes_fast_vs_full(seed, max_cycles=25, max_step_m=12.0) == 50


def test_step_mover_equals_step_with_options() -> None:
    n = _episodes_fast_vs_full(
        9, episodes=1, max_cycles=20, max_step_m=20.0, reward_form="utility", normalise_reward=False,
        max_drift_m=60.0, settle_steps=3, overrides=[*FAST["overrides"], "link.inband_emission_db=-20"],
    )  # fmt: skip
    assert n == 20


def test_update_of_one_receiver_equals_its_column_of_the_full_update() -> None:
    a, b = _v3(), _v3()
    a.reset(seed=8)
    b.reset(seed=8)
    rng = np.random.default_rng(2)
    for _ in range(15):
        pos = _moved(a, rng)
        p, _, rx = a.links.evaluate_rx(pos)
        a.measure.update(rx, p)
        b.measure.update(rx, p, np.array([3], dtype=np.int64))
        assert np.array_equal(a.measure.rsrp_dbm[:, 3], b.measure.rsrp_dbm[:, 3], equal_nan=True)
        assert np.array_equal(a.measure.age[:, 3], b.measure.age[:, 3])
    assert a.measure.rng.random() == b.measure.rng.random()  # the same draws consumed


def test_single_mover_v3_takes_the_fast_path_and_the_vector_env_is_batched() -> None:
    env = SingleMoverEnvV3(**FAST)
    assert env.fast and env.par.fast_mover == 0
    assert MobilityEnv(movers=[0], shadow_field=True, truth_los="geometry", **FAST).fast_mover is None  # numpy path
    assert batch_problem(env.par) is None
    reason = batch_problem(MobilityEnv(movers=[0], shadow_field=True, **FAST))
    assert reason is not None and "observation version 3" in reason
    vec = gym.make_vec("cv2x/SingleMover-v3", num_envs=2, vectorization_mode="vector_entry_point", max_cycles=6, **FAST)
    assert vec.unwrapped.batched
    refs = [SingleMoverEnvV3(max_cycles=6, **FAST) for _ in range(2)]
    obs, _ = vec.reset(seed=[11, 12])
    for k, ref in enumerate(refs):
        assert np.array_equal(obs[k], ref.reset(seed=11 + k)[0])
    rng = np.random.default_rng(0)
    for _ in range(6):
        act = rng.uniform(-1, 1, (2, 2)).astype(np.float32)
        o, r, _term, trunc, _info = vec.step(act)
        for k, ref in enumerate(refs):
            ro, rr, _, rt, _ = ref.step(act[k])
            assert np.array_equal(o[k], ro) and r[k] == rr and trunc[k] == rt
    # the copies see the batch's state: measurements, positions
    copies = vec.unwrapped._synced()
    for k, ref in enumerate(refs):
        par = copies[k].par
        assert np.array_equal(par.state()[: 6 * par.n], ref.par.state()[: 6 * par.n])
        assert np.array_equal(par.measure.rsrp_dbm[:, 0], ref.par.measure.rsrp_dbm[:, 0], equal_nan=True)
        # the draws made inside the compiled step (env/pcg64.py) left the copy's stream where numpy's leaves it
        assert par.measure.rng.bit_generator.state == ref.par.measure.rng.bit_generator.state
    vec.close()


@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"overrides": [*FAST["overrides"], "road.wrap_distances=true", "link.inband_emission_db=-20"]},
        {"shadow_field": False, "reward_form": "utility", "max_drift_m": 30.0, "settle_steps": 3},
    ],
)
def test_batched_v3_step_equals_step_mover_bit_for_bit(kw: dict[str, Any]) -> None:
    """K copies through ``MoverBatch`` (field row, column, measurements, v3 entries compiled) against
    ``step_mover`` per copy, across autoresets."""
    kw = {"max_cycles": 12, "max_step_m": 15.0, **FAST, **kw}
    copies = 3
    ref = [SingleMoverEnvV3(**kw) for _ in range(copies)]
    bat = [SingleMoverEnvV3(**kw) for _ in range(copies)]
    batch = MoverBatch([e.par for e in bat])
    assert batch.v3 is not None
    for k in range(copies):
        ref[k].reset(seed=20 + k)
        bat[k].reset(seed=20 + k)
        batch.load(k)
    rng = np.random.default_rng(3)
    for _ in range(30):
        act = rng.uniform(-1.5, 1.5, (copies, 2)).astype(np.float32)
        obs, rew, done, info = batch.step(act)
        for k in range(copies):
            o, r, _term, trunc, inf = ref[k].step(act[k])
            assert np.array_equal(o, obs[k]) and o.dtype == obs.dtype
            assert r == rew[k] and trunc == done[k]
            assert np.array_equal([inf[key] for key in INFO_KEYS], info[k])
            assert np.array_equal(ref[k].par.measure.rsrp_dbm[:, 0], batch.v3.rsrp_dbm[k][:, 0], equal_nan=True)
            if trunc:
                ref[k].reset()
                bat[k].reset()
                batch.load(k)


def test_start_equals_a_window_of_updates() -> None:
    """``Measurements.start`` (one compiled pass) against ``window`` calls of ``update`` with the same inputs."""
    from cv2x_marl.env.measurement import Measurements

    env = _v3()
    env.reset(seed=3)
    p, _, rx = env.links.evaluate_rx(env.positions_m)
    n = env.n
    for seed in range(3):
        a = Measurements.start(rx, p, 10, 3.0, np.random.default_rng(seed))
        b = Measurements(
            10, 3.0, np.random.default_rng(seed), np.zeros((10, n, n)), np.zeros((10, n, n)), 0,
            np.full((n, n), np.nan), np.zeros((n, n), dtype=np.int64),
        )  # fmt: skip
        for _ in range(10):
            b.update(rx, p)
        assert np.array_equal(a.rsrp_dbm, b.rsrp_dbm, equal_nan=True) and np.array_equal(a.age, b.age)
        assert np.array_equal(a.power_mw, b.power_mw) and np.array_equal(a.count, b.count) and a.head == b.head
        assert a.rng.random() == b.rng.random()


def test_gymnasium_env_and_vector_env_draw_resets_from_the_start_pool() -> None:
    """``reset()`` without a seed of SingleMover-v3 (and the vector env's autoresets) start from the pool's
    seeds; the sequence follows the first seeded reset."""
    from cv2x_marl.env.seeds import training_pool

    pool = set(training_pool(3))
    env = gym.make("cv2x/SingleMover-v3", start_pool=3, max_cycles=3, **FAST)
    env.reset(seed=5)
    assert env.unwrapped.par.seed_used == 5
    used = []
    for _ in range(4):
        env.reset()
        used.append(env.unwrapped.par.seed_used)
    assert set(used) <= pool
    again = gym.make("cv2x/SingleMover-v3", start_pool=3, max_cycles=3, **FAST)
    again.reset(seed=5)
    assert [again.reset() and again.unwrapped.par.seed_used for _ in range(4)] == used
    vec = gym.make_vec(
        "cv2x/SingleMover-v3", num_envs=2, vectorization_mode="vector_entry_point", start_pool=3, max_cycles=2,
        autoreset_mode="SameStep", **FAST,
    )  # fmt: skip
    vec.reset(seed=0)
    for _ in range(2):
        vec.step(np.zeros((2, 2), dtype=np.float32))
    assert {e.par.seed_used for e in vec.unwrapped.envs} <= pool
    vec.close()


@pytest.mark.parametrize("version", [0, 2, 3])
def test_vector_env_pooled_resets_from_kept_starts_equal_the_envs_own_resets(version: int) -> None:
    """Pooled autoresets of the batched vector env copy kept rows (SingleMoverVectorEnv._pool_reset) instead of
    running each copy's reset: observations, rewards, infos and final observations equal independent
    ``SingleMover-v3`` envs resetting from the same pool, bit for bit, and once read (``get_attr``) the copies'
    env objects equal theirs (seed, positions, measurements, both generators)."""
    k_count, pool, cycles = 3, 4, 3
    vec = gym.make_vec(
        f"cv2x/SingleMover-v{version}", num_envs=k_count, vectorization_mode="vector_entry_point", start_pool=pool,
        max_cycles=cycles, autoreset_mode="SameStep", **FAST,
    )  # fmt: skip
    assert vec.unwrapped.batched
    refs = [gym.make(f"cv2x/SingleMover-v{version}", start_pool=pool, max_cycles=cycles, **FAST).unwrapped
            for _ in range(k_count)]  # fmt: skip
    obs, _ = vec.reset(seed=[21, 22, 23])
    for k, ref in enumerate(refs):
        assert np.array_equal(obs[k], ref.reset(seed=21 + k)[0])
    rng = np.random.default_rng(4)
    copied = 0
    for _ in range(16):
        act = rng.uniform(-1.2, 1.2, (k_count, 2))
        o, r, _term, trunc, info = vec.step(act)
        for k, ref in enumerate(refs):
            ro, rr, _, rt, ri = ref.step(act[k])
            assert r[k] == rr and trunc[k] == rt
            if rt:
                assert np.array_equal(info["final_obs"][k], ro)
                assert [info["final_info"][key][k] for key in INFO_KEYS] == [ri[key] for key in INFO_KEYS]
                ro, ri = ref.reset()
            assert np.array_equal(o[k], ro)
            assert [info[key][k] for key in INFO_KEYS] == [ri[key] for key in INFO_KEYS]
        copied += sum(p is not None for p in vec.unwrapped._pending)
    assert copied > 0  # kept starts were copied, not recomputed
    for k, par in enumerate(vec.get_attr("par")):
        ref = refs[k].par
        assert par.seed_used == ref.seed_used and par.t == ref.t
        assert np.array_equal(par.positions_m, ref.positions_m)
        if version == 3:
            assert np.array_equal(par.measure.rsrp_dbm, ref.measure.rsrp_dbm, equal_nan=True)
            assert np.array_equal(par.measure.power_mw, ref.measure.power_mw)
            assert par.measure.rng.bit_generator.state == ref.measure.rng.bit_generator.state
        assert par._np_random.bit_generator.state == ref._np_random.bit_generator.state
    vec.close()


def test_kept_starts_are_keyed_by_every_option() -> None:
    """Two vector envs whose options differ only in the measurement error share no kept start: the second
    one's pooled resets equal its own single envs', not the first one's rows."""
    from cv2x_marl.env.vector import KEPT_STARTS

    common = {"start_pool": 2, "max_cycles": 2, "autoreset_mode": "SameStep", **FAST}
    first = gym.make_vec("cv2x/SingleMover-v3", num_envs=2, vectorization_mode="vector_entry_point", **common)
    first.reset(seed=[1, 2])
    for _ in range(6):
        first.step(np.zeros((2, 2)))
    assert KEPT_STARTS
    second = gym.make_vec(
        "cv2x/SingleMover-v3", num_envs=2, vectorization_mode="vector_entry_point", rsrp_error_db=0.5, **common
    )
    refs = [SingleMoverEnvV3(start_pool=2, max_cycles=2, rsrp_error_db=0.5, **FAST) for _ in range(2)]
    second.reset(seed=[1, 2])
    for k, ref in enumerate(refs):
        ref.reset(seed=1 + k)
    for _ in range(6):
        o, _r, _t, _trunc, _i = second.step(np.zeros((2, 2)))
        for k, ref in enumerate(refs):
            ro, _, _, rt, _ = ref.step(np.zeros(2))
            if rt:
                ro, _ = ref.reset()
            assert np.array_equal(o[k], ro)
    first.close()
    second.close()
