"""The batch-invariance rule of the learned policies (cv2x_marl.policies.base): an agent's action is a function of
its own observation (and its own recurrent state) alone, bit for bit, whatever the batch it is acted on in.

The reference for a row is the network run on that row alone (``[1, obs_dim]``: the shipped SB3 PPO model's
``model.predict``, the shipped MAPPO actor on a fresh tensor); the policy must give exactly that for the row acted
on alone, among its episode's agents, and stacked among 63 random others. Bit-for-bit equality is the claim: both
sides run the same arithmetic (the same network on the same ``[1, obs_dim]`` input).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cv2x_marl.env import tasks
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments.evaluate import evaluate_rows
from cv2x_marl.policies.base import BatchPolicy, act_rows

ROOT = Path(__file__).resolve().parents[2]
PPO_MODEL = ROOT / "agents" / "models" / "singlemover-v3_seed0" / "model.zip"
MAPPO_MODEL = ROOT / "agents" / "models" / "cooperative_seed0" / "model.pt"
#: the first three held-out seeds of the cooperative task (cv2x/Cooperative-v0: its 21 vehicles all move)
COOP_SEEDS = tasks.TASKS["cooperative"].seeds("heldout")[:3]


def _episode_observations(seed: int) -> dict[str, np.ndarray]:
    """The 21 agents' observations at the reset of a Cooperative-v0 episode ([351] float32 each: the size both
    shipped networks read)."""
    env = make_parallel_env("cv2x/Cooperative-v0", max_cycles=100, max_step_m=5.0)
    obs, _ = env.reset(seed=seed)
    return obs


def _check_rows(policy: BatchPolicy, alone: object) -> None:
    """``policy.act`` gives every agent ``alone(row)`` exactly: the episode's agents together, each agent by
    itself, and six of them each stacked among 63 random observations (at another place each time)."""
    obs = _episode_observations(COOP_SEEDS[0])
    agents = list(obs)
    want = {a: np.asarray(alone(obs[a][None]), dtype=np.float32).reshape(2) for a in agents}
    together = policy.act(obs)
    assert list(together) == agents
    rng = np.random.default_rng(7)
    for k, a in enumerate(agents):
        np.testing.assert_array_equal(together[a], want[a])
        np.testing.assert_array_equal(policy.act({a: obs[a]})[a], want[a])
        if k % 4:  # stacked among 63 others: agents 0, 4, ..., 20 (at places 0, 4, ..., 20 of 64)
            continue
        others = rng.uniform(-1.0, 1.0, size=(63, obs[a].shape[0])).astype(np.float32)
        stack = {f"other_{i}": o for i, o in enumerate(others)}
        names = list(stack)
        names.insert(k, a)
        stacked = policy.act({n: obs[a] if n == a else stack[n] for n in names})
        np.testing.assert_array_equal(stacked[a], want[a])


def test_sb3_ppo_acts_on_each_row_alone() -> None:
    pytest.importorskip("stable_baselines3")
    from cv2x_marl.policies.ppo import PpoPolicy

    policy = PpoPolicy(PPO_MODEL)
    assert policy.row_by_row and not policy.recurrent

    def alone(row: np.ndarray) -> np.ndarray:
        return policy.model.predict(row, deterministic=True)[0]

    _check_rows(policy, alone)


def test_mappo_actor_acts_on_each_row_alone() -> None:
    torch = pytest.importorskip("torch")
    from cv2x_marl.policies.mappo import MappoPolicy

    policy = MappoPolicy(MAPPO_MODEL)

    def alone(row: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return policy.actor.deterministic(torch.from_numpy(np.array(row, dtype=np.float32))).numpy()

    _check_rows(policy, alone)


def test_batch_policy_calls_its_function_on_one_row_at_a_time() -> None:
    """``act_fn`` sees [1, obs_dim] per agent, in the dict's order; ``row_by_row=False`` one call on all agents."""
    seen: list[np.ndarray] = []

    def act_fn(obs: np.ndarray) -> np.ndarray:
        seen.append(obs.copy())
        return np.stack([obs[:, 0], -obs[:, 1]], axis=1)

    obs = {"b": np.array([0.5, 0.25, 9.0], np.float32), "a": np.array([-1.0, 0.125, 3.0], np.float32)}
    acts = BatchPolicy(act_fn).act(obs)
    assert [s.shape for s in seen] == [(1, 3), (1, 3)]
    np.testing.assert_array_equal(seen[0][0], obs["b"])
    assert list(acts) == ["b", "a"]
    np.testing.assert_array_equal(acts["b"], [0.5, -0.25])
    np.testing.assert_array_equal(acts["a"], [-1.0, -0.125])
    seen.clear()
    together = BatchPolicy(act_fn, row_by_row=False).act(obs)
    assert [s.shape for s in seen] == [(2, 3)]
    np.testing.assert_array_equal(together["a"], acts["a"])
    assert BatchPolicy(act_fn).act({}) == {}
    np.testing.assert_array_equal(act_rows(act_fn, np.stack(list(obs.values()))), [[0.5, -0.25], [-1.0, -0.125]])


def test_evaluate_rows_of_three_seeds_equal_three_one_seed_jobs() -> None:
    """A learned multi-agent policy (the shipped MAPPO actor, 21 movers) on 3 held-out seeds in one evaluation:
    the rows of three one-seed evaluations, value for value (the policy keeps nothing across episodes)."""
    pytest.importorskip("torch")
    spec = f"ppo:{MAPPO_MODEL}"
    short = {"max_cycles": 4}
    _, together = evaluate_rows(None, spec, 3, 0, env_kwargs=short, seeds=COOP_SEEDS, progress=False)
    apart = [evaluate_rows(None, spec, 1, 0, env_kwargs=short, seeds=[s], progress=False)[1] for s in COOP_SEEDS]
    assert len(together) == 3 * 21
    keys = ("seed", "agent", "utility_start", "utility_end", "prr_start", "prr_end", "return", "utility_gain")
    for ep, rows in enumerate(apart):
        assert len(rows) == 21
        for one, joint in zip(rows, together[21 * ep : 21 * (ep + 1)], strict=True):
            assert joint["episode"] == ep and one["episode"] == 0
            assert {k: joint[k] for k in keys} == {k: one[k] for k in keys}
    # the episodes are not trivial: the movers moved, so the actions reached the utilities
    assert any(r["utility_end"] != r["utility_start"] for r in together)
