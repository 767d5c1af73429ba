"""Bad inputs of issue 25 (defects 7, 10, 11 and 13, the parsing, configuration, dataset and model
parts): each is refused with exit code 2 and a message naming the culprit and the limit, before an
output folder exists."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from cv2x_marl.cli import MAX_SEED, main
from cv2x_marl.runs import sha256_file
from cv2x_marl.yamlcore import MAX_DEPTH, MAX_FILE_BYTES, MAX_NODES

HUGE = "9" * 400  # a 400-digit integer


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI, assert exit code 2 (a refusal, argparse's included), return stderr."""
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse's refusal of an option value
        rc = exc.code  # type: ignore[assignment]
    assert rc == 2
    return capsys.readouterr().err


def _write_dataset(
    folder: Path, rows: int = 400, change: Callable[[dict[str, np.ndarray]], None] | None = None
) -> Path:
    """A small dataset folder as `cv2x-marl dataset` writes it (samples, manifest with the checksum),
    after ``change`` edits its columns."""
    rng = np.random.default_rng(0)
    cols: dict[str, np.ndarray] = {
        "run": np.repeat(np.arange(4, dtype=np.int32), rows // 4),
        "tx": rng.integers(0, 21, rows).astype(np.int32),
        "rx": rng.integers(0, 21, rows).astype(np.int32),
        "subframe": np.arange(rows, dtype=np.int64),
        "d_m": rng.uniform(10.0, 400.0, rows),
        "l_m": rng.uniform(10.0, 200.0, rows),
        "nsv": rng.integers(0, 3, rows).astype(np.int16),
        "p_success": rng.uniform(0.0, 1.0, rows),
        "outcome": rng.uniform(size=rows) < 0.5,
    }
    if change is not None:
        change(cols)
    folder.mkdir()
    pq.write_table(pa.table(cols), folder / "samples.parquet")
    manifest = {
        "kind": "cv2x_marl stage-1 dataset",
        "runs": 4,
        "rows": rows,
        "aggregate_window_ms": 0,
        "sha256": {"samples.parquet": sha256_file(folder / "samples.parquet")},
    }
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def _model_file(folder: Path) -> Path:
    """A model file as `cv2x-marl fit` writes it (the paper's coefficients, with the SHA-256)."""
    from cv2x_marl.regression import TwoDistanceModel

    return TwoDistanceModel.paper_table2().save(folder / "model.json")


# ---------------------------------------------------------------- defect 7: NaN in a dataset


def test_fit_refuses_nan_distances_naming_file_column_and_count(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = _write_dataset(tmp_path / "good")
    assert main(["fit", "--data", str(good), "--out", str(tmp_path / "fit-good"), "--no-figures", "--json"]) == 0

    def nan_distances(cols: dict[str, np.ndarray]) -> None:
        cols["d_m"][[3, 50, 51, 200, 399]] = np.nan
        cols["l_m"][7] = np.inf

    data = _write_dataset(tmp_path / "nan", change=nan_distances)
    out = tmp_path / "fit"
    err = _refused(["fit", "--data", str(data), "--out", str(out), "--no-figures"], capsys)
    assert f"{data / 'samples.parquet'}: column 'd_m' has 5 of 400 rows that are NaN or infinite" in err
    assert not out.exists()


# ---------------------------------------------------------------- defect 10: crashes


@pytest.mark.parametrize("where", ["--set", "json config", "yaml config"])
def test_a_400_digit_integer_in_a_config_is_refused_naming_the_key_and_range(
    where: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if where == "--set":
        source = ["--set", f"sim.n_subframes={HUGE}"]
    else:
        path = tmp_path / ("c.json" if where == "json config" else "c.yaml")
        path.write_text(
            f'{{"sim": {{"n_subframes": {HUGE}}}}}' if path.suffix == ".json" else f"sim:\n  n_subframes: {HUGE}\n"
        )
        source = ["--config", str(path)]
    out = tmp_path / "run"
    err = _refused(["simulate", *source, "--out", str(out), "--quiet"], capsys)
    assert "sim.n_subframes: an integer of 400 digits is out of range; allowed range: [1, 1e+08]" in err
    assert not out.exists()
    # a float key: the integer is beyond the float range
    err = _refused(["simulate", "--set", f"radio.tx_power_dbm={HUGE}", "--out", str(out), "--quiet"], capsys)
    assert "radio.tx_power_dbm: an integer of 400 digits is out of range; allowed range: [-30, 46]" in err


@pytest.mark.parametrize("seed", [HUGE, str(MAX_SEED + 1), "1e400"])
def test_a_seed_beyond_32_bits_is_refused_naming_the_option_and_range(
    seed: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    err = _refused(["simulate", "--seed", seed, "--out", str(out)], capsys)
    assert "argument --seed: must be an integer >= 0 and <= 4294967295, got" in err
    assert len(err.splitlines()[-1]) < 200  # the 400 digits are cut short
    assert not out.exists()


def test_a_dataset_manifest_that_is_a_list_is_refused_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = _write_dataset(tmp_path / "ds")
    (data / "manifest.json").write_text("[1, 2]")
    out = tmp_path / "fit"
    err = _refused(["fit", "--data", str(data), "--out", str(out)], capsys)
    assert f"{data / 'manifest.json'} holds a JSON list, not the object of a dataset manifest" in err
    assert not out.exists()


@pytest.mark.parametrize("methods", ["", ",", " , "])
def test_gbmu_without_methods_is_refused_listing_the_methods(
    methods: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "gbmu"
    err = _refused(["gbmu", "--methods", methods, "--out", str(out), "--quiet"], capsys)
    assert "--methods" in err and "names no method" in err
    assert "gbmu, greedy, oracle, planner, optimum, gbmu-logistic" in err
    assert not out.exists()
    err = _refused(["gbmu", "--methods", "gbmu,fastest", "--out", str(out), "--quiet"], capsys)
    assert "unknown method(s) fastest" in err and not out.exists()


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_a_5000_deep_config_is_refused_with_the_nesting_limit(
    suffix: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / f"deep{suffix}"
    path.write_text('{"sim": ' + "[" * 5000 + "]" * 5000 + "}")  # flow YAML is JSON
    out = tmp_path / "run"
    err = _refused(["simulate", "--config", str(path), "--out", str(out)], capsys)
    assert f"configuration file {path}" in err
    assert f"nest more than {MAX_DEPTH} levels deep (the limit)" in err
    assert not out.exists()
    # block mappings, and nesting reached through aliases, count the same
    block = tmp_path / "block.yaml"
    block.write_text("".join(" " * i + "a:\n" for i in range(150)))
    assert "nest more than 100 levels" in _refused(["config", "--config", str(block)], capsys)
    chain = ["a0: &a0 [[[[[[[[[[1]]]]]]]]]]"] + [f"a{k}: &a{k} [[[[[[[[[[*a{k - 1}]]]]]]]]]]" for k in range(1, 12)]
    (tmp_path / "chain.yaml").write_text("\n".join(chain) + "\n")
    assert "once aliases are expanded" in _refused(["config", "--config", str(tmp_path / "chain.yaml")], capsys)


# ---------------------------------------------------------------- defect 11: resources


def test_dataset_runs_beyond_memory_are_refused_with_the_estimate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from cv2x_marl.config import apply_overrides, preset
    from cv2x_marl.experiments.dataset import build_dataset, estimate_dataset_bytes

    monkeypatch.setenv("CV2X_MARL_MEMORY_LIMIT_GB", "4")
    out = tmp_path / "ds"
    err = _refused(["dataset", "--runs", "1e9", "--out", str(out), "--quiet"], capsys)
    est = estimate_dataset_bytes(preset("paper"), 10**9)
    assert est["rows_per_run"] == 21 * 20 * 103  # every transmission to every other vehicle, 103 periods
    assert "dataset --runs 1,000,000,000: 1,000,000,000 runs x up to 43,260 link samples per run" in err
    assert f"= {est['rows']:,} samples" in err and "above the limit of 4 GB (CV2X_MARL_MEMORY_LIMIT_GB)" in err
    assert "runs fit" in err
    assert not out.exists()
    # the estimate bounds a real run from above, and closely (half-duplex pairs are not samples)
    cfg = apply_overrides(preset("paper"), ["sim.n_subframes=1500", "sim.warmup_subframes=200"])
    manifest = build_dataset(cfg, 1, 0, tmp_path / "real", progress=False)
    per_run = estimate_dataset_bytes(cfg, 1)["rows_per_run"]
    assert 0.8 * per_run <= manifest["rows"] <= per_run


def test_fit_nsv_cap_beyond_the_maximum_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = _write_dataset(tmp_path / "ds")
    out = tmp_path / "fit"
    err = _refused(["fit", "--data", str(data), "--out", str(out), "--nsv-cap", "1e9"], capsys)
    assert "--nsv-cap 1000000000 is out of range" in err and "allowed range: [0, 255]" in err
    assert not out.exists()


def test_a_yaml_alias_bomb_is_refused_before_it_is_expanded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    levels = ['  - &a ["x","x","x","x","x","x","x","x","x","x"]']
    levels += [f"  - &{b} [{','.join([f'*{a}'] * 10)}]" for a, b in zip("abcdefg", "bcdefgh", strict=True)]
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("sim:\n  n_subframes:\n" + "\n".join(levels) + "\n")  # 10^8 strings once expanded
    assert bomb.stat().st_size < 500
    out = tmp_path / "run"
    t0 = time.perf_counter()
    err = _refused(["simulate", "--config", str(bomb), "--out", str(out)], capsys)
    assert time.perf_counter() - t0 < 5.0
    assert f"configuration file {bomb}" in err
    assert f"more than {MAX_NODES:,} values once its aliases are expanded (the limit)" in err
    assert len(err) < 1000 and not out.exists()
    # the same through --set
    flow = "[" + ",".join(x.strip()[2:] for x in levels) + "]"
    err = _refused(["simulate", "--set", f"sim.n_subframes={flow}", "--out", str(out)], capsys)
    assert "once its aliases are expanded" in err and len(err) < 1000 and not out.exists()


def test_config_files_that_are_devices_or_too_large_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    t0 = time.perf_counter()
    err = _refused(["simulate", "--config", "/dev/zero", "--out", str(out)], capsys)
    assert time.perf_counter() - t0 < 5.0
    assert "configuration file /dev/zero is a character device, not a regular file" in err
    large = tmp_path / "large.yaml"
    with large.open("wb") as f:
        f.truncate(MAX_FILE_BYTES + 1)
    err = _refused(["simulate", "--config", str(large), "--out", str(out)], capsys)
    assert f"configuration file {large} is 10,485,761 bytes, above the limit of 10,485,760 bytes (10 MiB)" in err
    assert not out.exists()


# ---------------------------------------------------------------- defect 13: unclear messages


def test_a_nan_coefficient_in_a_model_file_names_the_file_and_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _model_file(tmp_path)
    doc = json.loads(path.read_text())
    doc["per_nsv"][2]["alpha"] = float("nan")
    path.write_text(json.dumps(doc))  # NaN, as Python's json writes it
    out = tmp_path / "gbmu"
    err = _refused(["gbmu", "--model", str(path), "--case", "seven-node", "--out", str(out), "--quiet"], capsys)
    assert f"model file {path}: per_nsv[2].alpha is not a finite number (NaN or infinite)" in err
    assert not out.exists()


def test_a_string_column_in_a_dataset_names_the_file_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def strings(cols: dict[str, np.ndarray]) -> None:
        cols["l_m"] = np.array(["far"] * cols["l_m"].shape[0], dtype=object)

    data = _write_dataset(tmp_path / "ds", change=strings)
    out = tmp_path / "fit"
    err = _refused(["fit", "--data", str(data), "--out", str(out)], capsys)
    assert f"{data / 'samples.parquet'}: column 'l_m' holds string values, not numbers" in err
    assert not out.exists()


def test_a_model_file_without_its_checksum_or_with_huge_coefficients_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from cv2x_marl.regression.model import _digest

    path = _model_file(tmp_path)
    doc = json.loads(path.read_text())
    del doc["sha256"]
    doc["per_nsv"][0]["alpha"] = 1e308
    path.write_text(json.dumps(doc))
    out = tmp_path / "gbmu"
    argv = ["gbmu", "--model", str(path), "--case", "seven-node", "--out", str(out), "--quiet"]
    assert f"model file {path} has no sha256 key" in _refused(argv, capsys)
    doc["sha256"] = _digest(doc)  # a checksum that matches: the range check still refuses it
    path.write_text(json.dumps(doc))
    err = _refused(argv, capsys)
    assert (
        f"model file {path}: alpha of NSV 0 is 1e+308: model coefficients must be finite numbers within +-1e+06" in err
    )
    assert not out.exists()


def test_a_long_set_value_is_cut_short_in_the_message(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "run"
    err = _refused(["simulate", "--set", "sim.n_subframes=" + "x" * 100_000, "--out", str(out)], capsys)
    assert "sim.n_subframes: expected an integer in [1, 1e+08], got 'xxxx" in err
    assert "... (100,000 characters)" in err and len(err) < 400
    err = _refused(["simulate", "--set", "sim." + "k" * 100_000 + "=1", "--out", str(out)], capsys)
    assert "unknown configuration key sim.kkkk" in err and "(100,000 characters)" in err and len(err) < 400
    assert not out.exists()


def test_a_config_file_preset_line_that_disagrees_with_preset_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("preset: highway\nsim:\n  n_subframes: 100\n")
    out = tmp_path / "run"
    err = _refused(["simulate", "--preset", "paper", "--config", str(path), "--out", str(out)], capsys)
    assert f"--preset paper and the line 'preset: highway' of configuration file {path} name different presets" in err
    assert not out.exists()
    for agreeing in ([], ["--preset", "highway"], ["--preset", "highway-3gpp"]):  # one preset, or the same
        assert main(["config", *agreeing, "--config", str(path)]) == 0
        resolved = json.loads(capsys.readouterr().out)
        assert resolved["road"]["kind"] == "highway" and resolved["sim"]["n_subframes"] == 100
