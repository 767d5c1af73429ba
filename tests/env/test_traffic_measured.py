"""cv2x/Traffic-v1: observation version 4 (what the mover measured on the road) against an independent numpy
replay of the same draws and the simulator's SPS state; Traffic-v0's dynamics, rewards and shared entries kept."""

from __future__ import annotations

import itertools
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the ids
from cv2x_marl.env.measurement import RSRP_REF_DBM, RSRP_SCALE_DB
from cv2x_marl.env.observation import FEATURES, FEATURES_V4, OWN_DRIVE, OWN_V4
from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.rng import env_stream

N = 8
WINDOW = 3  # the ring wraps within the episode
STEPS = 24
ERROR_DB = 3.0
N_SUB, RRI_MS = 2, 100  # the paper preset's sps.n_subchannels and traffic.rri_ms
# a small scene with the standard's reservation signalling (SCIs announce reselections)
OVERRIDES = [f"vehicles.n_vehicles={N}", "sps.reservation_signalling=standard"]


def _dense_rx_dbm(geo: Any) -> np.ndarray:
    """[tx, rx] mean received power of the simulator's period geometry (the pairs (rx, tx), first half i < j)."""
    out = np.full((N, N), -np.inf)
    for a, b, v in zip(geo.rx, geo.tx, np.concatenate([geo.mean_rx_dbm_half] * 2), strict=True):
        out[b, a] = v  # tx b -> rx a
    return out


def _dense_links(links: Any) -> tuple[np.ndarray, np.ndarray]:
    """[tx, rx] success probability and decoded outcome (cause 0: ok) of the simulator's last period."""
    tx, rx, p, cause = links
    prob, decoded = np.zeros((N, N)), np.zeros((N, N), dtype=bool)
    for t, r, pv, c in zip(tx, rx, p, cause, strict=True):
        prob[t, r] = pv
        decoded[t, r] = c == 0
    return prob, decoded


class Replay:
    """The measurement of the module docstring of env/measurement.py, replayed with numpy loops over pairs."""

    def __init__(self, seed: int, rx_dbm: np.ndarray, p: np.ndarray, resource: np.ndarray, release: np.ndarray):
        self.rng = env_stream(seed, "measurement")
        self.samples = np.zeros((WINDOW, N, N))
        self.heard = np.zeros((WINDOW, N, N), dtype=bool)
        self.rsrp = np.full((N, N), np.nan)
        self.age = np.zeros((N, N), dtype=np.int64)
        for k in range(WINDOW):  # the start window: W periods at the start with P
            u, e, z = self._draws()
            self._period(k, rx_dbm, u < p, e, z, report=k == WINDOW - 1)
        self.head = 0
        self.sci_res = np.where(np.isfinite(self.rsrp), resource[:, None], -1)
        self.sci_rel = np.isfinite(self.rsrp) & release[:, None]
        self.sent = (resource.copy(), release.copy())

    def _draws(self) -> tuple[np.ndarray, ...]:
        return self.rng.random((N, N)), self.rng.standard_exponential((N, N)), self.rng.standard_normal((N, N))

    def _period(self, k: int, rx_dbm: np.ndarray, decoded: np.ndarray, e: np.ndarray, z: np.ndarray, report: bool):
        self.samples[k] = np.where(decoded, 10.0 ** (rx_dbm / 10.0) * e, 0.0)
        self.heard[k] = decoded
        self.age = np.where(decoded, 0, self.age + 1)
        if report:
            any_heard = self.heard.any(axis=0)
            with np.errstate(divide="ignore", invalid="ignore"):
                mean_mw = self.samples.sum(axis=0) / self.heard.sum(axis=0)
            self.rsrp = np.where(any_heard, 10.0 * np.log10(mean_mw) + ERROR_DB * z, self.rsrp)

    def step(self, rx_dbm: np.ndarray, decoded: np.ndarray, resource: np.ndarray, release: np.ndarray) -> None:
        _, e, z = self._draws()  # the uniforms are drawn and unused: the simulator decided the decoding
        self._period(self.head, rx_dbm, decoded, e, z, report=True)
        self.head = (self.head + 1) % WINDOW
        self.sci_res = np.where(decoded, self.sent[0][:, None], self.sci_res)
        self.sci_rel = np.where(decoded, self.sent[1][:, None], self.sci_rel)
        self.sent = (resource.copy(), release.copy())


def _expected(env: Any, rep: Replay) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[N, K, F4] measured entries, [N, OWN_V4] own entries (before clipping and float32) and the neighbour
    order [N, K] (nearest first, ties by index: np.lexsort, not the env's sort)."""
    k = N - 1
    dist = np.sqrt(env.geometry.dist2_m2)
    order = np.array([[j for j in np.lexsort((np.arange(N), dist[i])) if j != i][:k] for i in range(N)])
    n_sub, rri = env.config.sps.n_subchannels, env.config.traffic.rri_ms
    own_res = env.sim.resource
    meas = np.zeros((N, k, FEATURES_V4))
    for i in range(N):
        for kk, j in enumerate(order[i]):
            heard = np.isfinite(rep.rsrp[j, i])
            res = rep.sci_res[j, i]
            meas[i, kk] = [
                (rep.rsrp[j, i] - RSRP_REF_DBM) / RSRP_SCALE_DB if heard else 0.0,
                rep.age[j, i] / WINDOW,
                float(heard),
                (res // n_sub) / rri if res >= 0 else 0.0,
                (res % n_sub) / n_sub if res >= 0 else 0.0,
                float(res >= 0 and rep.sci_rel[j, i]),
                float(res >= 0 and res // n_sub == own_res[i] // n_sub),
                float(res >= 0 and res == own_res[i]),
            ]
    sched = env.sim.scheduler
    counter_max = env.config.sps.counter_max  # with RRI 100 ms (TS 36.321 5.14.1.1)
    u = env.own.u_now
    own = np.stack(
        [(own_res // n_sub) / rri, (own_res % n_sub) / n_sub, sched.counter / counter_max, sched.releasing, u,
         10.0 * (u - env.own.u_prev)],
        axis=1,
    )  # fmt: skip
    return meas, own, order


@pytest.fixture(scope="module")
def trajectory() -> list[dict[str, Any]]:
    """Every step of one Traffic-v1 episode (all vehicles' observations) with the replay's expected entries."""
    env = make_parallel_env(
        "cv2x/Traffic-v1", overrides=OVERRIDES, sensing_window=WINDOW, max_cycles=STEPS, rsrp_error_db=ERROR_DB
    )
    seed = 11
    obs, _ = env.reset(seed=seed)
    sim = env.sim
    p0, _ = _dense_links(sim.last_links)
    rep = Replay(seed, _dense_rx_dbm(sim.last_geometry), p0, sim.resource.copy(), sim.scheduler.releasing.copy())
    rng = np.random.default_rng(5)
    out = []
    for t in range(STEPS + 1):
        meas, own, order = _expected(env, rep)
        stacked = np.stack([obs[a] for a in env.possible_agents])
        disp = env.geometry.disp_m.copy()
        out.append({"obs": stacked, "meas": meas, "own": own, "order": order, "disp": disp, "sent": rep.sent[0].copy()})
        if t == STEPS:
            break
        sent_before = sim.resource.copy()
        action = rng.uniform(-1, 1, size=2).astype(np.float32)
        obs, *_ = env.step({a: action if a == "vehicle_0" else np.zeros(2, np.float32) for a in env.agents})
        _, decoded = _dense_links(sim.last_links)
        rep.step(_dense_rx_dbm(sim.last_geometry), decoded, sim.resource.copy(), sim.scheduler.releasing.copy())
        out[-1]["decoded_next"], out[-1]["sent_before"] = decoded, sent_before
    out.append({"layout": env.layout})
    return out


@pytest.mark.kernel_equality
def test_rsrp_age_and_sci_entries_equal_an_independent_replay(trajectory: list[dict[str, Any]]) -> None:
    """Every vehicle's measured entries at every step equal the numpy replay of the same draws (the RSRP through
    the compiled measurement: a tolerance of 1e-5 on the scaled entry, i.e. 2e-4 dB)."""
    layout = trajectory[-1]["layout"]
    k, v0 = N - 1, layout.v0_size
    heard_any = released = collided = 0
    for step in trajectory[:-1]:
        obs = step["obs"]
        got = obs[:, v0 : v0 + k * FEATURES_V4].reshape(N, k, FEATURES_V4)
        want = np.clip(step["meas"], -layout.obs_clip, layout.obs_clip).astype(np.float32)
        np.testing.assert_allclose(got[..., 0], want[..., 0], rtol=0, atol=1e-5)
        np.testing.assert_array_equal(got[..., 1:], want[..., 1:])
        # the neighbour order is the v0 block's: its relative positions are the replay's neighbours'
        rel = obs[:, : k * FEATURES].reshape(N, k, FEATURES)[..., :2] * layout.scale_m
        for i in range(N):
            np.testing.assert_allclose(rel[i], step["disp"][:, i, step["order"][i]].T, rtol=0, atol=1e-3)
        heard_any += int(want[..., 2].sum())
        released += int(want[..., 5].sum())
        collided += int(want[..., 7].sum())
    # the scene exercises what is tested: reports, announced reselections, co-channel neighbours
    assert heard_any > 0 and released > 0 and collided > 0


def test_resource_entries_equal_the_simulators_sps_state(trajectory: list[dict[str, Any]]) -> None:
    """A neighbour decoded in the last period reports the resource it held when it sent (the scheduler's before
    the step); the own entries are the scheduler's resource, counter and announcement now."""
    layout = trajectory[-1]["layout"]
    k, v0, o0 = N - 1, layout.v0_size, layout.own_v1_offset
    checked = 0
    for before, after in itertools.pairwise(trajectory[:-1]):
        got = after["obs"][:, v0 : v0 + k * FEATURES_V4].reshape(N, k, FEATURES_V4)
        for i in range(N):
            for kk, j in enumerate(after["order"][i]):
                if before["decoded_next"][j, i]:  # decoded this period: age 0, the SCI just read
                    res = before["sent_before"][j]
                    assert got[i, kk, 1] == 0.0
                    assert got[i, kk, 3] == np.float32((res // N_SUB) / RRI_MS)
                    assert got[i, kk, 4] == np.float32((res % N_SUB) / N_SUB)
                    checked += 1
        own = np.clip(after["own"], -layout.obs_clip, layout.obs_clip).astype(np.float32)
        np.testing.assert_array_equal(after["obs"][:, o0 : o0 + OWN_V4], own)
    assert checked > 50


def test_same_dynamics_rewards_and_shared_entries_as_traffic_v0() -> None:
    """Traffic-v1 is Traffic-v0 with more observed: the same seed and actions give the same rewards and infos,
    bit for bit, and the same v0 block and driving entries."""
    envs = [gym.make(i, overrides=OVERRIDES, max_cycles=8) for i in ("cv2x/Traffic-v0", "cv2x/Traffic-v1")]
    layouts = [e.unwrapped.par.layout for e in envs]
    assert layouts[1].size == layouts[0].size + (N - 1) * FEATURES_V4 + OWN_V4
    outs: list[list[Any]] = [[], []]
    for e, out in zip(envs, outs, strict=True):
        ob, info = e.reset(seed=3)
        out.append((ob, 0.0, info))
        for a in np.random.default_rng(2).uniform(-1, 1, size=(8, 2)).astype(np.float32):
            ob, r, _, _, info = e.step(a)
            out.append((ob, r, info))
    v0 = layouts[0].v0_size
    for (a, ra, ia), (b, rb, ib) in zip(*outs, strict=True):
        assert ra == rb and ia == ib
        np.testing.assert_array_equal(a[:v0], b[:v0])
        np.testing.assert_array_equal(a[-OWN_DRIVE:], b[-OWN_DRIVE:])


def test_checker_seeding_and_refusals() -> None:
    from gymnasium.utils.env_checker import check_env

    check_env(gym.make("cv2x/Traffic-v1", max_cycles=5).unwrapped, skip_render_check=True)
    env = gym.make("cv2x/Traffic-v1", overrides=OVERRIDES, max_cycles=4)
    runs = []
    for seed in (4, 4, 5):
        ob, _ = env.reset(seed=seed)
        obs = [ob] + [env.step(np.array([0.3, 0.0], np.float32))[0] for _ in range(4)]
        runs.append(np.stack(obs))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])
    with pytest.raises(ValueError, match="invalid env argument observation=4"):
        make_parallel_env("cv2x/Traffic-v0", observation=4, drive_observation=False)
    with pytest.raises(ValueError, match="invalid env argument movers: Traffic-v1 always moves vehicle 0"):
        gym.make("cv2x/Traffic-v1", movers=[1])


def test_a_variant_of_the_traffic_task_with_its_seed_lists() -> None:
    from cv2x_marl.env import tasks
    from cv2x_marl.experiments import evaluate as ev

    task = tasks.task_of_env("cv2x/Traffic-v1")
    assert task is not None and task.name == "traffic" and task.env_id == "cv2x/Traffic-v1"
    assert "cv2x/Traffic-v1" not in {t.env_id for t in tasks.TASKS.values()}  # no task of the benchmark
    assert ev.parse_seeds("heldout", "cv2x/Traffic-v1") == tasks.TASKS["traffic"].heldout_seeds
    assert ev.parse_seeds("train", "cv2x/Traffic-v1") == tasks.TRAIN_SEEDS
    with pytest.raises(ValueError, match="cannot run on task traffic \\(cv2x/Traffic-v1\\)"):
        task.check_policy("planner")


def test_parallel_variant_passes_pettingzoos_api_test() -> None:
    """``parallel_env(**TRAFFIC_V1_DEFAULTS)``: every vehicle drives and observes version 4."""
    from pettingzoo.test import parallel_api_test

    from cv2x_marl.env import parallel_env
    from cv2x_marl.env.defaults import TRAFFIC_V1_DEFAULTS

    env = parallel_env(**TRAFFIC_V1_DEFAULTS, overrides=OVERRIDES, max_cycles=3)
    parallel_api_test(env, num_cycles=3)
    obs, _ = env.reset(seed=1)
    assert env.layout.version == 4 and all(o.shape == (env.layout.size,) for o in obs.values())
