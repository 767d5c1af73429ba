"""Behaviour references of issue 26 ("One env core"), recorded before the refactor (commit b9b8a2c).

The data in ``tests/data/reference_26/`` was written by ``tests/reference/record.py`` on the code before the
refactor; these tests replay the same cases on the current code and ask for the same results:

* ``env_trajectories.npz`` / ``env_cases.json``: episodes of every env id and version (``cv2x/Mobility-v0``
  ``-v1`` ``-v2`` through ``pettingzoo.make``, the AEC factories, ``cv2x/SingleMover-v0`` ``-v1`` ``-v2``
  through ``gymnasium.make``, which steps through the one-mover path, and the batched vector env through
  ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``) with the options that take
  different code paths (reward kinds and forms, ``plan_residual``, ``replan_every``, movers, drift bounds,
  truth LOS, link models, traffic mode on model lanes and on SUMO with offset and speed actions): per
  step the observations, rewards, terminations, truncations and every numeric ``info`` value.
* ``prr.json``: ``cv2x-marl simulate`` of every preset for seeds 0, 1, 2 (few subframes): the summary's
  results (PRR per node, mean, at distances and per 10 m bin, loss causes, SPS state at the start, counts).
* ``heldout_slice.json``: ``cv2x-marl evaluate`` of every policy of the held-out tables of
  ``docs/results.md`` (scripted ones and the ten shipped PPO models, both envs) on their first held-out
  episodes (``--seed 2026``): ``summary.json`` and ``episodes.csv``. The full tables are compared by
  ``benchmarks/check_references.py`` (about half an hour).

Only public entry points are used (env ids, ``cv2x_marl.env``'s factories, ``cv2x_marl.cli.main``), so the
tests survive a refactor that moves modules. Integers, booleans, strings, dtypes, shapes and keys are compared
exactly; floating-point values to a relative tolerance of ``FLOAT64_RTOL`` (float32 observations: ``FLOAT32_RTOL``,
a few float32 ulps). The refactor runs the same arithmetic in the same order, but numpy's reductions
(``sum`` / ``mean``) and transcendental functions take CPU-dependent SIMD paths (AVX2 against AVX-512: other
lane counts, so another summation order), which move aggregates such as Jain's index, a mean PRR or a
reward by one or two ulps between machines (seen: 7e-15 on a utility of -44, relative 1.6e-16, on an AMD
EPYC with AVX-512 against references recorded without it). Those tolerances are 10^4 times that, and 10^9
times below any change of behaviour (one packet more or less moves a PRR by 1e-3 or more).
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pettingzoo
import pytest

import cv2x_marl  # noqa: F401 - registers the env ids
from cv2x_marl import env as cv2x_env
from cv2x_marl.cli import main as cli_main

DATA = Path(__file__).resolve().parents[1] / "data" / "reference_26"
ROOT = Path(__file__).resolve().parents[2]
#: SUMO presets need libsumo and the sumo tools (as tests/env/test_env_sumo.py)
try:
    import libsumo  # noqa: F401
    import sumo  # noqa: F401

    HAVE_SUMO = True
except ImportError:
    HAVE_SUMO = False
SUMO_ENV = "CV2X_MARL_SUMO_CACHE"  # the SUMO network/route cache folder (an environment variable of the package)
#: summary.json entries that are not results (wall times, versions, the resolved configuration)
VOLATILE = ("runtime_s", "total_runtime_s", "versions", "config")

pytestmark = pytest.mark.filterwarnings("ignore")

#: relative tolerance of float64 values (results of CPU-dependent numpy reductions: see the module docstring)
FLOAT64_RTOL = 1e-12
#: absolute floor of the float64 comparison, for values that are 0 on one machine and 1e-17 on another
FLOAT64_ATOL = 1e-15
#: float32 observations: an input moved by one float64 ulp may round to the neighbouring float32
FLOAT32_RTOL = 1e-6


def same_array(got: np.ndarray, ref: np.ndarray) -> bool:
    """Equal arrays: exact for integers and booleans, float64 to ``FLOAT64_RTOL``, float32 to
    ``FLOAT32_RTOL`` (NaN equal to NaN in the same places, infinities exact)."""
    if got.dtype.kind != "f":
        return bool(np.array_equal(got, ref))
    rtol, atol = (FLOAT32_RTOL, 1e-7) if got.dtype == np.float32 else (FLOAT64_RTOL, FLOAT64_ATOL)
    return bool(np.allclose(got, ref, rtol=rtol, atol=atol, equal_nan=True))


def same_value(got: Any, ref: Any, where: str = "") -> list[str]:
    """Where two JSON-like values differ: floats to ``FLOAT64_RTOL``, everything else exactly (types
    included: an int is not a float)."""
    if isinstance(ref, dict):
        if not isinstance(got, dict) or got.keys() != ref.keys():
            return [f"{where}: keys {sorted(got) if isinstance(got, dict) else got!r} != {sorted(ref)}"]
        return [d for k in ref for d in same_value(got[k], ref[k], f"{where}/{k}")]
    if isinstance(ref, list):
        if not isinstance(got, list) or len(got) != len(ref):
            return [f"{where}: {got!r} != {ref!r}"]
        return [d for i, (g, r) in enumerate(zip(got, ref, strict=True)) for d in same_value(g, r, f"{where}[{i}]")]
    if isinstance(ref, float) and isinstance(got, float):
        if math.isnan(ref) and math.isnan(got):
            return []
        close = math.isclose(got, ref, rel_tol=FLOAT64_RTOL, abs_tol=FLOAT64_ATOL)
        return [] if close else [f"{where}: {got!r} != {ref!r}"]
    return [] if type(got) is type(ref) and got == ref else [f"{where}: {got!r} != {ref!r}"]


# ----------------------------------------------------------------------------------------------- cases
SUMO_SHORT = ["sim.warmup_subframes=200"]

#: every recorded env case: name -> (api, env id, keyword arguments, seed, steps)
#: api: ``parallel`` (pettingzoo.make), ``aec`` (the AEC factory of cv2x_marl.env), ``gym`` (gymnasium.make),
#: ``vec`` (gymnasium.make_vec with the vector entry point, 3 copies)
ENV_CASES: dict[str, tuple[str, str, dict[str, Any], int, int]] = {
    # cv2x/Mobility-v0 (ParallelEnv)
    "mobility-v0": ("parallel", "cv2x/Mobility-v0", {}, 3, 8),
    "mobility-v0-team": ("parallel", "cv2x/Mobility-v0", {"reward": "team"}, 4, 6),
    "mobility-v0-mixed-normalised": (
        "parallel",
        "cv2x/Mobility-v0",
        {"reward": "mixed", "local_ratio": 0.3, "normalise_reward": True, "p_min": 0.01},
        5,
        6,
    ),
    "mobility-v0-improvement-settle-truncation": (
        "parallel",
        "cv2x/Mobility-v0",
        {"reward_form": "improvement", "settle_steps": 2, "max_cycles": 6, "max_step_m": 20.0},
        6,
        6,
    ),
    "mobility-v0-movers-drift-roi-geometry": (
        "parallel",
        "cv2x/Mobility-v0",
        {"movers": [0, 3, 5], "max_drift_m": 12.0, "roi": True, "truth_los": "geometry", "n_neighbours": 6},
        7,
        6,
    ),
    "mobility-v0-threshold-wrap-inband-always": (
        "parallel",
        "cv2x/Mobility-v0",
        {
            "overrides": ["link.model=threshold", "radio.sensitivity_dbm=-95", "road.wrap_distances=true"],
            "truth_los": "always",
        },
        8,
        5,
    ),
    "mobility-v0-highway": (
        "parallel",
        "cv2x/Mobility-v0",
        {"preset": "highway", "overrides": ["vehicles.n_vehicles=12"], "n_neighbours": 5, "scale_m": 250.0},
        9,
        5,
    ),
    "mobility-v0-traffic": ("parallel", "cv2x/Mobility-v0", {"mode": "traffic", "max_cycles": 7}, 10, 7),
    "mobility-v0-traffic-drift-team": (
        "parallel",
        "cv2x/Mobility-v0",
        {"mode": "traffic", "max_drift_m": 4.0, "reward": "team", "reward_form": "improvement", "movers": [1, 2]},
        11,
        5,
    ),
    "mobility-v1": ("parallel", "cv2x/Mobility-v1", {}, 12, 6),
    "mobility-v1-privileged-team": ("parallel", "cv2x/Mobility-v1", {"privileged": True, "reward": "team"}, 13, 5),
    "mobility-v1-traffic": ("parallel", "cv2x/Mobility-v1", {"mode": "traffic"}, 14, 5),
    "mobility-v2": ("parallel", "cv2x/Mobility-v2", {}, 15, 6),
    "mobility-v2-plan-residual-replan-mixed": (
        "parallel",
        "cv2x/Mobility-v2",
        {"action_mode": "plan_residual", "replan_every": 3, "reward": "mixed", "reward_form": "utility"},
        16,
        7,
    ),
    # the AEC versions (parallel_to_aec over the same env)
    "mobility-v0-aec": ("aec", "env", {"max_cycles": 3}, 17, 3),
    "mobility-v2-aec": ("aec", "env_v2", {"max_cycles": 3}, 18, 3),
    # cv2x/SingleMover-v* (Gymnasium; the one-mover path ``step_mover`` unless noted), across truncations
    "singlemover-v0": ("gym", "cv2x/SingleMover-v0", {"max_cycles": 8}, 20, 20),
    "singlemover-v0-highway-wrap": (
        "gym",
        "cv2x/SingleMover-v0",
        {
            "preset": "highway",
            "overrides": ["vehicles.n_vehicles=12", "road.wrap_distances=true"],
            "n_neighbours": 5,
            "max_cycles": 10,
        },
        21,
        12,
    ),
    "singlemover-v0-team-fullstep": ("gym", "cv2x/SingleMover-v0", {"reward": "team", "max_cycles": 6}, 22, 8),
    "singlemover-v0-traffic-fullstep": ("gym", "cv2x/SingleMover-v0", {"mode": "traffic", "max_cycles": 6}, 23, 8),
    "singlemover-v1": ("gym", "cv2x/SingleMover-v1", {"max_cycles": 8}, 24, 12),
    "singlemover-v1-privileged-always-drift": (
        "gym",
        "cv2x/SingleMover-v1",
        {"privileged": True, "truth_los": "always", "max_drift_m": 12.0, "roi": True, "max_cycles": 8},
        25,
        10,
    ),
    "singlemover-v2": ("gym", "cv2x/SingleMover-v2", {"max_cycles": 8}, 26, 12),
    "singlemover-v2-plan-residual-settle": (
        "gym",
        "cv2x/SingleMover-v2",
        {"action_mode": "plan_residual", "reward_form": "utility", "settle_steps": 3, "max_cycles": 8},
        27,
        12,
    ),
    "singlemover-v2-replan": ("gym", "cv2x/SingleMover-v2", {"replan_every": 3, "max_cycles": 8}, 28, 10),
    # K = 3 copies through the vector entry point (batched unless replan_every), NextStep autoreset
    "vector-v0": ("vec", "cv2x/SingleMover-v0", {"max_cycles": 5}, 30, 12),
    "vector-v0-threshold": (
        "vec",
        "cv2x/SingleMover-v0",
        {"overrides": ["link.model=threshold", "radio.sensitivity_dbm=-95"], "max_cycles": 5},
        31,
        8,
    ),
    "vector-v1": ("vec", "cv2x/SingleMover-v1", {"max_cycles": 5}, 32, 8),
    "vector-v2-plan-residual": (
        "vec",
        "cv2x/SingleMover-v2",
        {"action_mode": "plan_residual", "settle_steps": 1, "max_cycles": 5},
        33,
        8,
    ),
    "vector-v2-sameStep": ("vec", "cv2x/SingleMover-v2", {"max_cycles": 4, "autoreset_mode": "SameStep"}, 34, 7),
    "vector-v2-replan-loop": ("vec", "cv2x/SingleMover-v2", {"replan_every": 2, "max_cycles": 4}, 35, 6),
}
if HAVE_SUMO:
    ENV_CASES.update(
        {
            "mobility-v0-sumo-snapshot": (
                "parallel",
                "cv2x/Mobility-v0",
                {"preset": "sumo-grid", "overrides": SUMO_SHORT, "max_cycles": 4},
                40,
                4,
            ),
            "mobility-v0-sumo-traffic-offset": (
                "parallel",
                "cv2x/Mobility-v0",
                {"preset": "sumo-grid", "overrides": SUMO_SHORT, "mode": "traffic", "max_cycles": 5},
                41,
                5,
            ),
            "mobility-v0-sumo-traffic-speed": (
                "parallel",
                "cv2x/Mobility-v0",
                {
                    "preset": "sumo-grid",
                    "overrides": SUMO_SHORT,
                    "mode": "traffic",
                    "traffic_action": "speed",
                    "max_cycles": 5,
                },
                42,
                5,
            ),
        }
    )

PRESETS = ("paper", "highway", "highway-legacy", "sumo-grid", "sumo-highway", "sumo-grid-trips")
SUMO_PRESETS = ("sumo-grid", "sumo-highway", "sumo-grid-trips")
PRR_SEEDS = (0, 1, 2)
PRR_SUBFRAMES = 400
#: the runs the test suite replays: all but seeds 1-2 of the two slow SUMO presets (10-15 s each, their
#: SUMO warm-up); benchmarks/check_references.py replays every run of prr.json
PRR_SLOW = ("sumo-highway", "sumo-grid-trips")
PRR_TESTED = [(p, s) for p in PRESETS for s in PRR_SEEDS if p not in PRR_SLOW or s == 0]

HELDOUT_SEED = "2026"
HELDOUT_EPISODES = {"single": "3", "multi": "1"}


def heldout_runs() -> dict[str, list[str]]:
    """The rows of docs/results.md's held-out tables (benchmarks/check_references.py's), on few episodes."""
    spec = importlib.util.spec_from_file_location("check_references", ROOT / "benchmarks" / "check_references.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.SEED == HELDOUT_SEED
    return dict(module.runs(HELDOUT_EPISODES["single"], HELDOUT_EPISODES["multi"]))


# ------------------------------------------------------------------------------------------ playing
def _numeric(value: Any) -> bool:
    return isinstance(value, bool | int | float | np.number | np.bool_)


def _actions(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Actions in [-1.3, 1.3] (some outside the box: clipping is part of the behaviour)."""
    return rng.uniform(-1.3, 1.3, shape).astype(np.float32)


class _Recorder:
    """Collects one case's events (reset or step) as arrays."""

    def __init__(self) -> None:
        self.rows: dict[str, list[Any]] = {}

    def add(self, **fields: Any) -> None:
        for k, v in fields.items():
            self.rows.setdefault(k, []).append(np.asarray(v))

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: np.stack(v) for k, v in self.rows.items()}


def _agent_infos(infos: dict[str, dict[str, Any]], agents: list[str]) -> dict[str, np.ndarray]:
    keys = sorted({k for a in agents for k in infos.get(a, {})})
    out = {}
    for k in keys:
        vals = [infos[a][k] for a in agents]
        assert all(_numeric(v) for v in vals), f"non-numeric info {k}"
        out[f"info.{k}"] = np.asarray(vals, dtype=np.float64)
    return out


def _play_parallel(env_id: str, kw: dict[str, Any], seed: int, steps: int) -> dict[str, np.ndarray]:
    env = pettingzoo.make("parallel", env_id, **kw)
    agents = list(env.possible_agents)
    rng = np.random.default_rng(seed)
    rec = _Recorder()
    obs, infos = env.reset(seed=seed)
    n = len(agents)
    rec.add(
        event=0,
        obs=np.stack([obs[a] for a in agents]),
        reward=np.zeros(n),
        terminated=np.zeros(n, bool),
        truncated=np.zeros(n, bool),
        **_agent_infos(infos, agents),
    )
    for _ in range(steps):
        if not env.agents:
            obs, infos = env.reset()
            rec.add(
                event=0,
                obs=np.stack([obs[a] for a in agents]),
                reward=np.zeros(n),
                terminated=np.zeros(n, bool),
                truncated=np.zeros(n, bool),
                **_agent_infos(infos, agents),
            )
            continue
        act = _actions(rng, (n, 2))
        obs, rew, term, trunc, infos = env.step({a: act[i] for i, a in enumerate(agents)})
        rec.add(
            event=1,
            obs=np.stack([obs[a] for a in agents]),
            reward=np.array([rew[a] for a in agents], dtype=np.float64),
            terminated=np.array([term[a] for a in agents]),
            truncated=np.array([trunc[a] for a in agents]),
            **_agent_infos(infos, agents),
        )
    env.close()
    return rec.arrays()


def _play_aec(factory: str, kw: dict[str, Any], seed: int, steps: int) -> dict[str, np.ndarray]:
    env = getattr(cv2x_env, factory)(**kw)
    rng = np.random.default_rng(seed)
    rec = _Recorder()
    env.reset(seed=seed)
    for _ in range(steps * len(env.possible_agents) + len(env.possible_agents)):
        if not env.agents:
            break
        obs, rew, term, trunc, info = env.last()
        rec.add(
            obs=obs,
            reward=np.float64(rew),
            terminated=term,
            truncated=trunc,
            **{f"info.{k}": np.float64(v) for k, v in sorted(info.items()) if _numeric(v)},
        )
        env.step(None if (term or trunc) else _actions(rng, (2,)))
    env.close()
    return rec.arrays()


def _play_gym(env_id: str, kw: dict[str, Any], seed: int, steps: int) -> dict[str, np.ndarray]:
    env = gymnasium.make(env_id, **kw)
    rng = np.random.default_rng(seed)
    rec = _Recorder()

    def info_arrays(info: dict[str, Any]) -> dict[str, np.ndarray]:
        return {f"info.{k}": np.float64(v) for k, v in sorted(info.items()) if _numeric(v)}

    obs, info = env.reset(seed=seed)
    rec.add(event=0, obs=obs, reward=np.float64(0.0), terminated=False, truncated=False, **info_arrays(info))
    for _ in range(steps):
        obs, rew, term, trunc, info = env.step(_actions(rng, (2,)))
        rec.add(event=1, obs=obs, reward=np.float64(rew), terminated=term, truncated=trunc, **info_arrays(info))
        if term or trunc:  # the next episode's seed comes from the env's own generator
            obs, info = env.reset()
            rec.add(event=0, obs=obs, reward=np.float64(0.0), terminated=False, truncated=False, **info_arrays(info))
    env.close()
    return rec.arrays()


def _play_vec(env_id: str, kw: dict[str, Any], seed: int, steps: int, copies: int = 3) -> dict[str, np.ndarray]:
    envs = gymnasium.make_vec(env_id, num_envs=copies, vectorization_mode="vector_entry_point", **kw)
    rng = np.random.default_rng(seed)
    rec = _Recorder()

    def info_arrays(info: dict[str, Any]) -> dict[str, np.ndarray]:
        out = {}
        for k, v in sorted(info.items()):
            if k.startswith("final_"):  # SameStep: the ended episodes' last observation and info
                if k == "final_obs":
                    out["final_obs"] = np.stack(
                        [
                            np.asarray(o)
                            if o is not None
                            else np.full(envs.single_observation_space.shape, np.nan, np.float32)
                            for o in v
                        ]
                    )
                continue
            arr = np.asarray(v)
            if arr.dtype != object:
                out[f"info.{k}"] = arr
        return out

    obs, info = envs.reset(seed=seed)
    z = np.zeros(copies, bool)
    rec.add(event=0, obs=obs, reward=np.zeros(copies), terminated=z, truncated=z, **info_arrays(info))
    keys = set(rec.rows)
    for _ in range(steps):
        obs, rew, term, trunc, info = envs.step(_actions(rng, (copies, 2)))
        fields = info_arrays(info)
        if "final_obs" in fields and "final_obs" not in keys:  # same keys every step: fill the earlier ones
            rec.rows["final_obs"] = [np.full_like(fields["final_obs"], np.nan) for _ in rec.rows["obs"]]
            keys.add("final_obs")
        if "final_obs" in keys and "final_obs" not in fields:
            fields["final_obs"] = np.full((copies, *envs.single_observation_space.shape), np.nan, np.float32)
        rec.add(event=1, obs=obs, reward=rew, terminated=term, truncated=trunc, **fields)
    envs.close()
    return rec.arrays()


def play_env_case(name: str) -> dict[str, np.ndarray]:
    """Play one case of :data:`ENV_CASES`; the arrays of its events (reset or step), keyed by field."""
    api, env_id, kw, seed, steps = ENV_CASES[name]
    play: Callable[..., dict[str, np.ndarray]] = {
        "parallel": _play_parallel,
        "aec": _play_aec,
        "gym": _play_gym,
        "vec": _play_vec,
    }[api]
    return play(env_id, dict(kw), seed, steps)


def simulate_summary(preset: str, seed: int, out: Path) -> dict[str, Any]:
    """``cv2x-marl simulate`` of a preset (few subframes, no links file): its summary without wall times."""
    rc = cli_main(
        [
            *("simulate", "--preset", preset, "--seed", str(seed), "--subframes", str(PRR_SUBFRAMES)),
            *("--links", "off", "--out", str(out), "--quiet", "--overwrite"),
        ]
    )
    assert rc in (0, None)
    summary = json.loads((out / "summary.json").read_text())
    return {k: v for k, v in summary.items() if k not in VOLATILE}


def evaluate_run(args: list[str], out: Path) -> dict[str, Any]:
    """``cv2x-marl evaluate ARGS`` from the repository root: summary (without wall time) and episode rows."""
    cwd = os.getcwd()
    os.chdir(ROOT)  # the model paths are relative to the repository root
    try:
        rc = cli_main(["evaluate", *args, "--out", str(out), "--quiet", "--overwrite"])
    finally:
        os.chdir(cwd)
    assert rc in (0, None)
    summary = {k: v for k, v in json.loads((out / "summary.json").read_text()).items() if k not in VOLATILE}
    with open(out / "episodes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return {"summary": summary, "episodes": rows}


@pytest.fixture(autouse=True, scope="module")
def _sumo_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    mp = pytest.MonkeyPatch()
    mp.setenv(SUMO_ENV, str(tmp_path_factory.mktemp("sumo-cache")))
    yield None
    mp.undo()


# ------------------------------------------------------------------------------------------- tests
def _recorded_env() -> tuple[dict[str, Any], Any]:
    cases = json.loads((DATA / "env_cases.json").read_text())
    return cases, np.load(DATA / "env_trajectories.npz")


def test_recorded_env_cases_are_the_cases_replayed() -> None:
    cases, _ = _recorded_env()
    want = {k: v for k, v in cases.items() if HAVE_SUMO or not k.startswith("mobility-v0-sumo")}
    replayed = {k: list(v) for k, v in json.loads(json.dumps(ENV_CASES)).items()}
    assert replayed == want


@pytest.mark.parametrize("name", list(ENV_CASES))
def test_env_episode_equals_reference(name: str) -> None:
    """Observations (float32), rewards, terminations, truncations and numeric infos of every event are the
    recorded ones (same keys, dtypes and shapes; values as :func:`same_array`)."""
    _, data = _recorded_env()
    ref = {k.split("/", 1)[1]: data[k] for k in data.files if k.split("/", 1)[0] == name}
    got = play_env_case(name)
    assert sorted(got) == sorted(ref)
    for k in ref:
        assert got[k].dtype == ref[k].dtype, k
        assert got[k].shape == ref[k].shape, k
        assert same_array(got[k], ref[k]), f"{name}: {k} differs"


def test_prr_reference_has_every_preset_and_seed() -> None:
    ref = json.loads((DATA / "prr.json").read_text())
    assert ref["subframes"] == PRR_SUBFRAMES
    assert sorted(ref["runs"]) == sorted(f"{p}/seed{s}" for p in PRESETS for s in PRR_SEEDS)


@pytest.mark.parametrize(("preset", "seed"), PRR_TESTED)
def test_simulate_prr_of_preset_equals_reference(preset: str, seed: int, tmp_path: Path) -> None:
    """PRR per node, mean, at distances, per bin, loss causes, SPS state and counts (:func:`same_value`)."""
    if preset in SUMO_PRESETS and not HAVE_SUMO:
        pytest.skip("SUMO is not installed")
    ref = json.loads((DATA / "prr.json").read_text())
    got = json.loads(json.dumps(simulate_summary(preset, seed, tmp_path / str(seed))))
    assert same_value(got, ref["runs"][f"{preset}/seed{seed}"]) == []


def _cell(text: str) -> Any:
    """A CSV cell as the value it writes: an int, a float (repr), or the text itself."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _same_cells(got: dict[str, Any], ref: dict[str, Any]) -> None:
    assert same_value(got["summary"], ref["summary"]) == []
    assert len(got["episodes"]) == len(ref["episodes"])
    for g, r in zip(got["episodes"], ref["episodes"], strict=True):
        assert g.keys() == r.keys()
        for k in r:  # the CSV's text of each float is its repr: read back, then compared as values
            assert same_value(_cell(g[k]), _cell(r[k]), k) == []


@pytest.mark.parametrize("run", list(heldout_runs()))
def test_heldout_table_slice_equals_reference(run: str, tmp_path: Path) -> None:
    """The first held-out episodes of every row of the held-out tables (shipped PPO models included)."""
    ref = json.loads((DATA / "heldout_slice.json").read_text())
    assert ref["runs"][run]["args"] == heldout_runs()[run]
    got = evaluate_run(heldout_runs()[run], tmp_path / run)
    _same_cells(got, ref["runs"][run])


def test_full_heldout_tables_recorded_are_rows_of_the_tables() -> None:
    """The full tables (benchmarks/check_references.py --record): one folder per row of the tables."""
    folder = DATA / "heldout"
    names = sorted(p.name for p in folder.iterdir() if p.is_dir())
    assert names and set(names) <= set(heldout_runs())
    for name in names:
        s = json.loads((folder / name / "summary.json").read_text())
        assert s["episodes"] == (144 if name.startswith("single") else 48)
        assert math.isfinite(s["mean_utility_gain"])


def test_comparison_tolerates_ulps_and_nothing_more() -> None:
    """The comparators accept a move of a few ulps (another CPU's summation order) and refuse a change of
    behaviour, a change of type or a missing key."""
    u = -44.47164506371049
    assert same_value({"u": u, "n": 3}, {"u": np.nextafter(u, 0.0) + 0.0, "n": 3}) == []
    assert same_value({"u": u * (1 + 1e-9)}, {"u": u}) != []
    assert same_value({"prr": 0.5, "n": 3}, {"prr": 0.501, "n": 3}) != []
    assert same_value({"n": 3.0}, {"n": 3}) != []
    assert same_value({"a": 1}, {"a": 1, "b": 2}) != []
    assert same_value([float("nan")], [float("nan")]) == []
    x = np.array([0.25, -3.5, np.nan], dtype=np.float64)
    assert same_array(x + np.array([5e-17, 0.0, 0.0]), x)
    assert not same_array(x + np.array([1e-6, 0.0, 0.0]), x)
    assert not same_array(np.array([1, 2]), np.array([1, 3]))
    f32 = np.array([0.1, 2.5], dtype=np.float32)
    assert same_array(np.nextafter(f32, np.float32(1.0)), f32)
    assert not same_array(f32 + np.float32(1e-3), f32)
