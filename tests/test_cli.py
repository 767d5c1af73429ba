"""The `cv2x-marl simulate` command end to end (short run)."""

import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from cv2x_marl.cli import main
from cv2x_marl.sim import LINK_COLUMNS


def test_simulate_writes_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    rc = main(
        [
            "simulate",
            "--preset",
            "paper",
            "--seed",
            "3",
            "--subframes",
            "1500",
            "--out",
            str(out),
            "--json",
            "--quiet",
            "--set",
            "sim.warmup_subframes=200",
        ]
    )
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    for key in ("prr_mean", "prr_vs_distance", "loss_causes", "n_transmissions", "runtime_s", "config"):
        assert key in summary
    assert summary["n_transmissions"] == 21 * 15  # every vehicle transmits once per 100-ms period
    assert summary["config"]["sim"]["warmup_subframes"] == 200
    row = summary["prr_vs_distance"][0]
    assert set(row) >= {"distance_m", "prr", "n"} and row["distance_m"] == 5.0
    assert set(summary["loss_causes"][0]) >= {"half_duplex", "sensitivity", "propagation", "collision"}
    table = pq.read_table(out / "links.parquet")
    assert table.column_names == list(LINK_COLUMNS)
    assert table.num_rows == sum(r["n"] for r in summary["prr_vs_distance"])  # every link within 650 m is binned
    assert json.loads((out / "summary.json").read_text())["prr_mean"] == summary["prr_mean"]
    assert (out / "prr_vs_distance.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(out.glob(".*.tmp"))


def test_bad_key_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["simulate", "--set", "sps.keep_prob=0.2", "--quiet"])
    assert rc == 2
    err = capsys.readouterr().err
    assert "sps.keep_prob" in err and "keep_probability" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["gbmu", "--step", "nan", "--out", "x"],
        ["gbmu", "--step", "inf", "--out", "x"],
        ["evaluate", "--delta", "-100"],
        ["evaluate", "--episodes", "0"],
        ["evaluate", "--max-step", "0"],
        ["train", "--timesteps", "15.5", "--out", "x"],
        ["dataset", "--runs", "2.5", "--out", "x"],
        ["fit", "--test-fraction", "1", "--data", "a", "--out", "b"],
        ["simulate", "--seed", "-1"],
    ],
)
def test_bad_numbers_are_refused_by_name(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    flag = next(a for a in argv if a.startswith("--") and a != "--out")
    assert f"argument {flag}: must be" in err


def test_counts_in_scientific_notation() -> None:
    from cv2x_marl.cli import COUNT

    assert COUNT("1e5") == 100_000 and COUNT("12") == 12
