"""baselines/: every file loads and evaluates, bad files are refused by name, the committed results
table is what `cv2x-marl baselines` renders from its JSON and covers every file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.experiments.baselines import render_table, run_baselines
from cv2x_marl.experiments.evaluate import evaluate
from cv2x_marl.policies.baselines import baseline_files, load_baseline, make_baseline_policy

ROOT = Path(__file__).resolve().parent.parent
FAST = {"max_cycles": 4, "overrides": ["sim.warmup_subframes=200"]}


@pytest.mark.parametrize("path", baseline_files(ROOT / "baselines"), ids=lambda p: p.stem)
def test_every_baseline_file_loads_and_evaluates(path: Path) -> None:
    spec = load_baseline(path)
    res = evaluate(None, str(path), 1, 0, env_kwargs=FAST, progress=False)
    assert res["env"] == spec.env_id and res["policy"] == spec.policy
    if spec.policy == "static":
        assert res["mean_utility_gain"] == 0.0


def test_the_results_table_is_current() -> None:
    result = json.loads((ROOT / "baselines" / "results.json").read_text())
    assert (ROOT / "baselines" / "results.md").read_text() == render_table(result)
    assert sorted(r["baseline"] for r in result["rows"]) == sorted(p.stem for p in baseline_files(ROOT / "baselines"))


@pytest.mark.parametrize(
    ("text", "culprit"),
    [
        ("policy: gbmu\nstep: 3\n", "unknown key"),
        ("policy: sprint\n", "policy must be one of"),
        ("policy: gbmu\ndelta: -1\n", "delta"),
        ("policy: gbmu\ndelta: .nan\n", "delta"),
        ("policy: gbmu\nenv_id: cv2x/Other-v0\n", "env_id"),
        ("policy: gbmu\nenv: [1]\n", "env must be a mapping"),
        ("- gbmu\n", "must be a mapping"),
        ("policy: gbmu\nstep_schedule: adam\n", "step_schedule must be one of constant, decay, backtracking"),
        ("policy: optimum\nstep_schedule: decay\n", "step_schedule applies to policies gbmu, greedy only"),
        ("policy: gbmu\nstep_schedule: decay\ndecay_k0: 0\n", "decay_k0 must be a finite number > 0"),
        ("policy: gbmu\ndecay_k0: .inf\n", "decay_k0"),
        ("policy: gbmu\nmodel: 3\n", "model must be paper-table2, linear-fit, logistic-fit or a model file"),
        ("policy: gbmu\nmodel: nowhere/model.json\n", "model 'nowhere/model.json': model file .* does not exist"),
        ("policy: sensing\nmodel: nowhere.json\n", "model 'nowhere.json': model file .* does not exist"),
    ],
)
def test_bad_baseline_files_are_refused_by_name(tmp_path: Path, text: str, culprit: str) -> None:
    f = tmp_path / "mine.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=culprit) as err:
        load_baseline(f)
    assert "mine.yaml" in str(err.value)


def test_run_baselines_writes_the_table_and_shares(tmp_path: Path) -> None:
    for name in ("static", "optimum"):
        (tmp_path / f"{name}.yaml").write_text(
            f"policy: {name}\nenv: {{max_cycles: 4, overrides: [sim.warmup_subframes=200]}}\n"
        )
    result = run_baselines(tmp_path, 2, 5, progress=False)
    shares = {r["baseline"]: r["share_of_optimum"] for r in result["rows"]}
    assert shares["optimum"] == 1.0 and shares["static"] == 0.0
    assert (tmp_path / "results.md").read_text() == render_table(json.loads((tmp_path / "results.json").read_text()))


@pytest.mark.parametrize(
    ("name", "kind", "schedule"),
    [
        ("gbmu", "linear", None),
        ("gbmu-logistic", "logistic", None),
        ("gbmu-linear-fit", "linear", None),
        ("gbmu-schedule", "linear", "backtracking"),
        ("gbmu-decay", "linear", "decay"),
        ("gbmu-logistic-schedule", "logistic", "backtracking"),
    ],
)
def test_gbmu_variant_files_carry_their_model_and_schedule(name: str, kind: str, schedule: str | None) -> None:
    env = make_parallel_env("cv2x/SingleMover-v2", **FAST)
    policy = make_baseline_policy(load_baseline(ROOT / "baselines" / f"{name}.yaml"), env)
    assert policy.name == "gbmu" and policy.model.kind == kind  # type: ignore[attr-defined]
    got = policy.schedule  # type: ignore[attr-defined]
    assert (got and got.kind) == schedule
    if name.startswith("gbmu-logistic"):
        assert policy.model.provenance["shipped_as"] == "cv2x_marl/regression/data/logistic-fit.json"  # type: ignore[attr-defined]
