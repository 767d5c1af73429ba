"""Inputs a careless or hostile user gives, refused with a clear error before anything is written, and the
runs they asked for done as asked: ``benchmark --rows-from`` files cut short, garbled or edited; ``--workers``
beyond the CPUs or the memory; ``--model`` patterns; ``evaluate --seeds`` with ``--episodes`` / ``--seed``;
``--vs-optimum`` on a speed-change model; files given for folders and folders for files; a trace with NaN
positions; a scene too large for the GBMU study; a second Ctrl-C during ``train``; the numba warm-up."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import cv2x_marl.parallel
from cv2x_marl.cli import main
from cv2x_marl.config import ConfigError
from cv2x_marl.env import tasks
from cv2x_marl.experiments import benchmark
from cv2x_marl.experiments.dataset import DatasetError, load_dataset
from cv2x_marl.sim.sumo.trace import read_trace

ROOT = Path(__file__).resolve().parents[1]
#: a real benchmark.csv (the published scripted rows)
BENCHMARK_CSV = ROOT / "docs" / "benchmark" / "benchmark.csv"
CLI = str(Path(sys.executable).parent / "cv2x-marl")


def _err(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(argv)
    return code, capsys.readouterr().err


# -- benchmark --rows-from ------------------------------------------------------------------------


def test_rows_from_a_file_cut_mid_row_names_the_file_and_line(tmp_path: Path) -> None:
    text = BENCHMARK_CSV.read_text()
    lines = text.splitlines(keepends=True)
    cut = tmp_path / "cut.csv"
    cut.write_text("".join(lines[:10]) + lines[10][:40])  # the 11th line cut after 40 characters
    with pytest.raises(ValueError, match=rf"--rows-from {cut}, line 11: the last row does not end the line"):
        benchmark.read_rows(cut)
    short = tmp_path / "short.csv"  # a row missing its last values, the file otherwise intact
    short.write_text("".join(lines[:5]) + lines[5].rsplit(",", 3)[0] + "\n" + "".join(lines[6:10]))
    with pytest.raises(ValueError, match=r"line 6: 12 values, a row has 15"):
        benchmark.read_rows(short)
    assert len(benchmark.read_rows(BENCHMARK_CSV)) == len(lines) - 1  # the intact file: every scripted row


def test_rows_from_random_bytes_or_an_edited_value_names_flag_file_line_and_column(tmp_path: Path) -> None:
    noise = tmp_path / "noise.csv"
    noise.write_bytes(bytes(range(256)) * 8)
    with pytest.raises(ValueError, match=rf"--rows-from {noise}: not a benchmark.csv \(not UTF-8 text"):
        benchmark.read_rows(noise)
    rows = list(csv.reader(BENCHMARK_CSV.read_text().splitlines()))
    rows[7][9] = "abc"  # utility_gain of the 7th data row
    edited = tmp_path / "edited.csv"
    edited.write_text("\n".join(",".join(r) for r in rows[:20]) + "\n")
    with pytest.raises(ValueError, match=rf"--rows-from {edited}, line 8, column utility_gain: 'abc' is not a number"):
        benchmark.read_rows(edited)
    rows[7][9], rows[3][6] = "0.5", "12x"
    edited.write_text("\n".join(",".join(r) for r in rows[:20]) + "\n")
    with pytest.raises(ValueError, match=r"line 4, column seed: '12x' is not an integer"):
        benchmark.read_rows(edited)
    with pytest.raises(ValueError, match=r"--rows-from: no file .* \(it is a folder\)"):
        benchmark.read_rows(tmp_path)


def test_the_cli_refuses_a_bad_rows_from_before_the_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    noise = tmp_path / "noise.csv"
    noise.write_bytes(b"\x9e\x00\xff" * 100)
    out = tmp_path / "out"
    code, err = _err(["benchmark", "--out", str(out), "--rows-from", str(noise), "--quiet"], capsys)
    assert code == 2 and f"--rows-from {noise}: not a benchmark.csv" in err and "Traceback" not in err
    assert not out.exists()


# -- --workers and --model ------------------------------------------------------------------------


def test_workers_beyond_the_cpus_or_the_memory_are_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(cv2x_marl.parallel, "usable_cpus", lambda: 2)
    out = tmp_path / "out"
    argv = ["benchmark", "--out", str(out), "--backend", "processes", "--episodes-per-job", "1", "--quiet"]
    code, err = _err([*argv, "--workers", "16"], capsys)
    assert code == 2 and "--workers 16: this machine lets the run use 2 CPU(s); give at most 2" in err
    monkeypatch.setenv("CV2X_MARL_MEMORY_LIMIT_GB", "0.5")
    code, err = _err([*argv, "--workers", "2"], capsys)
    # 2 workers and this process at 350 MB each (scripted jobs)
    assert code == 2 and "--workers 2: about 1.05 GB (2 worker processes and this one, 0.35 GB each)" in err
    assert "above CV2X_MARL_MEMORY_LIMIT_GB (0.5 GB); give fewer --workers" in err
    assert not out.exists()
    jobs = [{"policy": "ppo:x/model.zip"}, {"policy": "static"}]
    monkeypatch.setenv("CV2X_MARL_MEMORY_LIMIT_GB", "100")
    assert benchmark.check_workers(2, jobs) == 3 * benchmark.LEARNED_WORKER_BYTES  # torch in the workers
    assert benchmark.check_workers(2, [{"policy": "static"}]) == 2 * benchmark.WORKER_BYTES  # one job: one worker
    assert benchmark.check_workers(16, jobs, address="auto") == 0  # a cluster's CPUs are its own


def test_a_model_pattern_that_matches_nothing_names_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _err(
        ["benchmark", "--out", str(tmp_path / "o"), "--model", "singlemover=ppo:/nonexistent/seed*/model.zip"], capsys
    )
    assert code == 2 and "--model ppo:/nonexistent/seed*/model.zip: no file matches the pattern" in err
    assert "--policy" not in err


# -- evaluate --seeds, --vs-optimum ---------------------------------------------------------------


def test_evaluate_seeds_with_episodes_takes_the_first_n(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ev"
    argv = ["evaluate", "--env", "cv2x/SingleMover-v3", "--policy", "static", "--seeds", "heldout", "--quiet"]
    assert main([*argv, "--episodes", "2", "--out", str(out)]) == 0
    with (out / "episodes.csv").open() as fh:
        seeds = [int(r["seed"]) for r in csv.DictReader(fh)]
    assert seeds == list(tasks.TASKS["singlemover"].heldout_seeds[:2])
    capsys.readouterr()
    code, err = _err([*argv, "--episodes", "49"], capsys)
    assert code == 2 and "--episodes 49: --seeds heldout gives only 48 seeds" in err
    code, err = _err([*argv, "--seed", "3"], capsys)
    assert code == 2 and "--seed does not apply with --seeds" in err


@pytest.mark.slow
def test_vs_optimum_scores_a_speed_change_model_against_its_tasks_ceiling(tmp_path: Path) -> None:
    """The shipped Traffic-v1 model commands speed changes; the ceiling commands target speeds: it is computed in
    the same env with target speeds, on the same episode, and equals the benchmark's ceiling row."""
    model = ROOT / "agents" / "models" / "traffic_seed0" / "model.zip"
    out = tmp_path / "ev"
    argv = ["evaluate", "--policy", f"ppo:{model}", "--seeds", "heldout", "--episodes", "1", "--vs-optimum"]
    assert main([*argv, "--quiet", "--out", str(out)]) == 0
    with (out / "episodes.csv").open() as fh:
        (row,) = list(csv.DictReader(fh))
    with BENCHMARK_CSV.open() as fh:
        ceiling = next(r for r in csv.DictReader(fh) if r["task"] == "traffic" and r["method"] == "optimum")
    assert int(row["seed"]) == int(ceiling["seed"]) == tasks.TASKS["traffic"].heldout_seeds[0]
    summary = json.loads((out / "summary.json").read_text())
    # the search's best episode mean here, the env replaying the ceiling's moves in the benchmark: the same
    # episode summed in another order (measured 4.4e-9 apart)
    assert summary["optimum_utility_gain"] == pytest.approx(float(ceiling["utility_gain"]), rel=1e-7)


# -- files for folders, folders for files ---------------------------------------------------------


def test_paths_of_the_wrong_kind_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    code, err = _err(["fit", "--data", str(a_file), "--out", str(tmp_path / "fit")], capsys)
    assert code == 2 and f"dataset folder {a_file} is a file, not a folder" in err
    code, err = _err(["baselines", "--dir", str(a_file)], capsys)
    assert code == 2 and f"baselines folder {a_file} is a file, not a folder" in err
    data = tmp_path / "data"
    (data / "samples.parquet").mkdir(parents=True)
    (data / "manifest.json").write_text(json.dumps({"sha256": {"samples.parquet": "0" * 64}}))
    with pytest.raises(DatasetError, match=r"samples\.parquet is a folder, not a file"):
        load_dataset(data)
    code, err = _err(["evaluate", "--policy", "ppo:", "--episodes", "1", "--quiet"], capsys)
    assert code == 2 and "no path after 'ppo:'" in err and "IsADirectory" not in err
    code, err = _err(["evaluate", "--policy", f"ppo:{tmp_path}", "--episodes", "1", "--quiet"], capsys)
    assert code == 2 and f"{tmp_path} is a folder; give the model file in it" in err


def test_a_trace_with_a_nan_position_names_the_value_vehicle_and_time(tmp_path: Path) -> None:
    fcd = tmp_path / "nan.xml"
    fcd.write_text(
        "<fcd-export>\n"
        '<timestep time="0.00"><vehicle id="a" x="0" y="10" angle="90" speed="10"/></timestep>\n'
        '<timestep time="0.10"><vehicle id="a" x="nan" y="10" angle="90" speed="10"/></timestep>\n'
        "</fcd-export>\n"
    )
    with pytest.raises(ConfigError, match=r"nan\.xml: x = nan for vehicle 'a' at t = 0\.1 s \(1 such values\)"):
        read_trace(fcd)


def test_a_gbmu_scene_too_large_names_the_vehicle_count(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _err(["gbmu", "--set", "vehicles.n_vehicles=100000", "--out", str(tmp_path / "g")], capsys)
    assert code == 2 and "vehicles.n_vehicles 100,000: one realisation would hold about" in err
    assert "lower vehicles.n_vehicles to at most 14,142" in err and "at most 0" not in err
    assert not (tmp_path / "g").exists()


# -- a second Ctrl-C during train ------------------------------------------------------------------

TINY_TRAIN = {
    "env_id": "cv2x/SingleMover-v0",
    "copies": 2,
    "env": {"max_cycles": 10, "normalise_reward": True, "overrides": ["sim.warmup_subframes=200"]},
    "ppo": {"n_steps": 16, "batch_size": 32, "n_epochs": 2, "net_arch": [16, 16]},
    "checkpoint_every": 64,
    "eval_every": 64,
    "eval_episodes": 2,
}


@pytest.mark.slow
@pytest.mark.parametrize("gap_s", [0.05, 0.3])
def test_two_ctrl_c_during_train_end_it_cleanly(tmp_path: Path, gap_s: float) -> None:
    """Before: torch printed "Exception ignored in atexit callback ... KeyboardInterrupt", or the process was
    killed by the second signal during its shutdown (exit -2)."""
    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps(TINY_TRAIN))
    out = tmp_path / "run"
    cmd = [CLI, "train", "--config", str(cfg), "--timesteps", "200000", "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (out / "eval.csv").exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    time.sleep(gap_s)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-2000:]
    assert "Exception ignored" not in stderr and "Traceback" not in stderr
    assert "cv2x-marl: interrupted: training stopped at" in stderr


# -- the numba warm-up ----------------------------------------------------------------------------


@pytest.mark.slow
def test_after_the_warm_up_a_fresh_process_compiles_nothing_for_any_env_id() -> None:
    """``make install`` runs the warm-up; a new process that resets and steps every registered env id (and the
    benchmark's policies) then finds every kernel in the cache: no cache file is added or rewritten."""
    from cv2x_marl.experiments.warm import warm

    warm(verbose=False)  # the cache as make install leaves it (quick when it is already warm)
    pkg = ROOT / "cv2x_marl"

    def cache() -> dict[str, float]:
        return {str(p): p.stat().st_mtime for p in pkg.rglob("*.nb[ic]")}

    before = cache()
    script = (
        "import numpy as np, warnings\n"
        "warnings.simplefilter('ignore')\n"
        "from cv2x_marl.env.registry import ENV_IDS, make_parallel_env\n"
        "for env_id in ENV_IDS:\n"
        "    env = make_parallel_env(env_id)\n"
        "    env.reset(seed=11)\n"
        "    for _ in range(2):\n"
        "        space = env.action_space(env.possible_agents[0])\n"
        "        if space.shape:\n"
        "            env.step({a: np.full(space.shape, 0.5, np.float32) for a in env.agents})\n"
        "        else:  # a resource choice (cv2x/Resource-v0): a list entry\n"
        "            env.step({a: np.int64(1) for a in env.agents})\n"
    )
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert before and cache() == before
