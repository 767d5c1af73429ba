"""The batched one-mover step (``MoverBatch``) and the ``vector_entry_point`` env built on it.

Reference values are the unbatched paths: ``MobilityEnv.step_mover`` per copy (itself tested
bit-identical to the full ``step``) and Gymnasium's ``SyncVectorEnv`` over the same single-agent
envs; every comparison is exact (``np.array_equal``, dtypes included).
"""

from __future__ import annotations

import functools
import subprocess
import sys
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env.mobility_env import INFO_KEYS
from cv2x_marl.env.mover_batch import MoverBatch, batch_problem
from cv2x_marl.env.single import SingleMoverEnv
from cv2x_marl.env.vector import SingleMoverVectorEnv

#: the single envs of the -v1 / -v2 ids (one class, the id an argument)
SingleMoverEnvV1 = functools.partial(SingleMoverEnv, "cv2x/SingleMover-v1")
SingleMoverEnvV2 = functools.partial(SingleMoverEnv, "cv2x/SingleMover-v2")

pytestmark = pytest.mark.filterwarnings("ignore:.*is out of date.*")


def _batch_vs_step_mover(cls: type[SingleMoverEnv], copies: int = 3, steps: int = 40, **kw: Any) -> int:
    """Step K copies through a MoverBatch and K reference copies through ``step`` (``step_mover``);
    returns how many (step, copy) results were compared, after asserting each is identical."""
    ref = [cls(**kw) for _ in range(copies)]
    bat = [cls(**kw) for _ in range(copies)]
    batch = MoverBatch([e.par for e in bat])
    for k in range(copies):
        ref[k].reset(seed=10 + k)
        bat[k].reset(seed=10 + k)
        batch.load(k)
    rng = np.random.default_rng(7)
    compared = 0
    for _ in range(steps):
        act = rng.uniform(-1.5, 1.5, (copies, 2)).astype(np.float32)
        obs, rew, done, info = batch.step(act)
        for k in range(copies):
            o, r, term, trunc, inf = ref[k].step(act[k])
            assert np.array_equal(o, obs[k]) and o.dtype == obs.dtype
            assert r == rew[k] and trunc == done[k] and not term
            assert np.array_equal([inf[key] for key in INFO_KEYS], info[k])
            par = ref[k].par
            assert np.array_equal(par.positions_m, batch.positions_m[k])
            assert par.geometry is not None
            assert np.array_equal(par.geometry.disp_m, batch.disp_m[k])  # -0.0 on the diagonal included
            assert np.array_equal(np.signbit(par.geometry.disp_m), np.signbit(batch.disp_m[k]))
            compared += 1
            if trunc:
                ref[k].reset()
                bat[k].reset()
                batch.load(k)
    return compared


@pytest.mark.parametrize(
    ("cls", "kw"),
    [
        (SingleMoverEnv, {}),
        (SingleMoverEnv, {"overrides": ["road.wrap_distances=true", "link.inband_emission_db=-20"]}),
        (SingleMoverEnv, {"overrides": ["link.model=threshold", "radio.sensitivity_dbm=-95"]}),
        (SingleMoverEnv, {"preset": "highway", "overrides": ["vehicles.n_vehicles=12"], "n_neighbours": 5}),
        (SingleMoverEnvV1, {"max_drift_m": 12.0, "roi": True}),
        (SingleMoverEnvV1, {"privileged": True, "normalise_reward": False, "truth_los": "always"}),
        (SingleMoverEnvV2, {"action_mode": "plan_residual", "reward_form": "utility", "settle_steps": 4}),
    ],
)
def test_batched_step_equals_step_mover_bit_for_bit(cls: type[SingleMoverEnv], kw: dict[str, Any]) -> None:
    assert _batch_vs_step_mover(cls, max_cycles=12, **kw) == 3 * 40  # across three autoresets per copy


def test_batch_refuses_what_it_cannot_step() -> None:
    assert batch_problem(SingleMoverEnv().par) is None
    assert "replan_every" in str(batch_problem(SingleMoverEnvV2(replan_every=5).par))
    assert "winner_b1" in str(batch_problem(SingleMoverEnv(truth_los="geometry").par))
    with pytest.raises(ValueError, match=r"copy 1 cannot be stepped in a batch: .*replan_every"):
        MoverBatch([SingleMoverEnvV2().par, SingleMoverEnvV2(replan_every=5).par])
    with pytest.raises(ValueError, match="copy 1 differs from copy 0"):
        MoverBatch([SingleMoverEnv(max_cycles=5).par, SingleMoverEnv(max_cycles=6).par])
    envs = [SingleMoverEnv(max_cycles=2) for _ in range(2)]
    batch = MoverBatch([e.par for e in envs])
    envs[0].reset(seed=0)
    batch.load(0)
    with pytest.raises(RuntimeError, match="copy 1 has no episode"):
        batch.step(np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"action of copy 0 is not finite: \[nan, 0.0\]"):
        batch.step(np.array([[np.nan, 0.0], [0.0, 0.0]]), np.array([True, False]))
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 2\)"):
        batch.step(np.zeros(2))
    for _ in range(2):
        batch.step(np.zeros((2, 2)), np.array([True, False]))
    with pytest.raises(RuntimeError, match="finished episode of copy 0"):
        batch.step(np.zeros((2, 2)), np.array([True, False]))


# ----------------------------------------------------------------- the vector env
def _vector_pair(env_id: str, mode: str, copies: int = 3, **kw: Any) -> tuple[Any, Any]:
    ours = gym.make_vec(env_id, num_envs=copies, vectorization_mode="vector_entry_point", autoreset_mode=mode, **kw)
    sync = gym.make_vec(
        env_id, num_envs=copies, vectorization_mode="sync", vector_kwargs={"autoreset_mode": mode}, **kw
    )
    return ours, sync


def _same_infos(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if key == "final_obs":
            assert all((x is None and y is None) or np.array_equal(x, y) for x, y in zip(a[key], b[key], strict=True))
        elif isinstance(a[key], dict):
            _same_infos(a[key], b[key])
        else:
            assert np.array_equal(a[key], b[key]) and a[key].dtype == b[key].dtype, key


@pytest.mark.parametrize("mode", ["NextStep", "SameStep"])
@pytest.mark.parametrize(
    ("env_id", "kw"),
    [
        ("cv2x/SingleMover-v0", {}),
        ("cv2x/SingleMover-v2", {"action_mode": "plan_residual", "reward_form": "utility"}),
        ("cv2x/SingleMover-v2", {"replan_every": 2}),  # not batched: the copies' own steps
    ],
)
def test_vector_entry_point_equals_sync_vector_env(mode: str, env_id: str, kw: dict[str, Any]) -> None:
    ours, sync = _vector_pair(env_id, mode, max_cycles=4, **kw)
    assert isinstance(ours.unwrapped, SingleMoverVectorEnv)
    assert ours.batched == ("replan_every" not in kw)
    assert ours.metadata["autoreset_mode"].value == mode
    assert ours.observation_space == sync.observation_space and ours.action_space == sync.action_space
    o1, i1 = ours.reset(seed=3)
    o2, i2 = sync.reset(seed=3)
    assert np.array_equal(o1, o2)
    _same_infos(i1, i2)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(11):  # two autoresets of every copy
        act = rng.uniform(-1.3, 1.3, (3, 2)).astype(np.float32)
        r1, r2 = ours.step(act), sync.step(act)
        for x, y in zip(r1[:4], r2[:4], strict=True):
            assert np.array_equal(x, y) and x.dtype == y.dtype
        _same_infos(r1[4], r2[4])
        ended += int(r1[3].sum())
    assert ended == 6
    ours.close()
    sync.close()


@pytest.mark.parametrize("env_id", ["cv2x/SingleMover-v0", "cv2x/SingleMover-v1", "cv2x/SingleMover-v2"])
def test_make_vec_builds_each_version(env_id: str) -> None:
    envs = gym.make_vec(env_id, num_envs=2, vectorization_mode="vector_entry_point")
    assert type(envs) is SingleMoverVectorEnv and envs.env_id == env_id and envs.num_envs == 2 and envs.batched
    assert all(e.env_id == env_id for e in envs.envs)
    assert envs.observation_space.shape == (2, *envs.single_observation_space.shape)


def test_seeded_first_reset_gives_the_same_episodes_across_autoresets() -> None:
    def run(seed: int) -> np.ndarray:
        envs = SingleMoverVectorEnv(2, max_cycles=3)
        out = [envs.reset(seed=seed)[0]]
        for _ in range(10):
            out.append(envs.step(np.full((2, 2), 0.5, dtype=np.float32))[0])
        return np.stack(out)

    a, b, c = run(1), run(1), run(2)
    assert np.array_equal(a, b)
    assert not np.array_equal(a[4:], c[4:])
    # copy 0 of seed 1 and copy 1 of seed 0 are the same episodes (seeds s + k, as SyncVectorEnv)
    assert np.array_equal(run(0)[:, 1], a[:, 0])


def test_disabled_autoreset_and_reset_mask() -> None:
    envs = SingleMoverVectorEnv(2, max_cycles=2, autoreset_mode="Disabled")
    envs.reset(seed=0)
    envs.step(np.zeros((2, 2)))
    _, _, _, trunc, _ = envs.step(np.zeros((2, 2)))
    assert trunc.tolist() == [True, True]
    with pytest.raises(RuntimeError, match="copy 0 finished its episode: reset it with options"):
        envs.step(np.zeros((2, 2)))
    before = envs.batch.positions_m[1].copy()
    _, info = envs.reset(seed=[5, None], options={"reset_mask": np.array([True, False])})
    assert info["_utility"].tolist() == [True, False]
    assert envs.envs[0].par.seed_used == 5 and np.array_equal(envs.batch.positions_m[1], before)
    with pytest.raises(RuntimeError, match="copy 1 finished"):
        envs.step(np.zeros((2, 2)))


def test_bad_vector_input_is_named() -> None:
    with pytest.raises(ValueError, match=r"invalid num_envs=0; allowed: an integer >= 1"):
        SingleMoverVectorEnv(0)
    with pytest.raises(ValueError, match=r"invalid autoreset_mode='sometimes'; allowed: NextStep, SameStep, Disabled"):
        SingleMoverVectorEnv(2, autoreset_mode="sometimes")
    envs = SingleMoverVectorEnv(2, max_cycles=3)
    with pytest.raises(RuntimeError, match="before reset"):
        envs.step(np.zeros((2, 2)))
    envs.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must have shape \(2, 2\), got \(3, 2\)"):
        envs.step(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="action of copy 1 is not finite"):
        envs.step(np.array([[0.0, 0.0], [np.inf, 0.0]]))
    with pytest.raises(ValueError, match="invalid reset seed"):
        envs.reset(seed=[1])
    with pytest.raises(ValueError, match="invalid env argument max_cycles"):
        SingleMoverVectorEnv(2, max_cycles=0)


def test_copies_see_the_batched_state() -> None:
    ours, sync = _vector_pair("cv2x/SingleMover-v1", "NextStep", copies=2, max_cycles=5)
    ours.reset(seed=4)
    sync.reset(seed=4)
    for _ in range(3):
        ours.step(np.full((2, 2), 0.7, dtype=np.float32))
        sync.step(np.full((2, 2), 0.7, dtype=np.float32))
    assert ours.get_attr("par")[1].t == 3
    ours_state = [env.par.state() for env in ours.get_attr("unwrapped")]
    sync_state = [env.par.state() for env in sync.get_attr("unwrapped")]
    assert all(np.array_equal(a, b) for a, b in zip(ours_state, sync_state, strict=True))
    ours.set_attr("marker", [1, 2])
    assert ours.call("marker") == (1, 2)


def test_make_vec_resolves_in_a_fresh_process() -> None:
    code = (
        "import gymnasium, numpy as np\n"
        "e = gymnasium.make_vec('cv2x_marl:cv2x/SingleMover-v2', num_envs=2, vectorization_mode='vector_entry_point')\n"
        "o, _ = e.reset(seed=0); o2 = e.step(np.zeros((2, 2), np.float32))[0]\n"
        "print(type(e).__name__, e.batched, o.shape, o2.shape)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["SingleMoverVectorEnv", "True", "(2,", "174)", "(2,", "174)"]


def test_batched_copies_refuse_what_would_desynchronise_them() -> None:
    from cv2x_marl.rl.sb3_vec_env import AgentsVecEnv

    envs = SingleMoverVectorEnv(2, max_cycles=4)
    envs.reset(seed=0)
    with pytest.raises(RuntimeError, match=r"call\('reset'\) on a batched copy would desynchronise it"):
        envs.call("reset", seed=1)
    assert envs.call("render_mode") == (None, None)  # reading is fine
    sb3 = AgentsVecEnv(lambda: SingleMoverEnv(max_cycles=4).par, 2)
    sb3.reset()
    with pytest.raises(RuntimeError, match=r"env_method\('step_mover'\)"):
        sb3.env_method("step_mover", np.zeros(2))
    with pytest.raises(RuntimeError, match=r"set_attr\('max_cycles'\) on batched copies"):
        sb3.set_attr("max_cycles", 9)
