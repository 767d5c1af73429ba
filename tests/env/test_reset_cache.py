"""The reset cache and the training start pool (issue 10, throughput): a cached start is the
computed start, bit for bit; the pool draws every training episode from N seeds."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.env import starts
from cv2x_marl.env.registry import make_parallel_env

KW = {
    "max_cycles": 12,
    "action_mode": "plan_residual",
    "replan_every": 5,
    "overrides": ["sim.warmup_subframes=200"],
}


def _episode(env, seed: int) -> list[np.ndarray]:  # type: ignore[no-untyped-def]
    obs, _ = env.reset(seed=seed)
    trace = [obs["vehicle_0"]]
    rng = np.random.default_rng(seed)
    for _ in range(12):
        ob, reward, _, info = env.step_mover(rng.uniform(-1, 1, 2).astype(np.float32))
        trace += [ob, np.array([reward, info["utility"], info["prr"]])]
    return trace


def test_cached_starts_are_bit_identical_to_computed_ones() -> None:
    starts.START_CACHE.clear()
    plain = make_parallel_env("cv2x/SingleMover-v2", **KW)
    cached = make_parallel_env("cv2x/SingleMover-v2", reset_cache=4, **KW)
    for seed in (3, 4, 3, 4):  # the second visit of each seed is served from the cache
        a, b = _episode(plain, seed), _episode(cached, seed)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert len(starts.START_CACHE) == 2
    np.testing.assert_array_equal(cached.plan_m, plain.plan_m)


def test_the_cache_is_bounded_and_keyed_by_what_the_start_depends_on() -> None:
    starts.START_CACHE.clear()
    env = make_parallel_env("cv2x/SingleMover-v2", reset_cache=2, **KW)
    for seed in range(5):
        env.reset(seed=seed)
    assert len(starts.START_CACHE) == 2  # least recently used starts dropped
    other = make_parallel_env("cv2x/SingleMover-v2", reset_cache=2, **{**KW, "max_cycles": 30})
    other.reset(seed=4)  # another reach: another plan, not the cached one
    fresh = make_parallel_env("cv2x/SingleMover-v2", **{**KW, "max_cycles": 30})
    fresh.reset(seed=4)
    np.testing.assert_array_equal(other.plan_m, fresh.plan_m)


@pytest.mark.parametrize("value", [-1, 1.5, True, "8"])
def test_bad_reset_cache_is_refused_by_name(value: object) -> None:
    with pytest.raises(ValueError, match="invalid env argument reset_cache="):
        make_parallel_env("cv2x/SingleMover-v2", reset_cache=value, **KW)
    for name in ("reset_cache", "start_pool"):  # traffic mode on SUMO lockstep: libsumo cannot be copied
        with pytest.raises(ValueError, match=rf"invalid env argument {name}=4.*libsumo runs one simulation"):
            make_parallel_env("cv2x/Mobility-v0", mode="traffic", preset="sumo-grid", **{name: 4})


def _traffic_episode(env, seed: int | None, steps: int = 6) -> list[np.ndarray]:  # type: ignore[no-untyped-def]
    """A Gymnasium Traffic-v0 episode's observations, rewards and infos (``seed=None``: a pooled reset)."""
    ob, info = env.reset(seed=seed)
    trace = [ob, np.array(list(info.values()))]
    rng = np.random.default_rng(1)
    for _ in range(steps):
        ob, reward, _, _, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        trace += [ob, np.array([reward, *info.values()])]
    return trace


def _same(a: list[np.ndarray], b: list[np.ndarray]) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_traffic_cached_and_pooled_starts_are_bit_identical_to_fresh_ones() -> None:
    """Traffic mode keeps the simulator after its warm-up and runs each episode on a copy: a cached reset and a
    pooled one give the fresh episode of the same seed, bit for bit, however often the start is reused."""
    import gymnasium as gym

    from cv2x_marl.env.seeds import TRAIN_SEEDS

    starts.START_CACHE.clear()
    kw = {"max_cycles": 6, "overrides": ["road.lanes_per_direction=2"]}
    fresh = gym.make("cv2x/Traffic-v0", **kw)
    cached = gym.make("cv2x/Traffic-v0", reset_cache=2, **kw)
    for seed in (3, 4, 3, 3, 4):  # the later visits run from the cache, the start untouched by earlier episodes
        assert _same(_traffic_episode(fresh, seed), _traffic_episode(cached, seed))
    assert len(starts.START_CACHE) == 2
    # the start pool: plain resets draw training seeds, each episode that seed's fresh one
    starts.START_CACHE.clear()
    pooled = gym.make("cv2x/Traffic-v0", start_pool=2, **kw)
    pooled.reset(seed=5)
    used = []
    for _ in range(4):
        trace = _traffic_episode(pooled, None)
        used.append(pooled.unwrapped.par.seed_used)
        assert _same(trace, _traffic_episode(fresh, used[-1]))
    assert set(used) == set(TRAIN_SEEDS[:2]) and len(starts.START_CACHE) == 2
    # the option through gymnasium.make_vec and pettingzoo.make: the autoresets draw from the pool
    vec = gym.make_vec("cv2x/Traffic-v0", num_envs=2, start_pool=2, max_cycles=2)
    vec.reset(seed=7)
    for _ in range(4):
        vec.step(np.zeros((2, 2), np.float32))
    assert {e.unwrapped.par.seed_used for e in vec.envs} <= set(TRAIN_SEEDS[:2])
    # Traffic-v1 (its measurements start from the kept simulator too): cached == fresh
    starts.START_CACHE.clear()
    fresh_v1 = gym.make("cv2x/Traffic-v1", **kw)
    cached_v1 = gym.make("cv2x/Traffic-v1", reset_cache=1, **kw)
    for seed in (3, 3):
        assert _same(_traffic_episode(fresh_v1, seed), _traffic_episode(cached_v1, seed))
    import pettingzoo

    par = pettingzoo.make("parallel", "cv2x/Traffic-v0", start_pool=2, movers=None, max_cycles=2)
    par.reset(seed=7)
    par.reset()
    assert par.seed_used in TRAIN_SEEDS[:2]


def test_start_pool_draws_episodes_from_n_seeds() -> None:
    from cv2x_marl.rl.train import TrainConfig, make_vec_env
    from cv2x_marl.rng import derive_seeds

    starts.START_CACHE.clear()
    cfg = TrainConfig(env_id="cv2x/SingleMover-v2", copies=2, env={**KW, "max_cycles": 2}, start_pool=3)
    vec = make_vec_env(cfg)
    vec.seed(7)
    vec.reset()
    seen = set()
    for _ in range(40):  # 20 episodes per copy
        vec.step(np.zeros((2, 2), np.float32))
        seen |= {env.seed_used for env in vec.envs}
    assert seen == set(derive_seeds(7, 3))  # the pool of PPO's seed, every member used
    assert len(starts.START_CACHE) == 3
    with pytest.raises(Exception, match="start_pool must be an integer >= 1"):
        TrainConfig(start_pool=0)


def test_start_pool_draws_training_seeds_and_keeps_their_starts() -> None:
    from cv2x_marl.env import tasks

    starts.START_CACHE.clear()
    env = make_parallel_env("cv2x/SingleMover-v3", start_pool=3, max_cycles=5)
    env.reset(seed=11)  # an explicit seed still runs that episode
    assert env.seed_used == 11
    rng = np.random.default_rng(11)  # the env's generator after reset(seed=11)
    expected = [tasks.TRAIN_SEEDS[int(rng.integers(3))] for _ in range(6)]
    used = []
    for _ in range(6):
        env.reset()
        used.append(env.seed_used)
    assert used == expected and set(used) <= set(tasks.TRAIN_SEEDS[:3])
    held = {s for h in tasks.HELDOUT_SEEDS.values() for s in h}
    assert not set(used) & held
    # the cache holds max(reset_cache, start_pool) = 3 starts: the pool's three, seed 11 dropped (least recent)
    assert len(set(used)) == 3 and len(starts.START_CACHE) == 3
    # a pooled start equals the same seed computed afresh, observation and rewards included
    fresh = make_parallel_env("cv2x/SingleMover-v3", max_cycles=5)
    o1, _ = fresh.reset(seed=used[-1])
    o2 = env.observations()
    np.testing.assert_array_equal(o1["vehicle_0"], o2["vehicle_0"])
    act = {a: np.array([0.3, -0.2], dtype=np.float32) for a in env.agents}
    r1 = fresh.step(act)[1]
    r2 = env.step(act)[1]
    assert r1 == r2


def test_start_pool_refused_outside_its_range() -> None:
    for bad in (-1, 4097, 1.5):
        with pytest.raises(ValueError, match="start_pool"):
            make_parallel_env("cv2x/SingleMover-v3", start_pool=bad)
