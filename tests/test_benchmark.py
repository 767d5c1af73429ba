"""The benchmark protocol: the task table and its seed lists (cv2x_marl.env.tasks), `evaluate`'s
--seeds / --env-option / several runs with IQM and bootstrap intervals, and `cv2x-marl benchmark`
(its table against an independent recomputation from benchmark.csv, and against `evaluate`)."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.stats

from cv2x_marl import stats
from cv2x_marl.env import tasks
from cv2x_marl.env.registry import ENV_IDS
from cv2x_marl.experiments import benchmark
from cv2x_marl.experiments import evaluate as ev

#: the tasks' options in these tests: 10 steps instead of 100 (the reachable square, and so the ceiling's
#: search, 10x smaller in side); everything else is the task's
QUICK_OPTIONS = {**tasks.BASE_OPTIONS, "max_cycles": 10}
MODELS = Path(__file__).resolve().parents[1] / "agents" / "models"


def stand_in_tasks() -> dict[str, tasks.Task]:
    """The task table with :data:`QUICK_OPTIONS` (the same ids, names, methods, refusals and seed lists)."""
    return {n: tasks.Task(**{**t.__dict__, "options": QUICK_OPTIONS}) for n, t in tasks.TASKS.items()}


# ------------------------------------------------------------------------------------------ task table
def test_seed_lists_sizes_distinct_and_disjoint() -> None:
    for task in tasks.TASKS.values():
        train, held = task.train_seeds, task.heldout_seeds
        assert len(held) == tasks.N_HELDOUT == 48 and len(train) == tasks.N_TRAIN == 4096
        assert len(set(held)) == len(held) and len(set(train)) == len(train)
        assert not set(train) & set(held)
        assert all(isinstance(s, int) and 0 <= s < 2**32 for s in (*train, *held))
    a, b = tasks.TASKS["singlemover"], tasks.TASKS["cooperative"]
    assert not set(a.heldout_seeds) & set(b.heldout_seeds)  # each task has its own lists


def test_seed_lists_are_deterministic_constants() -> None:
    # the state of SeedSequence(PROTOCOL_ENTROPY, spawn_key=(crc32(task), kind)), recomputed here
    import zlib

    for name, task in tasks.TASKS.items():
        ss = np.random.SeedSequence(tasks.PROTOCOL_ENTROPY, spawn_key=(zlib.crc32(name.encode()), 0))
        assert task.heldout_seeds == tuple(int(w) for w in ss.generate_state(48 + 64, dtype=np.uint32)[:48])
        assert task.train_seeds == tasks.TRAIN_SEEDS  # one training list, disjoint from every held-out list
    every_heldout = tuple(s for held in tasks.HELDOUT_SEEDS.values() for s in held)
    assert tasks.TRAIN_SEEDS == tasks.seed_list("protocol", "train", tasks.N_TRAIN, every_heldout)
    assert not set(tasks.TRAIN_SEEDS) & set(every_heldout)
    assert tasks.training_pool(3) == tasks.TRAIN_SEEDS[:3]
    for bad in (0, -1, tasks.N_TRAIN + 1, 2.0, True):
        with pytest.raises(ValueError, match="start_pool"):
            tasks.training_pool(bad)
    # pinned: a change of the derivation changes every published benchmark number
    assert tasks.TASKS["singlemover"].heldout_seeds[:2] == PINNED["singlemover"]
    assert tasks.TASKS["cooperative"].heldout_seeds[:2] == PINNED["cooperative"]
    assert tasks.TASKS["singlemover"].train_seeds[:2] == (2716985552, 2947267413)
    # the whole training list, as it was before the resource task's held-out list was added (it did not change)
    import hashlib

    assert hashlib.sha1(repr(tasks.TRAIN_SEEDS).encode()).hexdigest() == "65a0ac5f246ecab5a991e8e55bf5652176cc9df9"


#: the first two held-out seeds of each task, as first drawn (literal: the derivation must not change)
PINNED = {"singlemover": (238536871, 3978540970), "cooperative": (2811444015, 1893821544)}


def test_seed_list_skips_excluded_and_repeated_values() -> None:
    held = tasks.seed_list("x", "heldout", 5)
    train = tasks.seed_list("x", "train", 5, exclude=held[:3] + tasks.seed_list("x", "train", 2))
    raw = tasks.seed_list("x", "train", 7)
    assert train == raw[2:7]  # the first two drawn are excluded: the list moves on
    with pytest.raises(ValueError, match="kind must be one of heldout, train"):
        tasks.seed_list("x", "test", 3)


def test_task_table_entries() -> None:
    sm, co = tasks.TASKS["singlemover"], tasks.TASKS["cooperative"]
    assert sm.env_id == tasks.TASK_ENV_IDS["singlemover"] == "cv2x/SingleMover-v3"
    assert co.env_id == tasks.TASK_ENV_IDS["cooperative"] == "cv2x/Cooperative-v0"
    assert sm.methods == ("static", "random", "gbmu", "sensing")
    assert co.methods == ("static", "random", "gbmu", "sensing", "best-response")
    assert sm.ceiling == co.ceiling == "optimum"
    for t in (sm, co):
        assert t.available and t.env_id in ENV_IDS  # both ids registered in this version
        assert dict(t.options) == {"preset": "paper", "max_cycles": 100, "max_step_m": 5.0}
    tr = tasks.TASKS["traffic"]
    assert tr.env_id == tasks.TASK_ENV_IDS["traffic"] == "cv2x/Traffic-v0" and tr.available
    assert tr.methods == ("static", "random", "gbmu", "sensing") and tr.ceiling == "optimum"
    assert dict(tr.options) == {"preset": "paper", "max_cycles": 100, "max_step_m": 5.0}
    assert not tasks.PENDING_TASKS


def test_a_refused_policy_names_itself_the_task_and_the_allowed_ones() -> None:
    with pytest.raises(ValueError) as err:
        tasks.TASKS["singlemover"].check_policy("best-response")
    msg = str(err.value)
    assert "'best-response'" in msg and "singlemover" in msg and "cv2x/SingleMover-v3" in msg
    assert "allowed: static, random, gbmu, sensing, optimum, ppo:PATH" in msg
    tasks.TASKS["cooperative"].check_policy("best-response")  # accepted there
    with pytest.raises(ValueError, match="policy 'planner' cannot run on task traffic"):
        tasks.TASKS["traffic"].check_policy("planner")
    with pytest.raises(ValueError, match="unknown task 'nope'; tasks: singlemover, cooperative, traffic"):
        tasks.get_task("nope")


def test_evaluate_refuses_a_policy_its_task_refuses(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tasks, "TASKS", stand_in_tasks())
    with pytest.raises(ValueError, match="policy 'best-response' cannot run on task singlemover"):
        ev.evaluate("cv2x/SingleMover-v3", "best-response", 1, 0, progress=False)


# ------------------------------------------------------------------------------------ evaluate's flags
def test_parse_seeds(monkeypatch: pytest.MonkeyPatch) -> None:
    assert ev.parse_seeds("3, 1,2", None) == (3, 1, 2)
    assert ev.parse_seeds("7 8", None) == (7, 8)
    monkeypatch.setattr(tasks, "TASKS", stand_in_tasks())
    assert ev.parse_seeds("heldout", "cv2x/SingleMover-v3") == tasks.TASKS["singlemover"].heldout_seeds
    assert ev.parse_seeds("train", "cv2x/Cooperative-v0") == tasks.TASKS["cooperative"].train_seeds
    for text, match in (
        ("1,x", "integers separated by commas"),
        ("-1", r"integers in \[0, 4294967295\]"),
        ("4294967296", r"integers in \[0, 4294967295\]"),
        ("1,1", "repeated seed"),
        ("", r"integers in \[0"),
    ):
        with pytest.raises(ValueError, match=match):
            ev.parse_seeds(text, None)
    with pytest.raises(ValueError, match="--seeds heldout: --env cv2x/SingleMover-v1 is no task's env"):
        ev.parse_seeds("heldout", "cv2x/SingleMover-v1")
    with pytest.raises(ValueError, match="--seeds heldout: give --env"):
        ev.parse_seeds("heldout", None)


def test_parse_env_options() -> None:
    got = ev.parse_env_options(["movers=[0, 2]", "scale_m=50", "replan_every=null", "reward=team"])
    assert got == {"movers": [0, 2], "scale_m": 50, "replan_every": None, "reward": "team"}
    with pytest.raises(ValueError, match="unknown env argument 'speed'; allowed: preset, overrides, config"):
        ev.parse_env_options(["speed=3"])
    with pytest.raises(ValueError, match="--env-option max_cycles: set it with --max-cycles"):
        ev.parse_env_options(["max_cycles=3"], ev.EVALUATE_FLAGS)
    with pytest.raises(ValueError, match="given twice"):
        ev.parse_env_options(["scale_m=1", "scale_m=2"])
    with pytest.raises(ValueError, match="expects key=value"):
        ev.parse_env_options(["scale_m"])


def test_env_option_values_are_checked_by_the_env_before_the_folder(tmp_path: Path) -> None:
    out = tmp_path / "run"
    with pytest.raises(ValueError, match="invalid env argument scale_m=-1"):
        ev.evaluate(None, "static", 1, 0, out, ev.parse_env_options(["scale_m=-1"]), progress=False)
    assert not out.exists()


def test_expand_policies(tmp_path: Path) -> None:
    for name in ("b", "a"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "model.zip").write_bytes(b"")
    got = ev.expand_policies([f"ppo:{tmp_path}/*/model.zip"])
    assert got == [f"ppo:{tmp_path}/a/model.zip", f"ppo:{tmp_path}/b/model.zip"]
    with pytest.raises(ValueError, match="no file matches"):
        ev.expand_policies([f"ppo:{tmp_path}/none*/model.zip"])
    with pytest.raises(ValueError, match="given twice"):
        ev.expand_policies(["gbmu", "gbmu"])
    with pytest.raises(ValueError, match="several policies are the training runs of one learned method"):
        ev.evaluate(None, ["gbmu", "static"], 1, 0, progress=False)


def test_seeds_give_the_protocol_statistics_of_the_rows(tmp_path: Path) -> None:
    seeds = [11, 12, 13, 14, 15]
    summary = ev.evaluate(
        "cv2x/SingleMover-v2", "gbmu", 0, 0, tmp_path / "e", progress=False, seeds=seeds, vs_optimum=True
    )
    with open(tmp_path / "e" / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["seed"]) for r in rows] == seeds and "run" not in rows[0] and "optimum_gain" not in rows[0]
    assert summary["episodes"] == 5 and summary["seed"] is None and summary["seeds"] == seeds and summary["runs"] == 1
    ug = np.array([float(r["utility_gain"]) for r in rows])
    u0 = np.array([float(r["utility_start"]) for r in rows])
    uo = np.array([float(r["utility_optimum"]) for r in rows])
    assert summary["iqm_utility_gain"] == pytest.approx(scipy.stats.trim_mean(ug, 0.25), rel=1e-12)
    assert summary["ci95_utility_gain"] == list(stats.bootstrap_ci(ug, np.random.default_rng(0))[1:])
    share = ug / ((uo - u0) / np.abs(u0))
    assert summary["iqm_share_of_optimum"] == pytest.approx(scipy.stats.trim_mean(share, 0.25), rel=1e-9)
    lo, hi = summary["ci95_share_of_optimum"]
    assert lo <= summary["iqm_share_of_optimum"] <= hi
    # the same episodes through the default path: the same per-episode numbers, the old summary keys only
    legacy = ev.evaluate("cv2x/SingleMover-v2", "gbmu", 2, 0, progress=False)
    assert not set(legacy) & set(ev.PROTOCOL_KEYS) - {"seeds"} and "seeds" not in legacy


@pytest.mark.skipif(not (MODELS / "single_seed1" / "model.zip").exists(), reason="shipped models absent")
def test_several_runs_are_pooled_over_runs_and_episodes(tmp_path: Path) -> None:
    specs = [f"ppo:{MODELS}/single_seed0/model.zip", f"ppo:{MODELS}/single_seed1/model.zip"]
    summary = ev.evaluate(None, specs, 0, 0, tmp_path / "e", progress=False, seeds=[5, 6, 7])
    with open(tmp_path / "e" / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(int(r["run"]), int(r["seed"])) for r in rows] == [(0, 5), (0, 6), (0, 7), (1, 5), (1, 6), (1, 7)]
    grid = np.array([float(r["utility_gain"]) for r in rows]).reshape(2, 3)
    assert summary["runs"] == 2 and summary["policy"] == specs and summary["env"] == "cv2x/SingleMover-v2"
    assert summary["iqm_utility_gain"] == pytest.approx(scipy.stats.trim_mean(grid.ravel(), 0.25), rel=1e-12)
    assert summary["ci95_utility_gain"] == list(stats.bootstrap_ci(grid, np.random.default_rng(0))[1:])
    one = ev.evaluate(None, specs[1], 0, 0, progress=False, seeds=[5, 6, 7])  # run 1 alone: its own rows
    assert one["mean_utility_gain"] == pytest.approx(float(np.mean(grid[1])), rel=1e-12)


# ------------------------------------------------------------------------------------------- benchmark
def _read_csv(path: Path) -> list[dict[str, Any]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_benchmark_table_equals_a_recomputation_and_evaluate(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import cv2x_marl.parallel

    def no_ray(*a: Any, **k: Any) -> Any:
        raise AssertionError("one worker runs without Ray")

    monkeypatch.setattr(cv2x_marl.parallel, "ray_session", no_ray)
    # traffic: tests/env/test_traffic.py; resource (other methods, gains against sps): tests/env/test_resource.py
    table = {n: t for n, t in stand_in_tasks().items() if n not in ("traffic", "resource")}
    out = tmp_path / "bench"
    summary = benchmark.run_benchmark(out, methods=["static", "gbmu"], episodes=2, progress=False, task_table=table)
    assert {p.name for p in out.iterdir()} >= {"benchmark.csv", "summary.json", "table.md", "benchmark.png"}
    assert json.loads((out / "summary.json").read_text())["tasks"] == json.loads(json.dumps(summary["tasks"]))
    rows = _read_csv(out / "benchmark.csv")
    assert len(rows) == 2 * 3 * 2  # tasks x (2 methods + the ceiling) x episodes
    text = (out / "table.md").read_text()
    for name, task in table.items():
        mine = [r for r in rows if r["task"] == name]
        assert [int(r["seed"]) for r in mine if r["method"] == "optimum"] == list(task.heldout_seeds[:2])
        ceiling = np.array([float(r["utility_gain"]) for r in mine if r["method"] == "optimum"])
        for method in ("static", "gbmu", "optimum"):
            sel = [r for r in mine if r["method"] == method]
            ug = np.array([float(r["utility_gain"]) for r in sel])
            share = ug / ceiling
            got = summary["tasks"][name]["methods"][method]
            assert got["iqm_utility_gain"] == pytest.approx(scipy.stats.trim_mean(ug, 0.25), rel=1e-12, abs=1e-15)
            assert got["iqm_share_of_ceiling"] == pytest.approx(scipy.stats.trim_mean(share, 0.25), rel=1e-12)
            assert got["ci95_utility_gain"] == list(stats.bootstrap_ci(ug[None, :], np.random.default_rng(0))[1:])
            assert got["mean_prr"] == pytest.approx(np.mean([float(r["prr_end"]) for r in sel]), rel=1e-12)
            line = next(ln for ln in text.splitlines() if ln.startswith(f"| {method} |") and ln in _section(text, name))
            cells = [c.strip() for c in line.strip("|").split("|")]
            lo, hi = got["ci95_utility_gain"]
            assert cells[2:4] == [f"{100 * got['iqm_utility_gain']:+.1f}", f"[{100 * lo:+.1f}, {100 * hi:+.1f}]"]
            assert cells[4] == f"{100 * got['iqm_share_of_ceiling']:.1f}" and cells[6] == f"{got['mean_prr']:.4f}"
            if method != "gbmu":  # `evaluate` runs the same loop for every method: one cross-check per task
                continue
            # the same method through `evaluate` on the same seeds: the same episodes and statistics
            e = ev.evaluate(
                task.env_id, method, 0, 0, None, dict(task.options), progress=False, seeds=list(task.heldout_seeds[:2])
            )
            assert e["iqm_utility_gain"] == got["iqm_utility_gain"]
            assert e["ci95_utility_gain"] == got["ci95_utility_gain"]
            assert e["mean_utility_gain"] == pytest.approx(got["mean_utility_gain"], rel=1e-12, abs=1e-15)
            assert e["mean_prr_end"] == pytest.approx(got["mean_prr"], rel=1e-12)
        assert summary["tasks"][name]["methods"]["optimum"]["iqm_share_of_ceiling"] == 1.0
    # the aggregate over tasks: the tasks are strata of the pooled share
    shares = [
        np.array([[float(r["share_of_ceiling"]) for r in rows if r["task"] == n and r["method"] == "gbmu"]])
        for n in table
    ]
    agg = summary["all_tasks"]["gbmu"]
    assert agg["iqm_share_of_ceiling"] == pytest.approx(
        scipy.stats.trim_mean(np.concatenate(shares, axis=1), 0.25, axis=None)
    )


def _section(text: str, task: str) -> str:
    start = text.index(f"### {task} ")
    end = text.find("### ", start + 4)
    return text[start : end if end > 0 else None]


def test_benchmark_over_workers_gives_the_same_rows(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--workers 2 goes through Ray (here a stand-in that runs the remote calls in order) and gives the
    same rows as one worker."""
    import contextlib

    import cv2x_marl.parallel

    calls: dict[str, Any] = {}

    class Ref:
        def __init__(self, value: Any) -> None:
            self.value = value

    class FakeRay:
        def remote(self, num_cpus: int) -> Any:
            def wrap(fn: Any) -> Any:
                class R:
                    @staticmethod
                    def remote(job: dict[str, Any]) -> Any:
                        return Ref(fn(job))  # hashable by identity, as Ray's ObjectRef

                return R

            return wrap

        def wait(self, refs: list[Any], num_returns: int) -> tuple[list[Any], list[Any]]:
            return refs[-1:], refs[:-1]  # the last first: results must go back in job order

        def get(self, ref: Any) -> Any:
            return ref.value

    @contextlib.contextmanager
    def fake_session(address: str | None = None, num_cpus: int | None = None) -> Any:
        calls["address"], calls["num_cpus"] = address, num_cpus
        yield FakeRay()

    monkeypatch.setattr(cv2x_marl.parallel, "ray_session", fake_session)
    monkeypatch.setattr(cv2x_marl.parallel, "usable_cpus", lambda: 2)  # --workers 2 on any machine
    table = {"singlemover": stand_in_tasks()["singlemover"]}
    kw: dict[str, Any] = {"methods": ["static"], "episodes": 2, "progress": False, "task_table": table}
    benchmark.run_benchmark(tmp_path / "a", workers=2, **kw)
    assert calls == {"address": None, "num_cpus": 2}
    benchmark.run_benchmark(tmp_path / "b", workers=1, **kw)
    assert _read_csv(tmp_path / "a" / "benchmark.csv") == _read_csv(tmp_path / "b" / "benchmark.csv")


def test_chunked_jobs_give_the_rows_of_one_job() -> None:
    """Jobs of one episode each give the rows of one job over the same seeds (an episode depends on its seed
    alone), numbered from the task's first held-out episode; the chunks partition the seeds in order."""
    table = {"traffic": stand_in_tasks()["traffic"]}
    whole = benchmark.plan_jobs(table, None, ["random"], {}, 3)
    parts = benchmark.plan_jobs(table, None, ["random"], {}, 3, episodes_per_job=2)
    seeds = list(table["traffic"].heldout_seeds[:3])
    assert [(j["method"], j["seeds"]) for j in whole] == [("random", seeds), ("optimum", seeds)]
    assert [(j["method"], j["first_episode"], j["seeds"]) for j in parts] == [
        ("random", 0, seeds[:2]),
        ("random", 2, seeds[2:]),
        ("optimum", 0, seeds[:2]),
        ("optimum", 2, seeds[2:]),
    ]
    one = benchmark.run_job(whole[0])
    split = [r for j in parts[:2] for r in benchmark.run_job(j)]
    assert [r["episode"] for r in split] == [0, 1, 2] and [r["seed"] for r in split] == seeds
    assert split == one


def test_map_in_processes_keeps_the_input_order() -> None:
    """Spawned processes, the costliest first, results in input order; each finished item reported once."""
    import math

    from cv2x_marl.parallel import map_in_processes

    seen: list[int] = []
    items = [5, 3, 10, 4]
    got = map_in_processes(math.factorial, items, 2, cost=float, on_done=lambda i, r: seen.append(i))
    assert got == [120, 6, 3628800, 24]
    assert sorted(seen) == [0, 1, 2, 3]
    assert map_in_processes(math.factorial, items, 1) == got  # one worker: in this process
    with pytest.raises(ValueError, match="workers must be an integer >= 1"):
        map_in_processes(math.factorial, items, 0)


def test_benchmark_refusals_leave_no_folder(tmp_path: Path) -> None:
    out = tmp_path / "bench"
    table = stand_in_tasks()
    cases = [
        ({"task_table": None}, "not available in this version"),  # the new ids, before they are registered
        ({"tasks": ["traffic"], "methods": ["greedy"]}, "policy 'greedy' cannot run on task traffic"),
        ({"methods": ["oracle"]}, "--methods oracle: not a method of task singlemover"),
        ({"tasks": ["singlemover"], "methods": ["best-response"]}, "policy 'best-response' cannot run on task"),
        ({"models": ["singlemover=gbmu"]}, "--model expects TASK=ppo:PATH"),
        ({"models": ["nope=ppo:x.zip"]}, "unknown task 'nope'"),
        ({"models": ["singlemover=ppo:missing.zip"]}, "no model file missing.zip"),
        ({"episodes": 0}, "--episodes must be an integer >= 1"),
        ({"workers": 0}, "--workers must be an integer >= 1"),
        ({"backend": "threads"}, "--backend must be one of ray, processes"),
        ({"backend": "processes", "address": "auto"}, "--address names a Ray cluster"),
        ({"episodes_per_job": 0}, "--episodes-per-job must be an integer >= 1"),
    ]
    for kw, match in cases:
        if kw.get("task_table", table) is None and all(t.available for t in tasks.TASKS.values()):
            continue  # after the merge the new ids exist
        args: dict[str, Any] = {"task_table": table, "progress": False, **kw}
        with pytest.raises(ValueError, match=match):
            benchmark.run_benchmark(out, **args)
        assert not out.exists()


def test_benchmark_parse_models(tmp_path: Path) -> None:
    for name in ("s0", "s1"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "model.zip").write_bytes(b"")
    got = benchmark.parse_models(
        [f"singlemover=ppo:{tmp_path}/s*/model.zip", f"cooperative/mappo=ppo:{tmp_path}/s0/model.zip"], tasks.TASKS
    )
    assert got == {
        "singlemover": {"ppo": [f"ppo:{tmp_path}/s0/model.zip", f"ppo:{tmp_path}/s1/model.zip"]},
        "cooperative": {"mappo": [f"ppo:{tmp_path}/s0/model.zip"]},
    }


def test_cooperative_gains_are_of_the_team_objective(tmp_path: Path) -> None:
    """On a team task every row of an episode carries the team's gain: eq. 17 of J, the mean over the
    vehicles of the per-receiver utility, recomputed here from the env itself (team_search.team_objective)
    and from the rows; the network mean PRR likewise."""
    from cv2x_marl.env.registry import make_parallel_env
    from cv2x_marl.env.team_search import team_objective

    seeds = [5, 6]
    opts = {"max_cycles": 3}
    summary, rows = ev.evaluate_rows("cv2x/Cooperative-v0", "gbmu", 0, 0, progress=False, seeds=seeds, env_kwargs=opts)
    assert summary["gains_of"].startswith("the team")
    env = make_parallel_env("cv2x/Cooperative-v0", **opts)
    for ep, seed in enumerate(seeds):
        mine = [r for r in rows if r["episode"] == ep]
        assert len(mine) == env.n
        env.reset(seed=seed)
        j0 = team_objective(env.links, env.positions_m, env.p_min)
        assert np.mean([r["utility_start"] for r in mine]) == pytest.approx(j0, rel=1e-12)
        j1 = np.mean([r["utility_end"] for r in mine])
        p0, p1 = np.mean([r["prr_start"] for r in mine]), np.mean([r["prr_end"] for r in mine])
        for r in mine:
            assert r["utility_gain"] == pytest.approx((j1 - j0) / abs(j0), rel=1e-12)
            assert r["prr_gain"] == pytest.approx((p1 - p0) / p0, rel=1e-12)
    # an individually rewarded env keeps eq. 17 per mover
    single, srows = ev.evaluate_rows("cv2x/SingleMover-v3", "gbmu", 0, 0, progress=False, seeds=seeds, env_kwargs=opts)
    assert single["gains_of"] == "each mover (eq. 17)"
    for r in srows:
        assert r["utility_gain"] == pytest.approx((r["utility_end"] - r["utility_start"]) / abs(r["utility_start"]))


def test_offset_policies_are_refused_where_actions_are_speed_commands() -> None:
    """A scripted offset mover is never reinterpreted as speed and lane commands (issue 27, item 3)."""
    from types import SimpleNamespace

    from cv2x_marl.policies import registry

    speed_env = SimpleNamespace(mode="traffic", traffic_action="speed")
    for name in registry.OFFSET_POLICIES:
        with pytest.raises(
            ValueError, match=rf"policy '{name}' moves vehicles by position offsets.*allowed here: static"
        ):
            registry.make_policy(name, speed_env)  # type: ignore[arg-type]
    assert registry.make_policy("static", speed_env).name == "static"  # type: ignore[arg-type]
    resource = {"sps", "lowest-rssi", "farthest"}  # cv2x/Resource-v0's scripts (its action picks a resource)
    assert set(registry.OFFSET_POLICIES) | {"static", "random"} | resource == set(registry.SCRIPTED)


def test_rows_from_an_earlier_run_are_taken_not_run_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--rows-from``: the scripted and ceiling rows of an earlier benchmark.csv are taken as they are (their
    jobs do not run) and the table equals the earlier run's; a method it lacks runs; a foreign file is refused
    before the folder is made."""
    table = {"singlemover": stand_in_tasks()["singlemover"]}
    kw: dict[str, Any] = {"episodes": 2, "progress": False, "task_table": table}
    first = benchmark.run_benchmark(tmp_path / "a", methods=["static"], **kw)
    ran: list[str] = []
    real = benchmark.run_job

    def spy(job: dict[str, Any]) -> list[dict[str, Any]]:
        ran.append(job["method"])
        return real(job)

    monkeypatch.setattr(benchmark, "run_job", spy)
    again = benchmark.run_benchmark(
        tmp_path / "b", methods=["static", "gbmu"], rows_from=tmp_path / "a" / "benchmark.csv", **kw
    )
    assert ran == ["gbmu"]  # static and the ceiling were taken
    for method in ("static", "optimum"):
        assert again["tasks"]["singlemover"]["methods"][method] == first["tasks"]["singlemover"]["methods"][method]
    rows_a = _read_csv(tmp_path / "a" / "benchmark.csv")
    rows_b = [r for r in _read_csv(tmp_path / "b" / "benchmark.csv") if r["method"] != "gbmu"]
    assert rows_b == rows_a
    params = json.loads((tmp_path / "b" / "run.json").read_text())["parameters"]
    assert params["reused_jobs"] == 2 and params["rows_from"]["sha256"] == benchmark.sha256_of(
        tmp_path / "a" / "benchmark.csv"
    )
    # chunked jobs renumber their reused rows as one job would; a seed the earlier run lacks makes its job run
    ran.clear()
    chunked = benchmark.run_benchmark(
        tmp_path / "d", methods=["static"], rows_from=tmp_path / "a" / "benchmark.csv", episodes_per_job=1, **kw
    )
    assert ran == [] and chunked["tasks"] == first["tasks"]
    assert _read_csv(tmp_path / "d" / "benchmark.csv") == rows_a
    more = benchmark.run_benchmark(
        tmp_path / "e",
        methods=["static"],
        rows_from=tmp_path / "a" / "benchmark.csv",
        episodes_per_job=2,
        **{**kw, "episodes": 3},
    )
    assert ran == ["static", "optimum"]  # episode 2 of each: not in the earlier run
    assert more["tasks"]["singlemover"]["episodes"] == 3
    (tmp_path / "bad.csv").write_text("task,method\nsinglemover,static\n")
    with pytest.raises(ValueError, match=r"--rows-from .*bad.csv: not a benchmark.csv"):
        benchmark.run_benchmark(tmp_path / "c", rows_from=tmp_path / "bad.csv", **kw)
    assert not (tmp_path / "c").exists()


def test_a_learned_method_runs_on_the_env_it_was_trained_on(tmp_path: Path) -> None:
    """A model trained on a variant of the task (Traffic-v1 for traffic) runs there; one trained on another
    task's env, or runs of one method trained on different envs, are refused naming the allowed ids."""
    for name, env_id in (("v1", "cv2x/Traffic-v1"), ("v0", "cv2x/Traffic-v0"), ("coop", "cv2x/Cooperative-v0")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "model.zip").write_bytes(b"")
        (tmp_path / name / "train_config.json").write_text(json.dumps({"env_id": env_id, "env": {}}))
    traffic = tasks.TASKS["traffic"]
    assert benchmark.model_env_id(traffic, "ppo", [f"ppo:{tmp_path}/v1/model.zip"]) == "cv2x/Traffic-v1"
    assert benchmark.model_env_id(traffic, "ppo", [f"ppo:{tmp_path}/v0/model.zip"]) == "cv2x/Traffic-v0"
    with pytest.raises(ValueError, match=r"trained on cv2x/Cooperative-v0.*allowed: cv2x/Traffic-v0, cv2x/Traffic-v1"):
        benchmark.model_env_id(traffic, "ppo", [f"ppo:{tmp_path}/coop/model.zip"])
    with pytest.raises(ValueError, match="its runs were trained on different envs"):
        benchmark.model_env_id(traffic, "ppo", [f"ppo:{tmp_path}/v0/model.zip", f"ppo:{tmp_path}/v1/model.zip"])
    (tmp_path / "noisy").mkdir()
    (tmp_path / "noisy" / "model.zip").write_bytes(b"")
    cfg = {"env_id": "cv2x/Traffic-v1", "env": {"rsrp_error_db": 0.0}}
    (tmp_path / "noisy" / "train_config.json").write_text(json.dumps(cfg))
    with pytest.raises(
        ValueError, match=r"trained with rsrp_error_db=0.0; a task measures with the env's rsrp_error_db=3.0"
    ):
        benchmark.model_env_id(traffic, "ppo", [f"ppo:{tmp_path}/noisy/model.zip"])


def test_a_learned_label_may_not_name_a_scripted_method(tmp_path: Path) -> None:
    (tmp_path / "m.zip").write_bytes(b"")
    with pytest.raises(ValueError, match=r"--model singlemover/gbmu: the label names a scripted method.*best-response"):
        benchmark.run_benchmark(
            tmp_path / "out",
            methods=["static"],
            models=[f"singlemover/gbmu=ppo:{tmp_path}/m.zip"],
            progress=False,
            task_table=stand_in_tasks(),
        )
    assert not (tmp_path / "out").exists()
