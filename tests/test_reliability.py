"""Run folders as units (issue 12): one regression test per defect of the issue.

1 concurrent runs on one folder, 2 stale files of an earlier run, 7 file-system errors and
interrupts, 8 corrupted datasets and models; the resume defects (3) are in tests/rl/test_resume.py,
the parser (4) in tests/test_yamlcore.py, sizes (6) in tests/sim/test_memory.py.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest

from cv2x_marl import runs
from cv2x_marl.cli import main
from cv2x_marl.runs import RunFolder, RunFolderError, file_entries, verify

SIM = ["simulate", "--seed", "3", "--subframes", "300", "--quiet", "--set", "sim.warmup_subframes=100"]


def _simulate(out: Path, *extra: str) -> int:
    return main([*SIM, "--out", str(out), *extra])


def _leftovers(parent: Path) -> list[str]:
    """Hidden lock, staging, old-run and temporary files a run may leave beside or in its folder."""
    return sorted(p.name for p in parent.rglob(".*"))


# -- 1: two runs on one folder -----------------------------------------------------------------
def test_a_second_run_on_a_locked_folder_is_refused_naming_the_holder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    with RunFolder(out, "train"):
        assert _simulate(out) == 2
        err = capsys.readouterr().err
        assert f"output folder {out} is in use by pid {os.getpid()}" in err
        assert "`cv2x-marl train`" in err
        assert sorted(p.name for p in out.iterdir()) == ["run.json"]  # the refused run wrote nothing
    assert _simulate(out, "--overwrite") == 0  # the lock went with the first run
    assert _leftovers(tmp_path) == []


def test_lock_is_released_when_the_run_fails(tmp_path: Path) -> None:
    with pytest.raises(ZeroDivisionError), RunFolder(tmp_path / "r", "simulate"):
        raise ZeroDivisionError
    with RunFolder(tmp_path / "r", "simulate"):
        pass
    assert not (tmp_path / ".r.lock").exists()


# -- 2: stale files of an earlier run ----------------------------------------------------------
def test_a_non_empty_folder_is_refused_and_overwrite_replaces_it_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    assert _simulate(out) == 0
    assert (out / "links.parquet").exists()
    first = json.loads((out / "run.json").read_text())
    assert _simulate(out, "--set", "metrics.record_links=false") == 2
    assert "is not empty: it holds a previous `simulate` run (complete" in capsys.readouterr().err
    assert json.loads((out / "run.json").read_text()) == first  # untouched
    assert _simulate(out, "--set", "metrics.record_links=false", "--overwrite") == 0
    # the links table of the first run is gone: every file comes from the second run
    assert sorted(p.name for p in out.iterdir()) == ["prr_vs_distance.png", "run.json", "summary.json"]
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["status"] == "complete" and manifest["command"] == "simulate"
    assert manifest["argv"][:2] == ["cv2x-marl", "simulate"] and "--overwrite" in manifest["argv"]
    assert set(manifest["files"]) == {"prr_vs_distance.png", "summary.json"}
    verify(out)
    assert _leftovers(tmp_path) == []


def test_files_no_run_wrote_are_never_replaced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("precious")
    assert _simulate(out, "--overwrite") == 2
    assert "no cv2x-marl run wrote" in capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "precious"


def test_gbmu_and_evaluate_outputs_are_run_folders(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ev"
    argv = ["evaluate", "--policy", "static", "--episodes", "1", "--max-cycles", "2", "--quiet", "--out", str(out)]
    assert main(argv) == 0
    assert main(argv) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main([*argv, "--overwrite"]) == 0
    assert set(json.loads((out / "run.json").read_text())["files"]) == {"episodes.csv", "summary.json"}


# -- 7: file-system errors and interrupts ------------------------------------------------------
def test_out_naming_a_file_is_refused_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    assert _simulate(f) == 2
    assert f"output folder {f} is a file" in capsys.readouterr().err


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write a read-only folder")
def test_a_read_only_parent_is_refused_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert _simulate(ro / "run") == 2
        assert "not writable" in capsys.readouterr().err
    finally:
        ro.chmod(0o755)


def _fail_in_figure(monkeypatch: pytest.MonkeyPatch, exc: BaseException) -> None:
    import cv2x_marl.plotting as plotting

    def boom(*args: object, **kwargs: object) -> None:
        raise exc

    monkeypatch.setattr(plotting, "plot_prr_vs_distance", boom)


def test_a_full_disk_rolls_the_folder_back_to_the_previous_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    assert _simulate(out) == 0
    before = file_entries(out)
    _fail_in_figure(monkeypatch, OSError(errno.ENOSPC, "No space left on device", str(out / "x.png")))
    assert _simulate(out, "--seed", "4", "--overwrite") == 1
    err = capsys.readouterr().err
    assert "file system error" in err and "No space left on device" in err and "Traceback" not in err
    assert file_entries(out) == before  # the previous run, whole, not a mix
    assert json.loads((out / "run.json").read_text())["status"] == "complete"
    assert _leftovers(tmp_path) == []


def test_an_interrupt_leaves_no_partial_folder_and_no_temp_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    _fail_in_figure(monkeypatch, KeyboardInterrupt())
    assert _simulate(out) == 130
    assert "interrupted" in capsys.readouterr().err
    assert not out.exists()
    assert _leftovers(tmp_path) == []


def test_leftovers_of_a_killed_run_are_repaired(tmp_path: Path) -> None:
    """A run killed (SIGKILL) between moving the previous run aside and finishing: the next run
    that takes the lock restores the previous run and drops the partial one."""
    out = tmp_path / "run"
    with RunFolder(out, "simulate"):
        (out / "a.txt").write_text("previous")
    old = tmp_path / f"{runs._aside_prefix(out)}99999"
    os.replace(out, old)
    assert runs.previous_run_aside(out) == old  # what readers name until the next run repairs it
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"kind": runs.KIND, "status": "running"}))
    (out / "partial.txt").write_text("half")
    with pytest.raises(RunFolderError, match="not empty"), RunFolder(out, "simulate"):
        pass
    assert (out / "a.txt").read_text() == "previous" and not (out / "partial.txt").exists()
    assert not old.exists() and runs.previous_run_aside(out) is None
    verify(out)


# -- 8: corrupted datasets and models ----------------------------------------------------------
def test_flipped_bytes_are_caught_in_datasets_models_and_run_folders(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ds, fit = tmp_path / "ds", tmp_path / "fit"
    base = ["--quiet", "--set", "sim.warmup_subframes=100", "--subframes", "300"]
    assert main(["dataset", "--runs", "1", "--out", str(ds), *base]) == 0
    assert main(["fit", "--data", str(ds), "--out", str(fit), "--no-figures", "--min-samples", "5"]) == 0
    capsys.readouterr()
    samples = ds / "samples.parquet"
    raw = bytearray(samples.read_bytes())
    raw[len(raw) // 2] ^= 0xFF  # one flipped byte in the middle of the data
    samples.write_bytes(bytes(raw))
    assert main(["fit", "--data", str(ds), "--out", str(tmp_path / "fit2")]) == 2
    assert "does not match the SHA-256" in capsys.readouterr().err
    with pytest.raises(RunFolderError, match=r"samples\.parquet does not match its checksum"):
        verify(ds)
    model = fit / "model.json"
    model.write_text(model.read_text().replace('"alpha": -', '"alpha": -1', 1))
    argv = ["gbmu", "--case", "seven-node", "--iterations", "5", "--quiet", "--model", str(fit)]
    assert main(argv) == 2
    assert "does not match its SHA-256" in capsys.readouterr().err


def test_a_corrupted_ppo_model_in_a_run_folder_is_refused(tmp_path: Path) -> None:
    from cv2x_marl.policies.ppo import PpoPolicy

    run = tmp_path / "run"
    with RunFolder(run, "train"):
        (run / "model.zip").write_bytes(b"PK\x03\x04 pretend zip")
    (run / "model.zip").write_bytes(b"PK\x03\x04 changed zip")
    with pytest.raises(ValueError, match=r"model\.zip does not match its checksum"):
        PpoPolicy(run / "model.zip")


def test_baselines_folder_is_locked_while_results_are_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "bl"
    folder.mkdir()
    (folder / "static.yaml").write_text("policy: static\nenv:\n  max_cycles: 2\n")
    with runs.locked(folder, "baselines"):
        assert main(["baselines", "--dir", str(folder), "--episodes", "1", "--quiet"]) == 2
    assert "is in use by pid" in capsys.readouterr().err
    assert not (folder / "results.json").exists()
    assert main(["baselines", "--dir", str(folder), "--episodes", "1", "--quiet"]) == 0
    assert (folder / "results.json").exists() and _leftovers(tmp_path) == []
