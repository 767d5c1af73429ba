"""``cv2x-marl sumo export``: a generated SUMO scenario and SUMO's own FCD trace of it, written to a folder
(issue 14).

The files are those the simulator runs for the same configuration and seed (:mod:`cv2x_marl.sim.sumo`),
so the folder can be fed back as ``vehicles.sumo_config`` or ``vehicles.trace_file``. The size of the
trace is checked before anything is written (:func:`export_seconds`).
"""

from __future__ import annotations

import shutil
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.config import ConfigError, ScenarioConfig
from cv2x_marl.io import atomic_write
from cv2x_marl.rng import RngStreams
from cv2x_marl.sim.sumo import (
    CFG_FILE,
    NET_FILE,
    ROUTE_FILE,
    Trace,
    build_network,
    build_scenario,
    read_trace,
    run_tool,
    sumo_version,
    sumocfg_xml,
)

#: most ``<vehicle>`` rows (vehicles x SUMO steps) ``sumo export`` writes to ``fcd.xml`` (and then reads back)
MAX_FCD_ROWS = 10_000_000
#: bytes of one FCD row at 6 decimals (``<vehicle id=... x=... y=... angle=... type=... speed=... pos=...
#: lane=... slope=.../>``), for the size figure
FCD_ROW_BYTES = 150


def trace_table(trace: Trace) -> Any:
    """The trace as a long Arrow table (``time, id, x, y, angle, speed``; one row per record)."""
    import pyarrow as pa

    return pa.table(
        {
            "time": pa.array(trace.time_s[trace.ti]),
            "id": pa.array(np.asarray(trace.ids, dtype=object)[trace.vi].tolist(), type=pa.string()),
            "x": pa.array(trace.x_m),
            "y": pa.array(trace.y_m),
            "angle": pa.array(trace.angle_deg),
            "speed": pa.array(trace.speed_mps),
        }
    )


def export_seconds(cfg: ScenarioConfig, seconds: float | None) -> float:
    """The SUMO seconds :func:`export_scenario` records (``seconds``, or its default), checked: a finite
    number > 0 whose FCD trace, ``n_vehicles x (seconds / step + 1)`` rows, is at most :data:`MAX_FCD_ROWS`
    (a ValueError naming ``--seconds``, the estimate and the largest accepted value otherwise)."""
    if seconds is None:
        seconds = cfg.sumo_begin_s + (cfg.sim.warmup_subframes + cfg.sim.n_subframes) / 1000.0 + 60.0
    if isinstance(seconds, bool) or not isinstance(seconds, int | float) or not np.isfinite(seconds) or seconds <= 0:
        raise ValueError(f"--seconds must be a finite number > 0, got {seconds!r}")
    step_s = cfg.traffic.rri_ms / 1000.0
    n = cfg.n_vehicles
    rows = n * (int(np.ceil(seconds / step_s)) + 1)
    if rows > MAX_FCD_ROWS:
        most = (MAX_FCD_ROWS // n - 1) * step_s
        raise ValueError(
            f"--seconds {seconds:g} would write an FCD trace of about {rows:,} rows ({n} vehicles x one row per "
            f"{step_s:g} s step; about {rows * FCD_ROW_BYTES / 1e9:,.1f} GB of fcd.xml), above the limit of "
            f"{MAX_FCD_ROWS:,} rows; lower --seconds to at most {most:,.0f} for this scenario"
        )
    return float(seconds)


def export_scenario(
    cfg: ScenarioConfig, seed: int, out_dir: Path, seconds: float | None = None, parquet: bool = False
) -> dict[str, Any]:
    """Write the generated scenario of ``cfg`` for ``seed`` and SUMO's own FCD trace of it into ``out_dir``.

    The files are those :meth:`cv2x_marl.sim.Simulator.reset` runs for the same configuration and
    seed: ``net.net.xml``, ``routes.rou.xml``, ``scenario.sumocfg`` (usable as
    ``vehicles.sumo_config``) and ``fcd.xml`` from ``sumo --fcd-output`` (usable as
    ``vehicles.trace_file``; 6 decimals), plus ``fcd.parquet`` when ``parquet``.

    Args:
        cfg: the scenario (``vehicles.sumo_config`` must be null: the scenario is generated).
        seed: the run seed (as for ``simulate --seed``).
        out_dir: an existing folder.
        seconds: SUMO seconds to record; default: the run (``sim.warmup_subframes + sim.n_subframes``)
            plus 60 s for the vehicles to enter; at most what keeps the trace within
            :data:`MAX_FCD_ROWS` (:func:`export_seconds`).
        parquet: also write the trace as parquet.

    Returns:
        A summary: files, SUMO seed and version, seconds, vehicles and timesteps of the trace.
    """
    if cfg.vehicles.sumo_config is not None:
        raise ConfigError(
            "sumo export generates a scenario from the road section; vehicles.sumo_config is set "
            f"({cfg.vehicles.sumo_config!r}): run that scenario with SUMO directly"
        )
    seconds = export_seconds(cfg, seconds)
    scenario = build_scenario(cfg, RngStreams.from_seed(seed).mobility)
    atomic_write(out_dir / NET_FILE, partial(shutil.copyfile, build_network(cfg)))
    atomic_write(out_dir / ROUTE_FILE, partial(shutil.copyfile, scenario.sumocfg.parent / ROUTE_FILE))
    text = sumocfg_xml(NET_FILE, ROUTE_FILE, scenario.step_s, scenario.seed)
    atomic_write(out_dir / CFG_FILE, lambda p: p.write_text(text))
    fcd = "fcd.xml"
    atomic_write(
        out_dir / fcd,
        lambda p: run_tool(
            "sumo",
            ["-c", CFG_FILE, "--fcd-output", str(p), "--precision", "6", "--end", repr(float(seconds))],
            cwd=out_dir,
        ),
    )
    trace = read_trace(out_dir / fcd)
    files = [NET_FILE, ROUTE_FILE, CFG_FILE, fcd]
    if parquet:
        import pyarrow.parquet as pq

        table = trace_table(trace)
        atomic_write(out_dir / "fcd.parquet", lambda p: pq.write_table(table, p))
        files.append("fcd.parquet")
    return {
        "files": files,
        "seed": seed,
        "sumo_seed": scenario.seed,
        "sumo_version": sumo_version(),
        "step_s": scenario.step_s,
        "seconds": float(seconds),
        "n_vehicles": len(trace.ids),
        "n_timesteps": int(trace.time_s.size),
    }
