"""Helpers of `cv2x-marl reproduce`: per-method rows over seeds, model discovery, the markdown."""

from pathlib import Path

import pytest

from cv2x_marl.experiments.reproduce import _markdown, _row, shipped_models


def test_row_mean_and_spread_over_seeds() -> None:
    res = [
        {"mean_utility_gain": 0.1, "effectiveness": 0.5, "mean_prr_gain": 0.0, "jain_fairness": 0.5, "n_prr_drop": 2},
        {"mean_utility_gain": 0.3, "effectiveness": 0.7, "mean_prr_gain": 0.2, "jain_fairness": 0.6, "n_prr_drop": 4},
    ]
    row = _row("ppo", res)
    assert row["mean_utility_gain"] == pytest.approx(0.2)
    assert row["mean_utility_gain_std"] == pytest.approx(0.1414213562)  # sample std of (0.1, 0.3)
    assert row["n_prr_drop"] == pytest.approx(3.0) and row["n_seeds"] == 2
    assert _row("gbmu", res[:1])["effectiveness_std"] == 0.0


def test_shipped_models_sorted_by_seed(tmp_path: Path) -> None:
    for s in (10, 2, 0):
        (tmp_path / f"single_seed{s}").mkdir()
        (tmp_path / f"single_seed{s}" / "model.zip").write_bytes(b"x")
    (tmp_path / "multi_seed1").mkdir()
    (tmp_path / "multi_seed1" / "model.zip").write_bytes(b"x")
    assert [p.parent.name for p in shipped_models(tmp_path, "single")] == [
        "single_seed0",
        "single_seed2",
        "single_seed10",
    ]


def test_markdown_report_lists_every_method() -> None:
    rows = [
        _row(
            m,
            [
                {
                    "mean_utility_gain": 0.1,
                    "effectiveness": 0.5,
                    "mean_prr_gain": 0.02,
                    "jain_fairness": 0.5,
                    "n_prr_drop": 1,
                }
            ],
        )
        for m in ("static", "gbmu")
    ]
    rep = {
        "quick": True,
        "seed": 0,
        "runtime_s": 1.0,
        "settings": {"runs": 1, "realizations": 2, "iterations": 3, "episodes_single": 4, "episodes_multi": 5},
        "fit": {
            "per_nsv": [
                {"nsv": 0, "alpha": -0.7, "beta": 0.0, "gamma": 2.2, "r2": 0.3, "r2_test": 0.2, "instances": 10}
            ],
            "comparison": None,
        },
        "gbmu_study": {
            "ours": {"gbmu": {"effectiveness": 0.8, "mean_utility_gain": 0.2, "mean_prr_gain": 0.1, "n_prr_drop": 3}}
        },
        "movers": {"single": rows},
    }
    md = _markdown(rep)
    assert "| static | +10.0 %" in md and "| gbmu |" in md and "| 0 | -0.70 | 0.00 | 2.20 |" in md


def _models(root: Path, *names: str) -> Path:
    for name in names:
        (root / name).mkdir(parents=True)
        (root / name / "model.zip").write_bytes(b"x")
    return root


@pytest.mark.parametrize(
    ("models", "message"),
    [
        (
            "nonexistent",
            r"--models .*nonexistent: no such folder; expected one holding single_seed<N>/model.zip and "
            r"multi_seed<N>/model.zip .*or --models none to leave PPO out",
        ),
        ("empty", r"--models .*empty holds no single_seed<N>/model.zip and no multi_seed<N>/model.zip; expected"),
        ("single-only", r"--models .*single-only holds no multi_seed<N>/model.zip; expected"),
    ],
)
def test_reproduce_refuses_missing_models_before_writing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], models: str, message: str
) -> None:
    import re

    from cv2x_marl.cli import main

    (tmp_path / "empty").mkdir()
    _models(tmp_path / "single-only", "single_seed0", "single_seedX")  # seedX is not a model folder
    out = tmp_path / "results"
    assert main(["reproduce", "--quick", "--quiet", "--models", str(tmp_path / models), "--out", str(out)]) == 2
    assert not out.exists()
    err = capsys.readouterr().err
    assert re.search(message, err), err


def test_check_models_finds_both_envs_or_none_on_request(tmp_path: Path) -> None:
    import importlib.util

    from cv2x_marl.experiments.reproduce import check_models

    if importlib.util.find_spec("stable_baselines3") is None:  # check_models asks for the extra
        pytest.skip("stable-baselines3 (the train extra) is not installed")
    root = _models(tmp_path, "single_seed1", "single_seed0", "multi_seed0")
    found = check_models(root)
    assert {k: [p.parent.name for p in v] for k, v in found.items()} == {
        "single": ["single_seed0", "single_seed1"],
        "multi": ["multi_seed0"],
    }
    assert check_models(None) == {}


def _report(files: list[str], ppo: bool) -> dict:
    metrics = {"mean_utility_gain": 0.1, "effectiveness": 0.5, "mean_prr_gain": 0.0, "jain_fairness": 0.5}
    rows = [_row(m, [{**metrics, "n_prr_drop": 1}]) for m in ("static", "optimum")]
    return {
        "quick": True,
        "seed": 0,
        "runtime_s": 1.0,
        "settings": {"runs": 1, "realizations": 2, "iterations": 3, "episodes_single": 4, "episodes_multi": 5},
        "fit": {"per_nsv": [], "comparison": None},
        "gbmu_study": {"ours": {"gbmu": {**metrics, "n_prr_drop": 3}}},
        "movers": {"single": rows, "multi": rows},
        "ppo": ppo,
        "files": files,
    }


def test_report_cites_only_written_figures_and_no_ppo_without_models() -> None:
    import re

    written = ["comparison-single.png", "fit/fig2_surface.png", "fit/table2.md", "gbmu-ours/fig9_fig10_gains.png"]
    md = _markdown(_report(written, ppo=False))
    cited = set(re.findall(r"`([^`]+\.(?:png|md))`", md))
    assert cited == set(written)  # comparison-multi.png, learning-*.png, fit_quality.png... were not written
    assert "| ppo" not in md and "PPO: mean" not in md and "learning-" not in md
    assert "`cv2x-marl reproduce --quick --seed 0 --models none`" in md and "No PPO models were evaluated." in md
    md_all = _markdown(_report([], ppo=True))
    assert not re.findall(r"\.png|\.md`", md_all)  # nothing written: nothing cited


def test_written_files_lists_figures_and_tables_under_the_folder(tmp_path: Path) -> None:
    from cv2x_marl.experiments.reproduce import written_files

    for name in ("a.png", "fit/table2.md", "fit/model.json", "gbmu-ours/fig9_fig10_gains.png"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text("x")
    assert written_files(tmp_path) == ["a.png", "fit/table2.md", "gbmu-ours/fig9_fig10_gains.png"]
