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
