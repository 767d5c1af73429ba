"""The Cooperative ceiling (env/team_search.py, sim/kernels/team.py) and the policies that use it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cv2x_marl.env.planning import reachable_set
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.team_search import TeamObjective, _grid_in, team_moves, team_objective, team_search
from cv2x_marl.policies.optimum import BestResponsePolicy, OptimumPolicy, best_response_targets
from cv2x_marl.policies.registry import SCRIPTED, make_policy
from cv2x_marl.rng import env_stream
from cv2x_marl.sim.ground_truth import SnapshotLinks
from cv2x_marl.sim.shadow_field import ShadowField
from cv2x_marl.utility import utility_log


def _with_field(env, seed: int) -> None:
    snap = env.links.snapshot
    field = ShadowField.draw(
        env.config, snap.positions_m, snap.shadowing_db, snap.los, env_stream(seed, "shadow_field")
    )
    env.links = SnapshotLinks(env.config, snap, env.truth_los, field=field)


def _numpy_j(env, positions: np.ndarray) -> float:
    """J from the numpy reference links and eq. 12's numpy reference, independent of the search's kernels."""
    ref = SnapshotLinks(env.config, env.links.snapshot, env.truth_los, compiled=False, field=env.links.field)
    p = ref.success(positions)
    target = ref.target
    u = utility_log(p, target, env.p_min) / np.maximum(target.sum(axis=1), 1)
    return float(u.mean())


@pytest.fixture(scope="module")
def team_env():
    env = make_parallel_env(
        "cv2x/Mobility-v2", reward="team", normalise_reward=True, overrides=["link.inband_emission_db=-25"]
    )
    env.reset(seed=3)
    return env


@pytest.mark.parametrize("field", [False, True])
def test_incremental_objective_equals_full_evaluations(team_env, field: bool) -> None:
    """One vehicle at many candidates, incremental: J of a full evaluation with it there (1e-12: only the
    order of the additions differs)."""
    env = team_env
    if field:
        env = make_parallel_env("cv2x/Mobility-v2", reward="team", normalise_reward=True)
        env.reset(seed=4)
        _with_field(env, 4)
    obj = TeamObjective(env.links, env.p_min)
    rng = np.random.default_rng(0)
    pos = env.positions_m + rng.uniform(-30.0, 30.0, size=env.positions_m.shape)
    assert obj.set_positions(pos) == pytest.approx(team_objective(env.links, pos, env.p_min), abs=1e-12)
    for v in (0, 7, env.n - 1):
        cand = pos[v] + rng.uniform(-150.0, 150.0, size=(15, 2))
        got = obj.move_values(v, cand)
        want = []
        for c in cand:
            q = pos.copy()
            q[v] = c
            want.append(team_objective(env.links, q, env.p_min))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
        assert np.ptp(got) > 1e-3  # the candidates matter


def _three_vehicle_scene(seed: int, field: bool):
    """Three vehicles within about 100 m: 0 and 1 share a resource (each interferes with the other's
    packets at 2), 2 is in another subframe; snapshot shadowing N(0, 4 dB); reach 10 m (2 steps of 5 m)."""
    env = make_parallel_env(
        "cv2x/Mobility-v2", reward="team", normalise_reward=True, overrides=["vehicles.n_vehicles=3"],
        max_cycles=2, max_step_m=5.0,
    )  # fmt: skip
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    pos = np.full((3, 2), 100.0) + rng.uniform(-60.0, 60.0, size=(3, 2))
    s0 = np.triu(rng.normal(0.0, 4.0, size=(3, 3)), 1)
    s0 = s0 + s0.T
    snap = dataclasses.replace(
        env.links.snapshot, positions_m=pos, slot=np.array([0, 0, 1]), subchannel=np.array([0, 0, 0]), shadowing_db=s0
    )
    f = ShadowField.draw(env.config, pos, s0, snap.los, env_stream(seed, "shadow_field")) if field else None
    env.links = SnapshotLinks(env.config, snap, env.truth_los, field=f)
    env.positions_m = pos.copy()
    env.start_m = pos.copy()
    return env


@pytest.mark.parametrize(("seed", "field"), [(0, False), (1, True), (2, False), (3, True)])
def test_three_vehicles_match_a_joint_brute_force(seed: int, field: bool) -> None:
    """The search on 5 m then 1 m grids against every joint position of the 5 m grids (25^3, full
    evaluations): at least the brute force's J less 1e-4 relative (the search's 1 m refinement may beat
    the 5 m lattice; a point of the lattice it misses would cost far more than 1e-4).

    Known limit, not hidden: with this construction seeds 4 and 7 have their optimum where all three
    vehicles must move at once (single and pair moves gain nothing from the start): coordinate search
    with pair moves stays at the start there, the brute force reaches J = -1.50 against -2.30.
    """
    env = _three_vehicle_scene(seed, field)
    grids = [_grid_in(reachable_set(env, i), env.positions_m[i], np.inf, 5.0) for i in range(3)]
    assert [g.shape[0] for g in grids] == [25, 25, 25]
    best = -np.inf
    for a in grids[0]:
        for b in grids[1]:
            for c in grids[2]:
                best = max(best, team_objective(env.links, np.stack((a, b, c)), env.p_min))
    res = team_search(env, grids_m=(5.0, 1.0), n_orders=2, pair_points=25)
    assert res.objective >= best - 1e-4 * abs(best), (res.objective, best)
    assert res.objective > team_objective(env.links, env.positions_m, env.p_min) or seed == 0  # 0: nothing to gain
    assert np.all(np.stack([reachable_set(env, i).contains(res.positions_m[i][None])[0] for i in range(3)]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_never_below_best_response_and_the_objective_is_exact(seed: int) -> None:
    env = make_parallel_env(
        "cv2x/Mobility-v2", reward="team", normalise_reward=True, overrides=["vehicles.n_vehicles=8"], max_cycles=10,
    )  # fmt: skip
    env.reset(seed=seed)
    if seed == 2:
        _with_field(env, seed)
    br = best_response_targets(env, list(range(env.n)), 2, 10.0, 16)
    j_br = team_objective(env.links, br, env.p_min)
    res = team_search(env, [env.positions_m, br])
    assert res.start_objectives[1] == pytest.approx(j_br, abs=1e-12)
    assert res.objective >= j_br - 1e-12
    assert res.objective == pytest.approx(_numpy_j(env, res.positions_m), rel=1e-9, abs=1e-12)
    assert res.objective == max(res.end_objectives) or res.objective == pytest.approx(
        max(res.end_objectives), abs=1e-12
    )
    for i in range(env.n):
        assert reachable_set(env, i).contains(res.positions_m[i][None])[0]


def test_optimum_policy_uses_the_team_search_only_for_the_team_reward() -> None:
    kw = dict(overrides=["vehicles.n_vehicles=6"], max_cycles=6)
    team = make_parallel_env("cv2x/Mobility-v2", reward="team", normalise_reward=True, **kw)
    solo = make_parallel_env("cv2x/Mobility-v2", **kw)
    for env in (team, solo):
        env.reset(seed=1)
    movers = list(range(team.n))
    br = best_response_targets(solo, movers, 2, 10.0, 16)
    # individual reward: best response, as before (bit for bit)
    pol = OptimumPolicy(solo)
    assert not pol.team
    obs = {a: None for a in solo.agents}
    pol.act(obs)
    assert np.array_equal(pol.targets_m, br)
    # team reward, every vehicle a mover: the team search's positions
    pol = OptimumPolicy(team)
    assert pol.team
    pol.act({a: None for a in team.agents})
    expect = team_search(team, [team.positions_m, best_response_targets(team, movers, 2, 10.0, 16)]).positions_m
    assert np.array_equal(pol.targets_m, expect)
    # best-response: always best response
    brp = make_policy("best-response", team)
    assert isinstance(brp, BestResponsePolicy) and "best-response" in SCRIPTED and not brp.team
    brp.act({a: None for a in team.agents})
    assert np.array_equal(brp.targets_m, best_response_targets(team, movers, 2, 10.0, 16))


def test_team_moves_are_the_single_moves_of_the_search(team_env) -> None:
    """``team_moves(sequential=True)`` is one round of the search's ascent in index order without pair moves
    (bit for bit); made at once, each vehicle's move is taken against the positions now: the first vehicle's
    is the same, none lowers J on its own, and some differ from the sequential ones."""
    env = team_env
    seq = team_moves(env, sequential=True)
    ref = team_search(env, n_orders=1, max_rounds=1, pair_points=0)
    np.testing.assert_array_equal(seq, ref.positions_m)
    sim = team_moves(env)
    np.testing.assert_array_equal(sim[0], seq[0])
    now = np.array(env.positions_m)
    j_now = team_objective(env.links, now, env.p_min)
    for i in range(env.n):
        alone = now.copy()
        alone[i] = sim[i]
        assert team_objective(env.links, alone, env.p_min) >= j_now - 1e-12
    assert np.any(np.abs(sim - seq).max(axis=1) > 1.0)
