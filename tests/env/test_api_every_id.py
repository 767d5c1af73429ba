"""The framework API checks, once, over every registered env id: PettingZoo's parallel and AEC API tests and its
seed test for each id in PettingZoo's registries, Gymnasium's and SB3's env checkers for each id in Gymnasium's,
and for every id the same episode twice from the same seed (and another from another seed)."""

from __future__ import annotations

import warnings
from typing import Any

import gymnasium
import numpy as np
import pettingzoo
import pytest
from pettingzoo.test import api_test, parallel_api_test
from pettingzoo.test.seed_test import parallel_seed_test
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env import MobilityEnv
from cv2x_marl.env.registry import ENV_IDS, FACTORIES, SPEC, make_parallel_env

pytestmark = pytest.mark.filterwarnings("ignore")

#: a small, fast scene for the API tests (as the per-version tests use)
FAST: dict[str, Any] = {"overrides": ["sim.warmup_subframes=200"]}
PETTINGZOO_IDS = [i for i in ENV_IDS if i in pettingzoo.parallel_registry]
GYMNASIUM_IDS = [i for i in ENV_IDS if i in gymnasium.registry]


def test_every_id_is_registered_in_a_framework_and_aec_with_parallel() -> None:
    assert set(PETTINGZOO_IDS) | set(GYMNASIUM_IDS) == set(ENV_IDS)
    assert all(i in pettingzoo.aec_registry for i in PETTINGZOO_IDS)
    assert set(GYMNASIUM_IDS) == {i for i in ENV_IDS if "SingleMover" in i or "Traffic" in i or "Resource" in i}


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_every_route_builds_the_same_env(env_id: str) -> None:
    """``make_parallel_env``, ``pettingzoo.make``, the factories and ``gymnasium.make`` of an id build one class with
    the id's metadata name and options (its row of the spec table)."""
    name = "cv2x_" + env_id.split("/")[1].lower().replace("-", "_")
    ours = make_parallel_env(env_id, max_cycles=3, **FAST)
    assert type(ours) is MobilityEnv and ours.metadata["name"] == SPEC[env_id].name == name
    built = []
    if env_id in PETTINGZOO_IDS:
        built.append(pettingzoo.make("parallel", env_id, max_cycles=3, **FAST))
        built.append(FACTORIES[f"parallel_env{SPEC[env_id].factory}"](max_cycles=3, **FAST))
    if env_id in GYMNASIUM_IDS:  # vehicle 0's view: the parallel env of the id with movers [0]
        single = gymnasium.make(env_id, max_cycles=3, **FAST).unwrapped
        assert single.env_id == env_id and np.flatnonzero(single.par.mover_mask).tolist() == [0]
        assert single.par.options == make_parallel_env(env_id, max_cycles=3, movers=[0], **FAST).options
        built.append(single.par)
    for env in built:
        assert type(env) is MobilityEnv and env.metadata["name"] == name
    for env in built[:2] if env_id in PETTINGZOO_IDS else []:
        assert env.options == ours.options


@pytest.mark.parametrize("env_id", PETTINGZOO_IDS)
def test_pettingzoo_parallel_aec_and_seed_tests(env_id: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        parallel_api_test(pettingzoo.make("parallel", env_id, max_cycles=5, **FAST), num_cycles=10)
        api_test(pettingzoo.make("aec", env_id, max_cycles=3, **FAST), num_cycles=6)
        parallel_seed_test(lambda: pettingzoo.make("parallel", env_id, max_cycles=5, **FAST), num_cycles=8)


@pytest.mark.parametrize("env_id", GYMNASIUM_IDS)
def test_gymnasium_and_sb3_env_checkers(env_id: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = gymnasium.make(env_id, max_cycles=6, **FAST)
        gymnasium.utils.env_checker.check_env(env.unwrapped, skip_render_check=True)
        sb3_check_env(env.unwrapped, warn=True)
        spec = gymnasium.spec(env_id)
        if spec.vector_entry_point is not None:  # the batched copies: spaces of K envs, a reset and a step
            vec = gymnasium.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point", max_cycles=4, **FAST)
            obs, _ = vec.reset(seed=1)
            assert obs.shape == (3, *env.observation_space.shape) and vec.action_space.shape == (3, 2)
            obs, rew, term, trunc, _ = vec.step(np.zeros((3, 2), np.float32))
            assert obs.shape[0] == rew.shape[0] == term.shape[0] == trunc.shape[0] == 3
            vec.close()


def _episode(env_id: str, seed: int) -> np.ndarray:
    env = make_parallel_env(env_id, max_cycles=4, **FAST)
    rng = np.random.default_rng(7)
    obs, _ = env.reset(seed=seed)
    out = [np.stack([obs[a] for a in env.possible_agents]).ravel()]
    space = env.action_space(env.possible_agents[0])
    while env.agents:
        if isinstance(space, gymnasium.spaces.Discrete):  # cv2x/Resource-v0: list entries (past a list: the draw)
            act = {a: np.int64(rng.integers(space.n)) for a in env.agents}
        else:
            act = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}
        obs, rew, *_ = env.step(act)
        out.append(np.stack([obs[a] for a in env.possible_agents]).ravel())
        out.append(np.array([rew[a] for a in env.possible_agents]))
    return np.concatenate(out)


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_same_seed_same_episode_other_seed_other(env_id: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a, b, c = _episode(env_id, 5), _episode(env_id, 5), _episode(env_id, 6)
    np.testing.assert_array_equal(a, b)
    assert a.shape == c.shape and not np.array_equal(a, c)
