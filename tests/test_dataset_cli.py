"""`cv2x-marl dataset` and `cv2x-marl fit` end to end on a small configuration."""

import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from cv2x_marl.cli import main

SMALL = ["--set", "sim.n_subframes=1500", "--set", "sim.warmup_subframes=200", "--quiet"]


def _dataset(out: Path, seed: int = 1, extra: tuple[str, ...] = ()) -> None:
    assert (
        main(["dataset", "--preset", "paper", "--runs", "3", "--seed", str(seed), "--out", str(out), *SMALL, *extra])
        == 0
    )


def test_dataset_is_deterministic_and_has_a_manifest(tmp_path: Path) -> None:
    _dataset(tmp_path / "a")
    _dataset(tmp_path / "b")
    _dataset(tmp_path / "c", seed=2)
    a, b = pq.read_table(tmp_path / "a" / "samples.parquet"), pq.read_table(tmp_path / "b" / "samples.parquet")
    assert a.equals(b)
    assert not a.equals(pq.read_table(tmp_path / "c" / "samples.parquet"))
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert manifest["rows"] == a.num_rows and manifest["runs"] == 3 and len(manifest["run_seeds"]) == 3
    assert sorted(set(a.column("run").to_pylist())) == [0, 1, 2]
    assert sum(manifest["rows_per_nsv"].values()) == a.num_rows
    assert manifest["config"]["sim"]["n_subframes"] == 1500


def test_aggregated_dataset(tmp_path: Path) -> None:
    _dataset(tmp_path / "agg", extra=("--aggregate-window-ms", "1000"))
    t = pq.read_table(tmp_path / "agg" / "samples.parquet").to_pydict()
    assert {"rate", "n", "window"} <= set(t)
    assert all(0.0 <= r <= 1.0 for r in t["rate"])
    assert max(t["n"]) <= 10  # at most one transmission per 100-ms period in a 1000-ms window


def test_paper_reading_is_concurrent_nsv_over_the_whole_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--reading paper`` = ``--set metrics.nsv_scope=concurrent`` with one aggregation window per
    run, sample for sample (with the default fixed warm-up that is a window of warm-up + measured
    subframes, as subframes count from the warm-up's start); ``fit`` then defaults to the rate."""
    _dataset(tmp_path / "paper", extra=("--reading", "paper"))
    _dataset(tmp_path / "explicit", extra=("--set", "metrics.nsv_scope=concurrent", "--aggregate-window-ms", "1700"))
    a = pq.read_table(tmp_path / "paper" / "samples.parquet")
    assert a.equals(pq.read_table(tmp_path / "explicit" / "samples.parquet"))
    manifest = json.loads((tmp_path / "paper" / "manifest.json").read_text())
    assert manifest["aggregate_window_ms"] == -1 and manifest["config"]["metrics"]["nsv_scope"] == "concurrent"
    assert set(a.column("window").to_pylist()) == {0}  # one window: the whole run
    # a warm-up that runs on until every vehicle reselected still gives one window per run
    _dataset(tmp_path / "long", extra=("--reading", "paper", "--set", "sim.warmup_mode=until_reselected"))
    t = pq.read_table(tmp_path / "long" / "samples.parquet").to_pydict()
    assert set(t["window"]) == {0}
    groups = set(zip(t["run"], t["tx"], t["rx"], t["nsv"], strict=True))
    assert len(groups) == len(t["window"])  # one instance per (run, link, NSV)
    capsys.readouterr()
    assert main(["fit", "--data", str(tmp_path / "paper"), "--out", str(tmp_path / "fit"), "--json"]) == 0
    capsys.readouterr()
    run = json.loads((tmp_path / "fit" / "run.json").read_text())
    assert run["parameters"]["target"] == "rate"
    with pytest.raises(SystemExit):
        main(["dataset", "--reading", "mine", "--out", str(tmp_path / "x")])
    assert main(["dataset", "--reading", "paper", "--aggregate-window-ms", "100", "--out", str(tmp_path / "y")]) == 2
    assert "drop --aggregate-window-ms" in capsys.readouterr().err


def test_fit_writes_model_tables_and_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = tmp_path / "ds"
    _dataset(data)
    capsys.readouterr()
    fit = tmp_path / "fit"
    rc = main(["fit", "--data", str(data), "--out", str(fit), "--json", "--compare", "--nsv-cap", "2"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["nsv"] for r in out["per_nsv"]] == [0, 1, 2]
    for r in out["per_nsv"]:
        assert {"alpha", "beta", "gamma", "r2", "r2_test", "instances"} <= set(r)
    assert out["per_nsv"][0]["alpha"] < 0  # P falls with the signal distance
    assert set(out["comparison"]) == {"linear", "logistic"}
    for name in ("model.json", "table2.md", "table3.md", "fig2_surface.png", "fit_quality.png", "model_comparison.md"):
        assert (fit / name).exists(), name
    assert "alpha" in (fit / "table2.md").read_text()
    assert json.loads((fit / "model.json").read_text())["provenance"]["dataset_runs"] == 3
    # the dataset folder is only read: its files are those its own run listed
    assert sorted(p.name for p in data.iterdir()) == ["manifest.json", "run.json", "samples.parquet"]


def test_fit_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["fit", "--data", str(empty), "--out", str(tmp_path / "m")]) == 2
    assert "manifest.json" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()  # a refused input leaves no output folder
    assert main(["fit", "--data", str(empty), "--out", str(tmp_path / "m.json")]) == 2
    assert "is a folder" in capsys.readouterr().err
    data = tmp_path / "ds"
    _dataset(data)
    (data / "samples.parquet").write_bytes(b"PAR1 this is not parquet")
    assert main(["fit", "--data", str(data), "--out", str(tmp_path / "m")]) == 2
    assert "samples.parquet" in capsys.readouterr().err
