"""`cv2x-marl simulate` streams the links table into links.parquet (issue 13: bounded memory)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from cv2x_marl.config import apply_overrides, preset
from cv2x_marl.experiments import simulate as sim_mod
from cv2x_marl.sim import Simulator

SMALL = ["sim.warmup_subframes=200"]


def test_streamed_links_table_equals_the_in_memory_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = apply_overrides(preset("paper"), SMALL)
    sim = Simulator(cfg)
    sim.reset(3)
    in_memory = sim.run(1500)
    assert in_memory.links is not None
    expected = sim_mod.links_table(in_memory.links)
    monkeypatch.setattr(sim_mod, "ROW_GROUP_ROWS", 1000)  # several row groups
    summary = sim_mod.simulate(cfg, 3, 1500, tmp_path / "run", progress=False)
    streamed = pq.read_table(tmp_path / "run" / "links.parquet")
    assert streamed.equals(expected)
    assert pq.ParquetFile(tmp_path / "run" / "links.parquet").num_row_groups > 1
    assert summary["prr_mean"] == in_memory.metrics.summary()["prr_mean"]
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [
        "links.parquet",
        "prr_vs_distance.png",
        "run.json",
        "summary.json",
    ]


def test_a_run_with_a_sink_keeps_no_links_in_memory() -> None:
    cfg = apply_overrides(preset("paper"), SMALL)
    sim = Simulator(cfg)
    sim.reset(1)
    chunks: list[dict[str, np.ndarray]] = []
    result = sim.run(300, links_sink=chunks.append)
    assert result.links is None and len(chunks) >= 2
    again = Simulator(cfg)
    again.reset(1)
    kept = again.run(300).links
    assert kept is not None
    for column, values in kept.items():  # the pieces, in order, are the in-memory table
        np.testing.assert_array_equal(np.concatenate([c[column] for c in chunks]), values)


def test_no_links_file_without_record_links_and_none_left_by_a_failed_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = apply_overrides(preset("paper"), [*SMALL, "metrics.record_links=false"])
    sim_mod.simulate(cfg, 0, 500, tmp_path / "off", progress=False)
    assert not (tmp_path / "off" / "links.parquet").exists()

    calls = {"n": 0}
    original = sim_mod.LinksWriter.__call__

    def fail_on_second(self: sim_mod.LinksWriter, chunk: dict[str, np.ndarray]) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError("disk full (simulated)")
        original(self, chunk)

    monkeypatch.setattr(sim_mod.LinksWriter, "__call__", fail_on_second)
    monkeypatch.setattr(sim_mod, "ROW_GROUP_ROWS", 1)  # the first chunk is already on disk
    cfg_on = apply_overrides(preset("paper"), SMALL)
    with pytest.raises(OSError, match="disk full"):
        sim_mod.simulate(cfg_on, 0, 500, tmp_path / "failed", progress=False)
    assert not (tmp_path / "failed").exists() or not any((tmp_path / "failed").iterdir())


def test_auto_links_skips_a_table_above_the_limit_and_says_so(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--links auto`` (the CLI's default): the expected row count (the memory model's pairs, 21 x 20
    links a period on the paper grid, no cut-off) equals the table's length; above the limit the table
    is not written and the summary says why; ``on`` writes it whatever its size."""
    import json

    cfg = apply_overrides(preset("paper"), SMALL)
    n_sub = 1000  # 10 whole periods
    rows = sim_mod.expected_link_rows(cfg, n_sub)
    assert rows == 10 * 21 * 20
    on = sim_mod.simulate(cfg, 2, n_sub, tmp_path / "on", progress=False, links="auto")
    assert pq.ParquetFile(tmp_path / "on" / "links.parquet").metadata.num_rows == rows
    assert "links_table" not in on
    monkeypatch.setattr(sim_mod, "AUTO_LINKS_MAX_ROWS", rows - 1)
    skipped = sim_mod.simulate(cfg, 2, n_sub, tmp_path / "auto", progress=False, links="auto")
    assert not (tmp_path / "auto" / "links.parquet").exists()
    assert skipped["links_table"] == {
        "written": False,
        "expected_rows": rows,
        "why": f"more than {rows - 1:,} expected rows; pass --links on to write it",
    }
    assert json.loads((tmp_path / "auto" / "summary.json").read_text())["links_table"]["expected_rows"] == rows
    assert skipped["prr_mean"] == on["prr_mean"]  # the same run, without the table
    sim_mod.simulate(cfg, 2, n_sub, tmp_path / "forced", progress=False, links="on")
    assert (tmp_path / "forced" / "links.parquet").exists()
    sim_mod.simulate(cfg, 2, n_sub, tmp_path / "off", progress=False, links="off")
    assert not (tmp_path / "off" / "links.parquet").exists()
    with pytest.raises(ValueError, match=r"links must be one of auto, on, off"):
        sim_mod.simulate(cfg, 2, n_sub, None, progress=False, links="maybe")
