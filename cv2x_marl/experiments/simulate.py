"""`cv2x-marl simulate`: one stage-1 run, written as links table, summary and figure."""

from __future__ import annotations

import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import cv2x_marl
from cv2x_marl.config import ScenarioConfig, to_dict
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.runs import run_folder
from cv2x_marl.sim import Simulator


def links_table(links: dict[str, np.ndarray]) -> pa.Table:
    """The links columns as an Arrow table."""
    return pa.table({k: pa.array(v) for k, v in links.items()})


def write_parquet(table: pa.Table, path: Path) -> Path:
    """Write a parquet file atomically."""
    return atomic_write(path, lambda p: pq.write_table(table, p))


def simulate(
    cfg: ScenarioConfig,
    seed: int,
    n_subframes: int,
    out_dir: Path | None,
    progress: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Reset, run and (when ``out_dir``) write ``links.parquet``, ``summary.json``, ``prr_vs_distance.png``.

    ``out_dir`` is a run folder (:class:`cv2x_marl.runs.RunFolder`): locked, refused when not
    empty unless ``overwrite``, removed again if the run fails.
    """
    with run_folder(out_dir, "simulate", overwrite=overwrite, parameters={"seed": seed, "n_subframes": n_subframes}):
        return _simulate(cfg, seed, n_subframes, out_dir, progress)


def _simulate(cfg: ScenarioConfig, seed: int, n_subframes: int, out_dir: Path | None, progress: bool) -> dict[str, Any]:
    from tqdm import tqdm

    t0 = time.perf_counter()
    sim = Simulator(cfg)
    sim.reset(seed)
    with tqdm(total=n_subframes, unit="sf", desc="simulate", file=sys.stderr, disable=not progress) as bar:
        result = sim.run(n_subframes, progress=bar.update)
    summary: dict[str, Any] = result.metrics.summary()
    summary.update(
        {
            "seed": seed,
            "n_subframes": n_subframes,
            "n_vehicles": sim.n,
            "n_reselections": sim.n_reselections,
            "runtime_s": result.runtime_s,
            "total_runtime_s": time.perf_counter() - t0,
            "prr_at_m": {str(d): result.metrics.prr_at(d) for d in (50, 100, 200, 300)},
            "versions": {
                "cv2x_marl": cv2x_marl.__version__,
                "numpy": np.__version__,
                "python": platform.python_version(),
            },
            "config": to_dict(cfg),
        }
    )
    if out_dir is not None:
        out_dir = Path(out_dir)
        if result.links is not None:
            write_parquet(links_table(result.links), out_dir / "links.parquet")
        write_json(out_dir / "summary.json", summary)
        from cv2x_marl.plotting import plot_prr_vs_distance

        plot_prr_vs_distance(summary, out_dir / "prr_vs_distance.png")
    return summary
