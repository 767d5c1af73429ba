"""cv2x/Cooperative-v1, the coordination channel (env/turns.py) and the scripts that use it (policies/sequential.py):
the order of decisions, what an agent sees at its turn, the rewards, and the sequential best response against a
brute-force sequential search."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env import step as step_core
from cv2x_marl.env.defaults import COOPERATIVE_DEFAULTS, VERSION_DEFAULTS
from cv2x_marl.env.planning import reachable_set
from cv2x_marl.env.registry import env_version, make_aec_env, make_parallel_env
from cv2x_marl.env.tasks import TASKS, task_of_env
from cv2x_marl.env.turns import (
    SubframeAECEnv,
    announced_positions,
    decide_in_turns,
    decision_order,
    subframes,
    turn_observation,
    visible_mask,
)
from cv2x_marl.policies.registry import make_policy
from cv2x_marl.policies.sequential import SequentialBestResponsePolicy, SequentialSensingPolicy

pytestmark = pytest.mark.filterwarnings("ignore")

#: a 4-vehicle scene, 4 steps of 5 m (reach 20 m)
TINY = {"overrides": ["vehicles.n_vehicles=4", "road.length_m=250", "sim.warmup_subframes=200"], "max_cycles": 4}
#: the hand-built subframes of the 4 vehicles: 1 and 2 share subframe 2 (on other sub-channels)
SUBFRAMES = np.array([6, 2, 2, 9])
#: their order of decisions: by subframe, the tie 1, 2 by the lower index
ORDER = [1, 2, 0, 3]


def test_the_id_is_cooperative_v0_with_subframe_decisions_and_a_variant_of_cooperative() -> None:
    assert env_version("cv2x/Cooperative-v1") == "cooperative-v1"
    assert VERSION_DEFAULTS["cooperative-v1"] == {**COOPERATIVE_DEFAULTS, "decision_order": "subframe"}
    v0 = make_parallel_env("cv2x/Cooperative-v0", **TINY)
    v1 = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    assert v0.options.decision_order == "simultaneous" and v1.options.decision_order == "subframe"
    task = task_of_env("cv2x/Cooperative-v1")
    assert task is not None and task.name == "cooperative" and task.env_id == "cv2x/Cooperative-v1"
    assert task.heldout_seeds == TASKS["cooperative"].heldout_seeds and task.options == TASKS["cooperative"].options
    with pytest.raises(ValueError, match=r"decision_order='subframe'.*simultaneous unless mode is snapshot"):
        make_parallel_env("cv2x/Traffic-v0", decision_order="subframe")
    with pytest.raises(ValueError, match="SubframeAECEnv needs decision_order='subframe'"):
        SubframeAECEnv(v0)
    with pytest.raises(ValueError, match=r"'sequential-best-response' needs .*decision_order='subframe'"):
        make_policy("sequential-best-response", v0)


def test_order_is_the_sorted_subframes_ties_by_index_and_a_tie_hears_nothing() -> None:
    np.testing.assert_array_equal(decision_order(SUBFRAMES), ORDER)
    np.testing.assert_array_equal(decision_order(np.array([3, 1, 3, 0, 1])), [3, 1, 4, 0, 2])
    decided = np.array([False, True, True, False])  # 1 and 2 have decided
    np.testing.assert_array_equal(visible_mask(SUBFRAMES, decided, 2), [False, False, False, False])  # half duplex
    np.testing.assert_array_equal(visible_mask(SUBFRAMES, decided, 0), [False, True, True, False])
    np.testing.assert_array_equal(visible_mask(SUBFRAMES, decided, 3), [False, True, True, False])


def _tiny_aec(seed: int = 4) -> tuple[object, SubframeAECEnv]:
    """The AEC of the tiny scene at its start, with the hand-built subframes (sub-channels 0, 0, 1, 0)."""
    aec = make_aec_env("cv2x/Cooperative-v1", **TINY)
    aec.reset(seed=seed)
    inner = aec.env
    assert isinstance(inner, SubframeAECEnv)
    n_sub = inner.par.config.sps.n_subchannels
    inner.par.resource = SUBFRAMES * n_sub + np.array([0, 0, 1, 0])
    inner._start_period()  # a period starts with the order of these resources
    return aec, inner


def _relative_neighbours(obs: np.ndarray, par: object) -> np.ndarray:
    """[K, 2] the v0 block's neighbour positions relative to the agent (m), sorted (the observation's entries)."""
    rel = par.layout.neighbours(obs[None])[0, :, :2].astype(np.float64) * par.layout.scale_m
    return rel[np.lexsort(rel.T[::-1])]


def test_second_agent_sees_the_first_agents_new_position_a_tie_its_old_one() -> None:
    aec, inner = _tiny_aec()
    par = inner.par
    start = par.positions_m.copy()
    assert inner.order == [f"vehicle_{i}" for i in ORDER]
    # the first agent (vehicle 1, first subframe) observes what the parallel env shows: nobody has moved
    assert aec.agent_selection == "vehicle_1"
    par_obs = par.observations()
    np.testing.assert_array_equal(aec.observe("vehicle_1"), par_obs["vehicle_1"])
    moves = {1: np.array([1.0, 0.0]), 2: np.array([0.0, -1.0]), 0: np.array([-1.0, 1.0]), 3: np.array([0.5, 0.5])}
    expected_new = start.copy()
    for i in ORDER:
        agent = f"vehicle_{i}"
        assert aec.agent_selection == agent
        heard = start.copy()
        for j in ORDER[: ORDER.index(i)]:
            if SUBFRAMES[j] < SUBFRAMES[i]:
                heard[j] = expected_new[j]
        # the agent's observation: the neighbours where it has heard them (new positions of earlier subframes)
        want = heard[np.arange(4) != i] - start[i]
        np.testing.assert_allclose(
            _relative_neighbours(aec.observe(agent), par), want[np.lexsort(want.T[::-1])], atol=1e-4
        )
        aec.step(moves[i].astype(np.float32))
        expected_new[i] = start[i] + 5.0 * moves[i]
    # vehicle 2 (the tie) saw vehicle 1 where it started; vehicle 0 saw it 5 m further in x
    np.testing.assert_allclose(par.positions_m, expected_new, atol=1e-12)
    assert par.t == 1


def test_observation_at_a_turn_is_the_parallel_observation_at_the_heard_positions() -> None:
    """The turn observation with the heard positions equals a parallel env's observation with the vehicles there."""
    aec, inner = _tiny_aec()
    par = inner.par
    aec.step(np.array([1.0, 0.0], np.float32))  # vehicle 1
    aec.step(np.array([0.0, -1.0], np.float32))  # vehicle 2
    heard = inner.heard_positions("vehicle_0")
    other = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    other.reset(seed=4)
    other.positions_m = heard.copy()
    other.link_p, other.target = other.dynamics.links()  # its geometry at the heard positions
    other.resource = par.resource.copy()
    v0 = par.layout.v0_size
    np.testing.assert_array_equal(aec.observe("vehicle_0")[:v0], other.build()[0, :v0])


def test_rewards_are_the_parallel_envs_team_rewards_for_the_same_actions() -> None:
    rng = np.random.default_rng(3)
    aec = make_aec_env("cv2x/Cooperative-v1", **TINY)
    par = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    aec.reset(seed=9)
    par.reset(seed=9)
    while par.agents:
        acts = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in par.agents}
        _, rew, *_ = par.step(acts)
        for _ in range(4):
            aec.step(acts[aec.agent_selection])
        got = {a: aec.rewards[a] for a in par.possible_agents}
        assert got == rew and len(set(rew.values())) == 1  # the team's reward, one value for every agent
    np.testing.assert_array_equal(aec.unwrapped.positions_m, par.positions_m)


def test_announced_positions_follow_the_envs_move_rule() -> None:
    env = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    env.reset(seed=2)
    act = np.array([[2.0, 0.0], [0.3, -0.4], [1.0, 1.0], [0.0, 0.0]])
    got = announced_positions(env, act, np.array([True, True, False, False]))
    new, _, _ = step_core.move_vehicles(
        act, env.positions_m, env.start_m, env.positions_m, env.step_scale_m, env.max_step_m, False, False,
        env.drift_m, env.roi, env.box_m,
    )  # fmt: skip
    np.testing.assert_array_equal(got[:2], new[:2])
    np.testing.assert_array_equal(got[2:], env.positions_m[2:])
    np.testing.assert_allclose(got[0] - env.positions_m[0], [5.0, 0.0])  # clipped to one step


def _utilities(env: object, i: int, heard_m: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """[M] vehicle ``i``'s eq. 12 utility at each candidate [M, 2], the others at ``heard_m``: the env's full link
    evaluation (every pair), not the mover row the policy searches."""
    out = np.empty(len(cand))
    pos = heard_m.copy()
    for k, c in enumerate(cand):
        pos[i] = c
        p, _ = env.links.evaluate(pos)
        out[k] = step_core.utilities(p, env.links.target, env.p_min, False)[0][i]
    return out


def _grid(env: object, i: int, center_m: np.ndarray, half_m: float, pitch_m: float) -> np.ndarray:
    """[M, 2] a ``pitch_m`` grid of the square ``center_m +- half_m`` inside vehicle ``i``'s reachable set."""
    ax = np.arange(-half_m, half_m + pitch_m / 2, pitch_m)
    cand = (center_m + np.stack(np.meshgrid(ax, ax, indexing="ij"), -1).reshape(-1, 2)).astype(np.float64)
    return cand[reachable_set(env, i).contains(cand)]


@pytest.mark.parametrize("seed", [4, 5])
def test_sequential_best_response_equals_a_brute_force_sequential_search(seed: int) -> None:
    """The first period: each vehicle in subframe order takes its best reachable position for its own utility, the
    earlier subframes' vehicles at their announced moves. The brute force, every candidate through the full link
    evaluation: no point of a 0.5 m grid over the reachable set (20 m each way) is better than the policy's target,
    and no point within 5 cm of it on a 5 mm grid is better (the policy refines its grid's best points to 2.5 mm)."""
    env = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    obs, _ = env.reset(seed=seed)
    env.resource = SUBFRAMES * env.config.sps.n_subchannels + np.array([0, 0, 1, 0])
    pol = SequentialBestResponsePolicy(env, grid_m=0.5, refine=16)
    acts = pol.act(obs)
    assert pol.targets_m is not None
    act = np.zeros((4, 2))
    decided = np.zeros(4, dtype=bool)
    moved = 0
    for i in ORDER:
        heard = announced_positions(env, act, visible_mask(SUBFRAMES, decided, i))
        target = pol.targets_m[i]
        got = _utilities(env, i, heard, target[None])[0]
        coarse = _utilities(env, i, heard, _grid(env, i, env.positions_m[i], 20.0, 0.5))
        fine = _utilities(env, i, heard, _grid(env, i, target, 0.05, 0.005))
        assert got >= coarse.max() - 1e-12 and got >= fine.max() - 1e-9, (i, got, coarse.max(), fine.max())
        act[i] = acts[f"vehicle_{i}"]
        decided[i] = True
        np.testing.assert_allclose(act[i], np.clip((target - env.positions_m[i]) / 5.0, -1, 1), atol=1e-6)
        moved += int(np.any(act[i] != 0))
    assert moved >= 1


def test_the_policy_through_the_aec_turns_makes_the_parallel_routes_moves() -> None:
    """turn_action with the AEC's heard positions (one agent at a time) and act (the turns made by the policy) move
    the vehicles alike over an episode."""
    routes = []
    for route in ("aec", "parallel"):
        if route == "aec":
            aec = make_aec_env("cv2x/Cooperative-v1", **TINY)
            aec.reset(seed=5)
            inner, par = aec.env, aec.unwrapped
            pol = SequentialBestResponsePolicy(par)
            for agent in aec.agent_iter():
                _, _, term, trunc, _ = aec.last()
                i = par.agent_index[agent]
                aec.step(None if term or trunc else pol.turn_action(i, inner.heard_positions(agent)))
        else:
            par = make_parallel_env("cv2x/Cooperative-v1", **TINY)
            obs, _ = par.reset(seed=5)
            pol = SequentialBestResponsePolicy(par)
            while par.agents:
                obs, *_ = par.step(pol.act(obs))
        routes.append(np.array(par.tracks))
    np.testing.assert_array_equal(routes[0], routes[1])
    assert not np.array_equal(routes[0][0], routes[0][-1])


def test_first_turn_observation_is_bit_identical_to_the_parallel_one() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        env = make_parallel_env("cv2x/Cooperative-v1", **TINY)
        obs, _ = env.reset(seed=11)
    for agent, i in env.agent_index.items():
        np.testing.assert_array_equal(turn_observation(env, i, env.positions_m), obs[agent])


def test_sequential_sensing_without_announcements_is_the_sensing_planner() -> None:
    """Nobody heard (``hear=False``, or every vehicle in one subframe): sequential-sensing makes the sensing planner's
    moves bit for bit (the same estimate, search and re-plans), so the benchmark's ``sensing`` rows are its ablation."""
    kw = {**TINY, "max_cycles": 12}
    tracks = {}
    for name in ("sensing", "deaf", "one-subframe"):
        env = make_parallel_env("cv2x/Cooperative-v1", **kw)
        obs, _ = env.reset(seed=5)
        if name == "one-subframe":
            env.resource = np.array([0, 1, 0, 1])  # subframe 0, sub-channels 0 / 1: half duplex, nobody hears
        pol = make_policy("sensing", env) if name == "sensing" else SequentialSensingPolicy(env, hear=name != "deaf")
        pol.reset(5)
        while env.agents:
            obs, *_ = env.step(pol.act(obs))
        tracks[name] = np.array(env.tracks)
    np.testing.assert_array_equal(tracks["deaf"], tracks["sensing"])
    np.testing.assert_array_equal(tracks["one-subframe"], tracks["sensing"])
    assert not np.array_equal(tracks["sensing"][0], tracks["sensing"][-1])


def test_decide_in_turns_gives_the_aec_observations_and_moves() -> None:
    """A batched actor through ``decide_in_turns`` on the parallel env sees, subframe by subframe, what each agent
    observes at its AEC turn (bit for bit) and makes the same episode."""

    def actor(obs: np.ndarray) -> np.ndarray:  # any deterministic function of the observation
        return np.tanh(obs[..., :2] * 3.0 + obs[..., 7:9])

    aec = make_aec_env("cv2x/Cooperative-v1", **TINY)
    aec.reset(seed=5)
    seen_aec: dict[tuple[int, str], np.ndarray] = {}
    for agent in aec.agent_iter():
        obs, _, term, trunc, _ = aec.last()
        if term or trunc:
            aec.step(None)
            continue
        seen_aec[(aec.unwrapped.t, agent)] = obs
        aec.step(actor(obs).astype(np.float32))
    par = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    par.reset(seed=5)
    calls = 0
    while par.agents:
        act, obs = decide_in_turns(par, lambda rows, o: actor(o))
        for a, i in par.agent_index.items():
            np.testing.assert_array_equal(obs[i], seen_aec[(par.t, a)])
        calls += len(np.unique(subframes(par)))
        par.step({a: act[i].astype(np.float32) for a, i in par.agent_index.items()})
    np.testing.assert_array_equal(np.array(par.tracks), np.array(aec.unwrapped.tracks))
    assert calls == 4 * len(np.unique(subframes(par))) and not np.array_equal(par.tracks[0], par.tracks[-1])


def _aec_episode(seed: int) -> np.ndarray:
    """Every observation at every turn and every reward of one AEC episode with fixed random actions."""
    rng = np.random.default_rng(1)
    aec = make_aec_env("cv2x/Cooperative-v1", **TINY)
    aec.reset(seed=seed)
    out = []
    for _ in aec.agent_iter():
        obs, rew, term, trunc, _ = aec.last()
        out += [obs, np.array([rew])]
        aec.step(None if term or trunc else rng.uniform(-1, 1, 2).astype(np.float32))
    return np.concatenate(out)


def test_aec_same_seed_same_episode_other_seed_other() -> None:
    a, b, c = _aec_episode(5), _aec_episode(5), _aec_episode(6)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_a_bad_action_is_refused_at_its_turn_naming_the_agent() -> None:
    aec = make_aec_env("cv2x/Cooperative-v1", **TINY)
    aec.reset(seed=5)
    first = aec.agent_selection
    with pytest.raises(ValueError, match=rf"action of {first} is not finite"):
        aec.step(np.array([np.nan, 0.0], np.float32))
    with pytest.raises(ValueError, match=rf"action of {first} must have shape \(2,\), got shape \(3,\)"):
        aec.step(np.zeros(3, np.float32))


def test_team_move_is_team_moves_single_move_of_one_vehicle() -> None:
    """``team_move`` with the vehicles where they are equals ``team_moves``' simultaneous row of that vehicle."""
    from cv2x_marl.env.team_search import team_move, team_moves

    env = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    env.reset(seed=5)
    every = team_moves(env)
    for i in range(env.n):
        np.testing.assert_array_equal(team_move(env, i, env.positions_m), every[i])
    assert not np.array_equal(every, env.positions_m)


def test_sequential_team_without_announcements_is_all_at_once_team_re_planning() -> None:
    """``sequential-team`` with ``hear=False`` moves every vehicle towards ``team_moves``' simultaneous targets (the
    all-at-once team-aware re-planning of benchmarks/cooperative_gap.py), with it the subframe order changes them."""
    from cv2x_marl.env.team_search import team_moves

    env = make_parallel_env("cv2x/Cooperative-v1", **TINY)
    obs, _ = env.reset(seed=5)
    env.resource = SUBFRAMES * env.config.sps.n_subchannels + np.array([0, 0, 1, 0])
    deaf = make_policy("sequential-team", env)
    deaf.hear = False
    want = np.clip((team_moves(env) - env.positions_m) / env.max_step_m, -1, 1)
    got = deaf.act(obs)
    np.testing.assert_array_equal(np.array([got[a] for a in env.possible_agents]), want.astype(np.float32))


def test_a_learned_policy_on_cooperative_v1_acts_at_its_turns() -> None:
    """``make_policy("ppo:PATH", env)`` on a turn-order env wraps the model in ``InTurns``: through the parallel API
    it makes the episode the same model makes acting agent by agent at its AEC turns (bit for bit); on
    Cooperative-v0 the model is not wrapped."""
    from cv2x_marl.policies.sequential import InTurns

    path = "agents/models/cooperative_seed0/model.pt"
    kw = {"overrides": ["sim.warmup_subframes=200"], "max_cycles": 4}  # the task's 21 vehicles: the model's size
    par = make_parallel_env("cv2x/Cooperative-v1", **kw)
    policy = make_policy(f"ppo:{path}", par)
    assert isinstance(policy, InTurns)
    assert not isinstance(make_policy(f"ppo:{path}", make_parallel_env("cv2x/Cooperative-v0")), InTurns)
    obs, _ = par.reset(seed=5)
    while par.agents:
        obs, *_ = par.step(policy.act(obs))
    aec = make_aec_env("cv2x/Cooperative-v1", **kw)
    aec.reset(seed=5)
    inner = policy.policy
    for agent in aec.agent_iter():
        o, _, term, trunc, _ = aec.last()
        aec.step(None if term or trunc else inner.act({agent: o})[agent])
    np.testing.assert_array_equal(np.array(par.tracks), np.array(aec.unwrapped.tracks))
    assert not np.array_equal(par.tracks[0], par.tracks[-1])
