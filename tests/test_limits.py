"""Resources refused up front (issue 25, defects 11 and 13): the env's step and episode length, the
position search's grid, evaluate's episodes, the GBMU study's realisations and step, and the
`sumo export` trace length are checked before anything is allocated or written; the error names
the option and the figure, the CLI exits 2 and leaves no output folder."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pytest

import cv2x_marl  # noqa: F401 - registers the env ids
from cv2x_marl.cli import main
from cv2x_marl.config import preset
from cv2x_marl.env import MobilityEnv, parallel_env_v2
from cv2x_marl.env.options import MAX_CYCLES
from cv2x_marl.env.planning import MAX_GRID_POINTS, SearchGridError, _grid
from cv2x_marl.experiments.evaluate import MAX_ROWS, episode_seeds
from cv2x_marl.experiments.gbmu_study import MAX_STUDY_BYTES, study_bytes
from cv2x_marl.rng import derive_seeds

FAST = {"overrides": ["sim.warmup_subframes=200"]}
PAPER_DIAGONAL = "636.4"  # the paper grid's road box, 450 m x 450 m


def _refused(argv: list[str], out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI with ``--out out``; assert exit 2 and no folder; return the one-line message."""
    assert main([*argv, "--out", str(out)]) == 2
    assert not out.exists()
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    return err


def test_env_refuses_a_step_larger_than_the_scene() -> None:
    with pytest.raises(ValueError, match=rf"invalid env argument max_step_m=1000000000000.0; .*<= {PAPER_DIAGONAL}"):
        MobilityEnv(max_step_m=1e12, **FAST)
    with pytest.raises(ValueError, match=r"max_step_m=2001.0; .*<= 2000.1 .*road box 2000 m x 21 m"):
        MobilityEnv(preset="highway", max_step_m=2001.0)
    with pytest.raises(ValueError, match=rf"max_step_m=1000.0; .*<= {PAPER_DIAGONAL}"):
        gymnasium.make("cv2x/SingleMover-v2", max_step_m=1000.0)
    assert MobilityEnv(max_step_m=636.0, **FAST).max_step_m == 636.0  # v0: no plan to search


def test_env_refuses_episodes_longer_than_max_cycles_limit() -> None:
    with pytest.raises(
        ValueError, match=rf"invalid env argument max_cycles=1000000000; allowed: integer in \[1, {MAX_CYCLES}\]"
    ):
        MobilityEnv(max_cycles=10**9, **FAST)
    with pytest.raises(ValueError, match="max_cycles=10001"):
        gymnasium.make("cv2x/SingleMover-v2", max_cycles=MAX_CYCLES + 1)
    assert MobilityEnv(max_cycles=MAX_CYCLES, **FAST).max_cycles == MAX_CYCLES


def test_env_refuses_a_plan_search_grid_above_the_limit() -> None:
    # 100 steps x 200 m each way: a 40,000 m square on the plan's 20 m grid, 2001 x 2001 points
    with pytest.raises(SearchGridError, match=r"max_cycles=100, max_step_m=200.0: .*4,004,001 points .*4,000,000"):
        parallel_env_v2(max_step_m=200.0, **FAST)
    parallel_env_v2(max_step_m=199.9, **FAST)  # 2000 x 2000 points: at the limit
    parallel_env_v2(max_step_m=600.0, roi=True, **FAST)  # the region of interest bounds the square


def test_search_grid_is_refused_before_it_is_allocated() -> None:
    lo, hi = np.zeros(2), np.full(2, 1e9)
    with pytest.raises(SearchGridError, match=r"10,000,000,200,000,001 points \(about 560,000.0 TB\)"):
        _grid(lo, hi, 10.0)
    assert _grid(np.zeros(2), np.full(2, 10.0), 2.5).shape == (25, 2)
    assert MAX_GRID_POINTS == 4_000_000


def test_env_takes_a_single_override_string_as_one_assignment() -> None:
    assert MobilityEnv(overrides="vehicles.n_vehicles=5").n == 5
    for bad in (5, [1], None):
        with pytest.raises(
            ValueError, match=r"invalid env argument overrides=.*; allowed: a section\.key=value string"
        ):
            MobilityEnv(overrides=bad)


def test_episode_seeds_stream_the_derived_seeds() -> None:
    assert list(episode_seeds(7, 40)) == derive_seeds(7, 40)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--max-step", "1e5"], rf"max_step_m=100000.0; allowed: finite number > 0 and <= {PAPER_DIAGONAL}"),
        (["--max-step", "600"], r"max_step_m=600.0: .*36,012,001 points \(about 2.0 GB\)"),
        (["--episodes", "1e9"], rf"--episodes 1,000,000,000 x 1 mover.*lower --episodes to at most {MAX_ROWS:,}"),
        (["--vs-optimum", "--max-step", "30"], r"the optimum policy .* 2.5 m grid: 5,764,801 points"),
        (["--policy", "optimum", "--max-step", "30"], r"the optimum policy .* 2.5 m grid: 5,764,801 points"),
    ],
)
def test_evaluate_refuses_sizes_up_front(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    import re

    err = _refused(["evaluate", "--quiet", "--episodes", "1", *argv], tmp_path / "out", capsys)
    assert re.search(message, err), err


def test_evaluate_refuses_episodes_times_movers_above_the_row_limit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _refused(
        ["evaluate", "--quiet", "--env", "cv2x/Mobility-v2", "--episodes", str(MAX_ROWS // 21 + 1)],
        tmp_path / "out",
        capsys,
    )
    assert f"x 21 mover(s) would keep {(MAX_ROWS // 21 + 1) * 21:,} per-mover rows" in err
    assert f"lower --episodes to at most {MAX_ROWS // 21:,} for this env" in err


def test_gbmu_refuses_realisations_above_the_memory_limit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = _refused(["gbmu", "--quiet", "--realizations", "1e9"], tmp_path / "out", capsys)
    total, per = study_bytes(preset("paper"), 10**9, 10_000, 5)
    assert f"--realizations 1,000,000,000 would hold about {total / 1e9:,.1f} GB" in err
    assert f"lower --realizations to at most {MAX_STUDY_BYTES // per:,} for this scenario" in err


def test_gbmu_refuses_a_step_larger_than_the_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = _refused(["gbmu", "--quiet", "--step", "1e12"], tmp_path / "out", capsys)
    assert f"--step must be > 0 and at most {PAPER_DIAGONAL} m" in err and "got 1e+12" in err


def test_sumo_export_refuses_a_trace_above_the_row_limit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = _refused(["sumo", "export", "--seconds", "1e9"], tmp_path / "out", capsys)
    # 21 vehicles x (1e9 s / 0.1 s + 1) rows; the largest accepted: (10,000,000 // 21 - 1) x 0.1 s
    assert "--seconds 1e+09 would write an FCD trace of about 210,000,000,021 rows" in err
    assert "lower --seconds to at most 47,619 for this scenario" in err
