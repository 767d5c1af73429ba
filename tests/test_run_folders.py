"""Run folders never lose data (issue 25, defects 1-4, 8 and the symlinked ``--out``).

Each test starts from a previous run (or another tool's files) and checks, file by file, that what
was there before is still there after the refused, failed or interrupted run.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from cv2x_marl import runs
from cv2x_marl.cli import main
from cv2x_marl.runs import RunFolder, RunFolderError

SIM = ["simulate", "--seed", "3", "--subframes", "300", "--quiet", "--set", "sim.warmup_subframes=100"]
REPO = Path(__file__).resolve().parents[1]


def _simulate(out: Path | str, *extra: str) -> int:
    return main([*SIM, "--out", str(out), *extra])


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (run.json included) with its bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _hidden(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name.startswith("."))


def _previous_run(out: Path) -> dict[str, bytes]:
    """A small complete run of ours in ``out`` (no simulation needed), and its files."""
    with RunFolder(out, "simulate"):
        (out / "summary.json").write_text('{"prr_mean": 0.5}\n')
        (out / "figs").mkdir()
        (out / "figs" / "a.png").write_bytes(b"\x89PNG fake")
    return _snapshot(out)


# -- 1: --overwrite never deletes a previous run it cannot move aside -------------------------------
def test_a_previous_run_that_cannot_be_moved_aside_is_left_untouched(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The move aside fails (another file system, a busy folder): refused before anything changed.
    Before the fix the previous run was removed by the rollback."""
    out = tmp_path / "run"
    before = _previous_run(out)
    real_replace = os.replace

    def cross_device(src: str | Path, dst: str | Path) -> None:
        if Path(src) == out:
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        real_replace(src, dst)

    monkeypatch.setattr(runs.os, "replace", cross_device)
    assert _simulate(out, "--overwrite") == 2
    err = capsys.readouterr().err
    assert "cannot move the previous run" in err and "nothing was changed" in err and "Invalid cross-device" in err
    assert _snapshot(out) == before
    assert _hidden(tmp_path) == []


def _mount_tmpfs(target: Path) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    target.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(target)], capture_output=True)
    return done.returncode == 0


def test_an_out_that_is_a_mount_point_is_refused_and_kept(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "mnt"
    if not _mount_tmpfs(out):
        pytest.skip("needs root and a tmpfs mount (mount -t tmpfs)")
    try:
        before = _previous_run(out)
        assert _simulate(out, "--overwrite") == 2
        assert "is a mount point" in capsys.readouterr().err
        assert _snapshot(out) == before
    finally:
        subprocess.run(["umount", str(out)], check=False)


def test_out_dot_dot_from_inside_the_run_is_refused_and_nothing_is_lost(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`cd outer/inner && cv2x-marl simulate --out .. --overwrite` wiped all of outer, inner/notes.txt included."""
    outer = tmp_path / "outer"
    before = _previous_run(outer)
    (outer / "inner").mkdir()
    monkeypatch.chdir(outer / "inner")
    # an empty folder of the user's inside the run: the run contains the current directory
    assert _simulate("..", "--overwrite") == 2
    assert f"output folder {outer} contains the current directory" in capsys.readouterr().err
    # a note the user put inside: a file the run did not write
    (outer / "inner" / "notes.txt").write_text("mine")
    assert _simulate("..", "--overwrite") == 2
    err = capsys.readouterr().err
    assert "files that run did not write (inner/notes.txt)" in err
    assert (outer / "inner" / "notes.txt").read_text() == "mine"
    assert {k: v for k, v in _snapshot(outer).items() if k != "inner/notes.txt"} == before
    assert _hidden(tmp_path) == []


def test_a_long_out_name_is_replaced_safely(tmp_path: Path) -> None:
    """A 246-character name: `.NAME.old-PID` was too long, the previous run was lost."""
    out = tmp_path / ("r" * 246)
    _previous_run(out)
    assert _simulate(out, "--overwrite") == 0
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["status"] == "complete" and "summary.json" in manifest["files"] and "figs/a.png" not in manifest
    assert not (out / "figs").exists()  # replaced whole
    assert _hidden(tmp_path) == []


def test_files_a_user_added_to_a_run_folder_are_never_replaced(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    before = _previous_run(out)
    (out / "figs" / "my-annotated.png").write_bytes(b"mine")
    assert _simulate(out, "--overwrite") == 2
    assert "files that run did not write (figs/my-annotated.png)" in capsys.readouterr().err
    assert _snapshot(out) == {**before, "figs/my-annotated.png": b"mine"}


# -- 2 (the runs.py half; train's own test is in tests/rl): a failed run restores the previous one --
def test_a_failing_keep_on_failure_run_restores_the_previous_run(tmp_path: Path) -> None:
    """Training keeps checkpoints when it fails, but never at the cost of the run it replaces."""
    out = tmp_path / "run"
    before = _previous_run(out)
    with pytest.raises(KeyboardInterrupt) as info, RunFolder(out, "train", overwrite=True, keep_on_failure=True):
        assert _snapshot(out).keys() == {"run.json"}  # the previous run is aside, not deleted
        (out / "checkpoints").mkdir()
        (out / "checkpoints" / "ppo_10.zip").write_bytes(b"partial")
        raise KeyboardInterrupt
    assert _snapshot(out) == before
    assert info.value.__notes__ == [f"the previous run in {out} was restored"]
    # without a previous run the partial run is kept and marked
    fresh = tmp_path / "fresh"
    with pytest.raises(KeyboardInterrupt), RunFolder(fresh, "train", keep_on_failure=True):
        (fresh / "ppo_10.zip").write_bytes(b"partial")
        raise KeyboardInterrupt
    manifest = json.loads((fresh / "run.json").read_text())
    assert manifest["status"] == "interrupted" and set(manifest["files"]) == {"ppo_10.zip"}


def test_a_full_disk_while_finishing_restores_the_previous_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "run"
    before = _previous_run(out)
    real = runs.write_json

    def full(path: Path, data: dict) -> Path:
        if data.get("status") == "complete":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, data)

    monkeypatch.setattr(runs, "write_json", full)
    with pytest.raises(OSError, match="No space"), RunFolder(out, "simulate", overwrite=True):
        (out / "summary.json").write_text("{}")
    assert _snapshot(out) == before and _hidden(tmp_path) == []


# -- 3: only folders this package wrote are replaced -----------------------------------------------
def test_another_tools_run_json_does_not_make_its_folder_ours(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "othertool"
    out.mkdir()
    (out / "run.json").write_text('{"epochs": 10}')
    (out / "weights.bin").write_bytes(b"\x00\x01")
    before = _snapshot(out)
    assert _simulate(out) == 2
    err = capsys.readouterr().err
    assert "no cv2x-marl run wrote" in err and "None" not in err
    assert _simulate(out, "--overwrite") == 2
    assert _snapshot(out) == before


# -- 4: an output that is an input ---------------------------------------------------------------
@pytest.mark.parametrize("where", ["same", "inside", "contains"])
def test_fit_refuses_an_out_that_overlaps_its_dataset(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    ds = tmp_path / "ds"
    assert main(["dataset", "--runs", "1", "--out", str(ds), "--quiet", "--subframes", "300"]) == 0
    before = _snapshot(ds)
    out = {"same": ds, "inside": ds / "fit", "contains": tmp_path}[where]
    assert main(["fit", "--data", str(ds), "--out", str(out), "--overwrite", "--no-figures"]) == 2
    how = {"same": "is", "inside": "lies inside", "contains": "contains"}[where]
    assert f"output folder {out} {how} the input {ds}" in capsys.readouterr().err
    assert _snapshot(ds) == before


def test_evaluate_refuses_an_out_holding_its_ppo_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    shipped = REPO / "agents" / "models" / "single_seed0"
    with RunFolder(run, "train"):
        for f in shipped.iterdir():
            shutil.copy(f, run / f.name)
    before = _snapshot(run)
    argv = ["evaluate", "--policy", f"ppo:{run / 'model.zip'}", "--out", str(run), "--overwrite"]
    assert main([*argv, "--episodes", "1", "--max-cycles", "2", "--quiet"]) == 2
    assert f"contains the input {run / 'model.zip'}" in capsys.readouterr().err
    assert _snapshot(run) == before


def test_check_not_an_input_follows_links_and_skips_names_that_are_not_files(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    link = tmp_path / "link"
    link.symlink_to(data)
    with pytest.raises(RunFolderError, match="is the input"):
        runs.check_not_an_input(link, [data])
    runs.check_not_an_input(tmp_path / "out", [data, "paper-table2"])  # disjoint; a shipped name is no path
    runs.check_not_an_input(tmp_path / "data2", [data])  # a common prefix is not containment


# -- symbolic links -------------------------------------------------------------------------------
def test_a_symlinked_out_replaces_its_target_and_keeps_the_link(tmp_path: Path) -> None:
    target = tmp_path / "real"
    _previous_run(target)
    link = tmp_path / "link"
    link.symlink_to(target)
    assert _simulate(link, "--overwrite") == 0
    assert link.is_symlink() and link.resolve() == target
    assert json.loads((target / "run.json").read_text())["command"] == "simulate"
    assert not (target / "figs").exists()
    assert _hidden(tmp_path) == []


# -- 8: Ctrl-C inside a numba kernel -------------------------------------------------------------
def test_is_interrupt_sees_the_interrupt_behind_a_numba_system_error() -> None:
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError("CPUDispatcher(<function period_chunk>) returned a result with an exception set") from ki
    except SystemError as exc:
        assert runs.is_interrupt(exc)
    assert not runs.is_interrupt(SystemError("other"))
    assert not runs.is_interrupt(ValueError())


_KERNEL_INTERRUPT = textwrap.dedent(
    """
    import sys, time
    import numba, numpy as np
    from cv2x_marl import cli
    from cv2x_marl.experiments import simulate as sim_mod
    from cv2x_marl.runs import RunFolder

    @numba.njit
    def spin(n, a):
        s = 0.0
        for i in range(n):
            s += np.sqrt(i * 1.0)
        out = np.empty(3)
        out[:] = s
        return a, out  # returning arrays: the dispatcher raises SystemError when a signal came in

    spin(10, np.zeros(2))  # compiled first: the timing below is of the loop alone, not of the compilation
    t0 = time.perf_counter()
    spin(10**8, np.zeros(2))
    n = int(10**8 * 4.0 / max(time.perf_counter() - t0, 1e-3))  # about four seconds of compiled code

    def fake_simulate(cfg, seed, n_subframes, out_dir, **kw):
        with RunFolder(out_dir, "simulate", overwrite=kw["overwrite"]):
            (out_dir / "partial.txt").write_text("half")
            print("in kernel", flush=True)
            spin(n, np.zeros(2))
            time.sleep(2)  # the code after the kernel: the CLI's handler raises here, a moment after the kernel
        raise AssertionError("not interrupted")

    sim_mod.simulate = fake_simulate
    sys.exit(cli.main(["simulate", "--out", sys.argv[1], "--overwrite", "--quiet"]))
    """
)


@pytest.mark.parametrize("sig", ["INT", "TERM"])
def test_a_signal_inside_a_compiled_kernel_ends_as_interrupted(tmp_path: Path, sig: str) -> None:
    out = tmp_path / "run"
    before = _previous_run(out)
    proc = subprocess.Popen(
        [sys.executable, "-c", _KERNEL_INTERRUPT, str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline() == "in kernel\n"
    time.sleep(0.5)  # the compiled loop runs for about four seconds: the signal lands inside it
    proc.send_signal(getattr(signal, f"SIG{sig}"))
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert f"cv2x-marl: interrupted; the previous run in {out} was restored" in stderr
    assert "SystemError" not in stderr and "Traceback" not in stderr
    assert _snapshot(out) == before


# -- 13: after SIGKILL, readers say where the previous run is ---------------------------------------
def test_a_dataset_left_half_replaced_by_a_killed_run_names_the_intact_previous_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ds = tmp_path / "ds"
    assert main(["dataset", "--runs", "1", "--out", str(ds), "--quiet", "--subframes", "300"]) == 0
    before = _snapshot(ds)
    aside = tmp_path / f"{runs._aside_prefix(ds)}4242"  # what a `dataset --overwrite` killed mid-run leaves
    os.replace(ds, aside)
    ds.mkdir()
    (ds / "run.json").write_text(json.dumps({"kind": runs.KIND, "command": "dataset", "status": "running"}))
    assert main(["fit", "--data", str(ds), "--out", str(tmp_path / "fit"), "--no-figures"]) == 2
    assert f"the previous dataset is intact in {aside}" in capsys.readouterr().err
    assert not (tmp_path / "fit").exists()
    # the next run on the folder repairs it (here a refused one: it takes the lock first)
    assert main(["dataset", "--runs", "1", "--out", str(ds), "--quiet", "--subframes", "300"]) == 2
    assert _snapshot(ds) == before and not aside.exists()
