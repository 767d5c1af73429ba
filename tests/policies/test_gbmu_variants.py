"""GBMU beyond the paper (issue 15): step-size schedules and the logistic steering model, against
closed forms, hand-built scenes and finite differences."""

import math

import numpy as np
import pytest

from cv2x_marl.config import preset
from cv2x_marl.experiments.gbmu_study import VARIANTS, run_study
from cv2x_marl.policies.gbmu import (
    GbmuInputs,
    SteeringUtility,
    StepSchedule,
    armijo_move,
    climb,
    gbmu_direction,
)
from cv2x_marl.regression import TwoDistanceModel
from cv2x_marl.regression.model import SHIPPED_MODELS, load_shipped_model

PAPER = TwoDistanceModel.paper_table2()
LN10 = math.log(10.0)


def _inputs(rx: list[list[float]], l_m: list[float], nsv: list[int]) -> GbmuInputs:
    return GbmuInputs(np.array([rx], float), np.array([l_m], float), np.array([nsv]), np.ones((1, len(rx)), bool))


def _random_inputs(seed: int, b: int = 3, r: int = 7) -> GbmuInputs:
    rng = np.random.default_rng(seed)
    mask = rng.random((b, r)) < 0.8
    mask[:, 0] = True
    return GbmuInputs(rng.uniform(-200, 200, (b, r, 2)), rng.uniform(20, 200, (b, r)), rng.integers(0, 7, (b, r)), mask)


# ------------------------------------------------------------------ decay


def test_decay_step_sizes_equal_the_closed_form() -> None:
    sched = StepSchedule("decay", decay_k0=4.0)
    # delta_k = 2 / (1 + k / 4): 2, 1.6, 1.3333..., 1.142857..., 1, 0.888...
    expected = [2.0, 1.6, 4.0 / 3.0, 8.0 / 7.0, 1.0, 8.0 / 9.0]
    np.testing.assert_allclose([sched.step_size(2.0, k) for k in range(6)], expected, rtol=1e-15)
    np.testing.assert_allclose(sched.step_size(2.0, np.arange(6)), expected, rtol=1e-15)
    assert StepSchedule("constant").step_size(2.0, 5) == 2.0
    assert StepSchedule("backtracking").step_size(2.0, 5) == 2.0


def test_climb_with_decay_moves_by_the_closed_form_steps() -> None:
    # a constant unit direction: after 3 iterations the mover is at sum_k delta_k = 2 + 1.6 + 4/3 = 4.9333...
    def direction(pos: np.ndarray) -> np.ndarray:
        return np.tile([1.0, 0.0], (pos.shape[0], 1))

    res = climb(np.zeros((1, 2)), direction, 2.0, 0.0, 3, record_every=1, schedule=StepSchedule("decay", decay_k0=4.0))
    np.testing.assert_allclose(res.trajectory_m[:, 0, 0], [0.0, 2.0, 3.6, 2.0 + 1.6 + 4.0 / 3.0], rtol=1e-15)
    assert res.final_m[0, 0] == pytest.approx(4.933333333333334, rel=1e-15)


# ------------------------------------------------------------------ constant: bit-identical


def _paper_climb(start: np.ndarray, direction, delta: float, th: float, n: int) -> np.ndarray:  # type: ignore[no-untyped-def]
    """GBMU's loop as it was before schedules (steps 3-5, constant delta)."""
    pos = start.copy()
    active = np.ones(pos.shape[0], bool)
    for _ in range(n):
        step = delta * direction(pos)
        moving = active & (np.hypot(step[:, 0], step[:, 1]) >= th)
        pos[moving] += step[moving]
        active = moving
        if not active.any():
            break
    return pos


def test_constant_schedule_is_bit_identical_to_the_paper_step() -> None:
    inp = _random_inputs(3)
    direction = gbmu_direction(inp, PAPER)
    start = np.zeros((3, 2))
    ref = _paper_climb(start, direction, 1.0, 1e-4, 2000)
    plain = climb(start, direction, 1.0, 1e-4, 2000)
    const = climb(start, direction, 1.0, 1e-4, 2000, schedule=StepSchedule("constant"))
    assert np.array_equal(plain.final_m, ref) and np.array_equal(const.final_m, ref)
    assert np.array_equal(plain.iterations, const.iterations)


# ------------------------------------------------------------------ backtracking


def test_backtracking_never_accepts_a_step_that_lowers_the_predicted_utility() -> None:
    # three receivers 150 m from the origin at 90, 210 and 330 degrees, equal l and NSV: the model's
    # utility peaks at the origin. From (30, 0) a huge constant step overshoots past the peak and lowers
    # the predicted utility.
    ang = np.deg2rad([90.0, 210.0, 330.0])
    inp = _inputs((150 * np.stack([np.cos(ang), np.sin(ang)], 1)).tolist(), [100.0] * 3, [1] * 3)
    util = SteeringUtility(inp, PAPER)
    direction = gbmu_direction(inp, PAPER)
    start = np.array([[30.0, 0.0]])
    delta = 40_000.0
    naive = climb(start, direction, delta, 0.0, 1)
    assert util(naive.final_m)[0] < util(start)[0]  # the scene does punish a constant step

    sched = StepSchedule("backtracking")
    res = climb(start, direction, delta, 0.0, 50, record_every=1, schedule=sched, utility=util)
    u = np.array([util(p)[0] for p in res.trajectory_m])
    assert np.all(np.diff(u) >= 0.0)
    assert u[-1] > u[0]
    assert abs(res.final_m[0, 0]) < 1.0  # it reaches the peak instead of bouncing around it

    # the first accepted step is the first of delta, delta/2, ... that passes Armijo's test (by hand)
    g = direction(start)
    grad_u = g * 3 / LN10  # |R| = 3
    t = delta
    while util(start + t * g)[0] < util(start)[0] + 1e-4 * t * float(grad_u[0] @ g[0]):
        t /= 2
    np.testing.assert_allclose(res.trajectory_m[1], start + t * g, rtol=1e-15)
    assert t < delta


def test_backtracking_with_a_box_checks_the_projected_move() -> None:
    inp = _inputs([[100.0, 0.0], [-100.0, 10.0]], [60.0, 150.0], [2, 0])
    util = SteeringUtility(inp, PAPER)
    pos = np.array([[40.0, 30.0]])
    g = gbmu_direction(inp, PAPER)(pos)

    def box(m: np.ndarray) -> np.ndarray:
        return np.clip(m, -5.0, 5.0)

    move, ok = armijo_move(pos, g, 1e6, util, StepSchedule("backtracking"), box)
    assert ok[0] and np.all(np.abs(move) <= 5.0)
    assert util(pos + move)[0] >= util(pos)[0]
    # at the peak of a symmetric scene (three receivers 150 m away at 120 degrees) every trial along a
    # direction that is no ascent loses utility: the mover stays put instead of accepting a loss
    ang = np.deg2rad([90.0, 210.0, 330.0])
    sym = _inputs((150 * np.stack([np.cos(ang), np.sin(ang)], 1)).tolist(), [100.0] * 3, [1] * 3)
    move0, ok0 = armijo_move(
        np.zeros((1, 2)),
        np.array([[-1.0, 0.0]]),
        50.0,
        SteeringUtility(sym, PAPER),
        StepSchedule("backtracking", max_halvings=3),
    )
    assert not ok0[0] and np.array_equal(move0, np.zeros((1, 2)))


def test_steering_utility_is_what_gbmu_ascends() -> None:
    # where no clip is active, grad U = |R| / ln 10 * gbmu_direction (central differences)
    inp = _inputs([[120.0, 10.0], [-60.0, 40.0], [20.0, -90.0]], [80.0, 150.0, 60.0], [1, 2, 3])
    util = SteeringUtility(inp, PAPER)
    pos = np.array([[5.0, -7.0]])
    h = 1e-4
    fd = np.array([(util(pos + e * h) - util(pos - e * h))[0] / (2 * h) for e in np.eye(2)])
    np.testing.assert_allclose(gbmu_direction(inp, PAPER)(pos)[0] * util.gradient_per_direction[0], fd, rtol=1e-6)


def test_bad_schedules_are_refused_by_key() -> None:
    with pytest.raises(ValueError, match="step_schedule must be one of constant, decay, backtracking"):
        StepSchedule("adam")
    with pytest.raises(ValueError, match="decay_k0"):
        StepSchedule("decay", decay_k0=0.0)
    with pytest.raises(ValueError, match="armijo_c"):
        StepSchedule("backtracking", armijo_c=1.0)
    with pytest.raises(ValueError, match="needs the steering model's utility"):
        climb(np.zeros((1, 2)), lambda p: p, 1.0, 0.0, 1, schedule=StepSchedule("backtracking"))


# ------------------------------------------------------------------ logistic steering


def test_shipped_models_load_with_their_provenance() -> None:
    for name in SHIPPED_MODELS:
        m = load_shipped_model(name)
        assert m.kind == name.split("-")[0]
        assert "cv2x-marl fit" in m.provenance["command"] and m.provenance["dataset_runs"] == 10
    with pytest.raises(ValueError, match="shipped models: linear-fit, logistic-fit"):
        load_shipped_model("cubic")


def test_logistic_direction_is_the_analytic_gradient_of_the_logistic_model() -> None:
    model = load_shipped_model("logistic-fit")
    assert model.kind == "logistic"
    inp = _random_inputs(11)
    pos = np.array([[10.0, -20.0], [0.0, 0.0], [-35.0, 15.0]])
    step = gbmu_direction(inp, model)(pos)
    # analytic: U = sum_j ln sigmoid(eta_j), d ln sigmoid / d eta = 1 - P, d eta / d d = alpha / (d ln 10),
    # d d / d pos = (pos - rx) / d; GBMU's step is grad U ln 10 / |R|
    diff = pos[:, None, :] - inp.rx_m
    d = np.hypot(diff[..., 0], diff[..., 1])
    p = model.predict_unclipped(d, inp.l_m, inp.nsv)
    assert np.all(p[inp.mask] > model.p_min)  # no clip active: U is smooth here
    a = model.alpha[np.minimum(inp.nsv, model.nsv_cap)]
    grad = np.einsum("br,brc->bc", np.where(inp.mask, (1 - p) * a / (d * LN10) / d, 0.0), diff)
    n_rx = inp.mask.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(step, grad * LN10 / n_rx, rtol=1e-12)
    # and central differences of the model's predicted utility
    util = SteeringUtility(inp, model)
    h = 1e-5
    fd = np.stack([(util(pos + h * e) - util(pos - h * e)) / (2 * h) for e in np.eye(2)], axis=1)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-10)


# ------------------------------------------------------------------ the study's variants


def test_study_reports_every_variant_against_the_optimum() -> None:
    methods = ["gbmu", *VARIANTS, "planner", "optimum"]
    s = run_study(
        "seven-node",
        preset("paper"),
        PAPER,
        None,
        iterations=300,
        delta=5.0,
        methods=methods,
        progress=False,
        judge="model",
    )
    m = s["methods"]
    assert set(m) == set(methods)
    best = m["optimum"]["mean_utility_gain"]
    for name in methods:
        assert m[name]["share_of_optimum"] == pytest.approx(m[name]["mean_utility_gain"] / best)
        assert m[name]["mean_utility_gain"] <= best + 1e-12  # the judge's global optimum bounds every method
    # judged by the steering model, the planner is the optimum, and small steps are never backed off
    assert m["planner"]["share_of_optimum"] == pytest.approx(1.0)
    assert m["gbmu-schedule"]["mean_utility_gain"] == m["gbmu"]["mean_utility_gain"] > 0
    with pytest.raises(ValueError, match="gbmu-logistic"):
        run_study("seven-node", preset("paper"), PAPER, None, methods=["gbmu-cubic"], progress=False)


# ------------------------------------------------------------------ the policy in the env


def _env_and_obs():  # type: ignore[no-untyped-def]
    from cv2x_marl.env.registry import make_parallel_env

    env = make_parallel_env("cv2x/SingleMover-v2", max_cycles=4, overrides=["sim.warmup_subframes=200"])
    obs, _ = env.reset(seed=3)
    return env, {"vehicle_0": obs["vehicle_0"]}


def test_policy_decay_counts_env_steps_since_reset() -> None:
    from cv2x_marl.policies.scripted import GbmuPolicy

    env, obs = _env_and_obs()
    # a small delta keeps the moves inside the action box, so the action is the scaled GBMU step
    policy = GbmuPolicy(PAPER, env.layout, env.max_step_m, delta=0.5, schedule=StepSchedule("decay", decay_k0=2.0))
    const = GbmuPolicy(PAPER, env.layout, env.max_step_m, delta=0.5)
    a0 = const.act(obs)["vehicle_0"]
    assert 0 < np.abs(a0).max() < 1
    first, second, third = (policy.act(obs)["vehicle_0"] for _ in range(3))
    np.testing.assert_array_equal(first, a0)  # delta_0 = delta
    np.testing.assert_allclose(second, a0 / 1.5, rtol=1e-6)  # delta_1 = delta / (1 + 1/2)
    np.testing.assert_allclose(third, a0 / 2.0, rtol=1e-6)  # delta_2 = delta / (1 + 2/2)
    policy.reset(0)
    np.testing.assert_array_equal(policy.act(obs)["vehicle_0"], a0)


def test_policy_backtracking_never_lowers_the_models_prediction() -> None:
    from cv2x_marl.env.observation import decode_observations
    from cv2x_marl.policies.scripted import GbmuPolicy

    env, obs = _env_and_obs()
    inputs = decode_observations(obs["vehicle_0"][None], env.layout)
    util = SteeringUtility(inputs, PAPER)
    for delta in (1.0, 1e3, 1e6, 1e9):
        policy = GbmuPolicy(PAPER, env.layout, env.max_step_m, delta=delta, schedule=StepSchedule("backtracking"))
        move_m = policy.act(obs)["vehicle_0"].astype(np.float64) * env.max_step_m
        assert util(move_m[None])[0] >= util(np.zeros((1, 2)))[0]
