"""The shipped models (agents/models/<task>_seed{0..4}/, the utility maps, the resource learner and the MAPPO trained in
turns on Cooperative-v1): five training seeds per learner, each with the configuration and env options that rebuild
its env, trained within 15 CPU-minutes, and reproducing its rows of the published benchmark run
(docs/benchmark/learners/benchmark.csv, learners-map/, resource-learners/ and cooperative-v1-learners/) through the
benchmark's own job."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from cv2x_marl.env import tasks
from cv2x_marl.experiments import benchmark
from cv2x_marl.experiments.evaluate import trained_env_options

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "agents" / "models"
TABLE = ROOT / "docs" / "benchmark" / "learners" / "benchmark.csv"
#: the learned utility maps' run (docs/benchmark.md, "A learner that plans")
MAP_TABLE = ROOT / "docs" / "benchmark" / "learners-map" / "benchmark.csv"
#: the resource learners' run (docs/rl.md, "Resource choice"), next to the task's scripted rows
RESOURCE_TABLE = ROOT / "docs" / "benchmark" / "resource-learners" / "benchmark.csv"
#: the MAPPO trained in turns on the coordination channel (docs/benchmark.md, "The coordination channel")
V1_TABLE = ROOT / "docs" / "benchmark" / "cooperative-v1-learners" / "benchmark.csv"
#: learner -> (folder prefix, env id the models were trained on, model file, benchmark label, config, the env options
#: that shape observations and actions beyond the id's defaults); the benchmark tasks' learners by task name
SHIPPED = {
    "singlemover": ("singlemover-v3", "cv2x/SingleMover-v3", "model.zip", "learned", "ppo_single_v3_deepsets.yaml", {}),
    "cooperative": ("cooperative", "cv2x/Cooperative-v0", "model.pt", "learned", "mappo_cooperative.yaml", {}),
    "traffic": (
        "traffic",
        "cv2x/Traffic-v1",
        "model.zip",
        "learned",
        "ppo_traffic_v1_change.yaml",
        {"speed_command": "change"},
    ),
    "singlemover-map": ("singlemover-map", "cv2x/SingleMover-v3", "model.npz", "map", "map_single_v3.yaml", {}),
    "resource-ippo": ("resource-ippo", "cv2x/Resource-v0", "model.pt", "ippo", "ippo_resource.yaml", {}),
    "cooperative-v1": (
        "cooperative-v1",
        "cv2x/Cooperative-v1",
        "model.pt",
        "mappo-v1",
        "mappo_cooperative_v1.yaml",
        {},
    ),
}
#: the table each learner's rows were published in (default :data:`TABLE`)
TABLES = {"singlemover-map": MAP_TABLE, "resource-ippo": RESOURCE_TABLE, "cooperative-v1": V1_TABLE}
#: the task of each learner of :data:`SHIPPED`
TASK_OF = {name: name.split("-")[0] for name in SHIPPED}
#: issue 28's training budget per seed on a 2-core machine
CPU_BUDGET_S = 15 * 60


def _shipped_rows() -> list[dict[str, str]]:
    with (MODELS / "shipped.csv").open(newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.parametrize("learner", list(SHIPPED))
def test_five_seeds_with_the_config_and_env_that_rebuild_them(learner: str) -> None:
    prefix, env_id, model, _, config, options = SHIPPED[learner]
    task = TASK_OF[learner]
    runs = sorted(p.name for p in MODELS.glob(f"{prefix}_seed*"))
    assert runs == [f"{prefix}_seed{k}" for k in range(5)]
    shipped = {r["name"]: r for r in _shipped_rows()}
    for k, name in enumerate(runs):
        folder = MODELS / name
        cfg = json.loads((folder / "train_config.json").read_text())
        assert cfg["seed"] == k and cfg["env_id"] == env_id
        pool = cfg["env"].get("start_pool") or cfg.get("start_pool") or 0  # (PPO also takes it at the top level)
        assert pool > 0  # training episodes from the training list's head, never a held-out one
        got_id, got_options = trained_env_options(folder / model)
        assert got_id == env_id and {key: got_options[key] for key in options} == options
        assert tasks.task_of_env(env_id).name == task  # the task itself or its variant: the task's episodes
        row = shipped[name]
        assert (row["task"], row["config"], int(row["seed"])) == (task, f"agents/configs/{config}", k)
        assert int(row["timesteps"]) == cfg["timesteps"]
        assert 0 < float(row["cpu_s"]) <= CPU_BUDGET_S


@pytest.mark.parametrize("learner", list(SHIPPED))
def test_a_shipped_model_reproduces_its_published_benchmark_rows(learner: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Seed 0's first two held-out episodes through the benchmark's job (the env rebuilt from the model's
    train_config.json): the recorded per-episode numbers, to 1e-9 relative (another CPU's ulps; nothing
    discrete may change)."""
    monkeypatch.chdir(ROOT)  # the table names the models by their paths in the repository
    prefix, env_id, model, label, _, _ = SHIPPED[learner]
    task = TASK_OF[learner]
    if model.endswith(".zip"):
        pytest.importorskip("stable_baselines3")
    elif model.endswith(".pt"):
        pytest.importorskip("torch")
    with TABLES.get(learner, TABLE).open(newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["task"] == task and r["method"] == label and r["run"] == "0"]
    rows = sorted(rows, key=lambda r: int(r["episode"]))[:2]
    assert rows[0]["policy"] == f"ppo:agents/models/{prefix}_seed0/{model}" and rows[0]["env_id"] == env_id
    # the benchmark's own planning: the env id from the model's train_config.json, the task's options
    models = benchmark.parse_models([f"{task}/{label}={rows[0]['policy']}"], tasks.TASKS)
    reference = tasks.TASKS[task].methods[:1]  # the task's reference method (static; sps on resource)
    jobs = benchmark.plan_jobs(tasks.TASKS, [task], reference, models, episodes=2)
    (job,) = [j for j in jobs if j["method"] == label]
    assert job["env_id"] == env_id and job["seeds"] == [int(r["seed"]) for r in rows]
    got = benchmark.run_job(job)
    for g, r in zip(got, rows, strict=True):
        for key in ("utility_start", "utility_end", "utility_gain", "prr_start", "prr_end", "prr_gain"):
            assert g[key] == pytest.approx(float(r[key]), rel=1e-9, abs=1e-12), (task, key)
