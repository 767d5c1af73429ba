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


def test_evaluate_seeds_report_iqm_and_intervals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["evaluate", "--policy", "gbmu", "--seeds", "3,4,5", "--json", "--quiet", "--out", str(tmp_path / "e")])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["seeds"] == [3, 4, 5] and summary["episodes"] == 3 and summary["runs"] == 1
    lo, hi = summary["ci95_utility_gain"]
    assert lo <= summary["iqm_utility_gain"] <= hi
    assert json.loads((tmp_path / "e" / "summary.json").read_text())["iqm_utility_gain"] == summary["iqm_utility_gain"]
    rc = main(["evaluate", "--policy", "static", "--seeds", "3,4", "--quiet"])
    assert rc == 0
    assert "IQM over 1 run(s) x 2 episodes (95% CI): utility gain +0.0% [+0.0%, +0.0%]" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["evaluate", "--env-option", "speed=1"], "unknown env argument 'speed'; allowed: preset, overrides"),
        (["evaluate", "--env-option", "max_step_m=2"], "--env-option max_step_m: set it with --max-step"),
        (["evaluate", "--seeds", "heldout", "--env", "cv2x/SingleMover-v1"], "is no task's env"),
        (["evaluate", "--policy", "gbmu", "--policy", "static"], "several policies are the training runs"),
        (["benchmark", "--out", "x", "--tasks", "traffic", "--methods", "planner"], "cannot run on task traffic"),
        (["benchmark", "--out", "x", "--model", "singlemover=gbmu"], "--model expects TASK=ppo:PATH"),
    ],
)
def test_protocol_flags_refused_by_name(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--quiet"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_the_env_option_flags_are_the_schemas() -> None:
    """The CLI's env-option flags hold the schema's entries as data (the CLI starts without numpy): equal to it."""
    from cv2x_marl.cli.env_flags import SPECS
    from cv2x_marl.env.options import flag_spec

    assert SPECS == {name: flag_spec(name) for name in SPECS}, "regenerate with: python -m cv2x_marl.cli.env_flags"


@pytest.mark.parametrize("value", ["10001", "1e9", "0"])
def test_an_env_option_flag_refuses_what_the_schema_refuses(
    value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Refused while the arguments are parsed (exit 2, nothing written), naming the flag and the schema's range."""
    from cv2x_marl.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--max-cycles", value, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    assert f"argument --max-cycles: must be an integer >= 1 and <= 10000, got '{value}'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
