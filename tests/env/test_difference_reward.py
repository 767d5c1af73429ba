"""``reward="difference"``: each vehicle's marginal contribution to the team objective (env/team_search.py,
``difference_rewards``), checked against J of the numpy reference links with the vehicle put back at its start."""

from __future__ import annotations

import numpy as np
import pytest

from cv2x_marl.env import parallel_env_cooperative
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.policies.optimum import uses_team_search
from cv2x_marl.sim.ground_truth import SnapshotLinks
from cv2x_marl.utility import utility_log


def _numpy_j(env, positions: np.ndarray) -> float:
    """J (per target receiver, mean over the vehicles) from the numpy reference links: independent of the
    compiled kernels that ``difference_rewards`` uses."""
    ref = SnapshotLinks(env.config, env.links.snapshot, env.truth_los, compiled=False, field=env.links.field)
    p = ref.success(positions)
    u = utility_log(p, ref.target, env.p_min) / np.maximum(ref.target.sum(axis=1), 1)
    return float(u.mean())


def _episode(env, seed: int, steps: int) -> tuple[np.ndarray, list[np.ndarray]]:
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    rewards = []
    for _ in range(steps):
        actions = {a: rng.uniform(-1.0, 1.0, 2).astype(np.float32) for a in env.agents}
        _, r, *_ = env.step(actions)
        rewards.append(np.array([r[a] for a in env.possible_agents]))
    return env.positions_m.copy(), rewards


def test_rewards_sum_to_each_vehicles_contribution_to_the_team_objective() -> None:
    """Improvement form: an episode's rewards of vehicle i sum to J(x) - J(x with i at its start), J from the
    numpy reference (1e-12: only the order of the additions differs); the first step's reward is that
    difference after one step (it is 0 at the start)."""
    env = parallel_env_cooperative(reward="difference", max_cycles=6)
    pos, rewards = _episode(env, seed=5, steps=6)
    j = _numpy_j(env, pos)
    expected = np.array(
        [j - _numpy_j(env, np.where((np.arange(env.n) == i)[:, None], env.start_m, pos)) for i in range(env.n)]
    )
    assert np.abs(expected).max() > 1e-3  # the moves matter
    np.testing.assert_allclose(np.sum(rewards, axis=0), expected, rtol=0, atol=1e-12)
    env2 = parallel_env_cooperative(reward="difference", max_cycles=6)
    pos1, first = _episode(env2, seed=5, steps=1)
    j1 = _numpy_j(env2, pos1)
    d1 = [j1 - _numpy_j(env2, np.where((np.arange(env2.n) == i)[:, None], env2.start_m, pos1)) for i in range(env2.n)]
    np.testing.assert_allclose(first[0], d1, rtol=0, atol=1e-12)


def test_only_movers_are_rewarded_and_the_positions_do_not_depend_on_the_reward() -> None:
    """Vehicles that do not move get 0; the same actions give the same trajectory as the team reward (the
    reward changes what an agent is told, not the dynamics); the env still counts as the team's."""
    team = parallel_env_cooperative(max_cycles=4, movers=[0, 3, 5])
    diff = parallel_env_cooperative(reward="difference", max_cycles=4, movers=[0, 3, 5])
    pos_team, _ = _episode(team, seed=2, steps=4)
    pos_diff, rewards = _episode(diff, seed=2, steps=4)
    np.testing.assert_array_equal(pos_team, pos_diff)
    still = np.setdiff1d(np.arange(diff.n), [0, 3, 5])
    total = np.sum(rewards, axis=0)
    assert np.all(total[still] == 0.0)
    j = _numpy_j(diff, pos_diff)
    for i in (0, 3, 5):  # each mover's contribution, the others (movers or not) where they are
        back = np.where((np.arange(diff.n) == i)[:, None], diff.start_m, pos_diff)
        assert abs(j - _numpy_j(diff, back)) > 1e-6
        assert total[i] == pytest.approx(j - _numpy_j(diff, back), abs=1e-12)
    assert not uses_team_search(diff)  # not every vehicle moves
    assert uses_team_search(parallel_env_cooperative(reward="difference"))


@pytest.mark.parametrize(
    ("env_id", "kwargs", "why"),
    [
        ("cv2x/Cooperative-v0", {"team_objective": "prr"}, "team_objective utility"),
        ("cv2x/Mobility-v0", {"truth_los": "geometry"}, "compiled WINNER"),
    ],
)
def test_refused_where_it_cannot_be_computed(env_id: str, kwargs: dict, why: str) -> None:
    with pytest.raises(ValueError, match=rf"invalid env argument reward='difference'; allowed: .*{why}"):
        make_parallel_env(env_id, reward="difference", **kwargs)


def test_refused_in_traffic_mode() -> None:
    with pytest.raises(ValueError, match=r"invalid env argument reward='difference'.*snapshot mode"):
        make_parallel_env("cv2x/Mobility-v0", mode="traffic", reward="difference")
