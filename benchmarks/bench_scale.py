"""Simulator cost vs vehicle count at corridor scale (issue 13): wall time and peak memory.

The highway-legacy preset (``--preset``: or highway, the standard's procedures) at 0.1 veh/m (road
length N / 0.1 m, distances wrapped), links table off
(``metrics.record_links=false``), with an interference and link cut-off ``link.max_range_m``. Each
vehicle count runs in its own subprocess so its peak resident size (``ru_maxrss``) is its own:
``Simulator(cfg)``, ``reset`` with ``--warmup-s`` of warm-up, then ``run`` for ``--measure-s``.

The cut-off: by default the distance at which the mean received power (EIRP minus the WINNER+ B1
LOS path loss of the preset, no shadowing) is ``--below-noise-db`` (10 dB) under the noise floor
(noise power plus noise figure). A single interferer there raises the noise-plus-interference by
0.4 dB, and a signal there cannot be decoded; with the highway preset (29 dBm EIRP, -102.45 dBm
noise at 5.9 GHz, h' = 1.5 m) that is about 2.8 km, where the preset's own default (1 km) leaves
the received power 8 dB above noise. ``--max-range-m`` sets it directly.

Run with ``python benchmarks/bench_scale.py [--sizes 1000 2000 5000 10000] [--preset highway] [--label before]``;
prints a markdown table and writes ``benchmarks/results/bench_scale.json`` (rows are merged by
label, so a ``before`` and an ``after`` run sit side by side). Single-threaded BLAS is forced so
the figures are per core.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

DENSITY = 0.1  # veh/m


def config_for(n_vehicles: int, max_range_m: float, warmup_s: float, name: str = "highway-legacy"):  # type: ignore[no-untyped-def]
    """The preset ``name`` (highway-legacy, or highway: the standard's procedures; highway-3gpp is its
    former name) with ``n_vehicles`` at 0.1 veh/m, the cut-off, links table off; ``warmup_s`` of fixed
    warm-up (highway: the warm-up runs until every vehicle has reselected once, at least ``warmup_s``)."""
    from cv2x_marl.config import apply_overrides, preset

    return apply_overrides(
        preset(name),
        [
            f"road.length_m={n_vehicles / DENSITY}",
            f"link.max_range_m={max_range_m}",
            "metrics.record_links=false",
            f"sim.warmup_subframes={round(warmup_s * 1000)}",
        ],
    )


def cutoff_m(below_noise_db: float) -> float:
    """Distance (m) where the highway preset's mean received power is ``below_noise_db`` under noise."""
    from cv2x_marl.config import preset
    from cv2x_marl.sim import channel
    from cv2x_marl.units import noise_power_dbm

    cfg = preset("highway")
    r = cfg.radio
    eirp = r.tx_power_dbm + r.tx_antenna_gain_dbi + r.rx_antenna_gain_dbi
    target_pl = eirp - (noise_power_dbm(r.noise_dbm, r.noise_figure_db) - below_noise_db)
    lo, hi = 10.0, 1e6
    for _ in range(100):  # path loss grows with distance: bisect
        mid = 0.5 * (lo + hi)
        pl = float(channel.path_loss_db(cfg.channel, r.carrier_hz, np.array([mid, 0.0]), True))
        lo, hi = (mid, hi) if pl < target_pl else (lo, mid)
    return round(lo, 1)


def child(n_vehicles: int, max_range_m: float, warmup_s: float, measure_s: float, name: str = "highway-legacy") -> dict:
    """One measurement, in this process: returns the row (peak RSS of this process included)."""
    t0 = time.perf_counter()
    from cv2x_marl.sim import Simulator
    from cv2x_marl.sim.memory import estimate_memory_bytes

    t_import = time.perf_counter() - t0
    rss_import = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    cfg = config_for(n_vehicles, max_range_m, warmup_s, name)
    n_sub = round(measure_s * 1000)
    est = estimate_memory_bytes(cfg, n_sub)["total"]
    t0 = time.perf_counter()
    sim = Simulator(cfg)
    snap = sim.reset(seed=0)
    t_reset = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = sim.run(n_sub)
    t_run = time.perf_counter() - t0
    del snap
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: kB
    simulated = sim.subframe / 1000.0  # warm-up (until_reselected: as long as it took) + measured
    return {
        "n_vehicles": cfg.n_vehicles,
        "road_m": cfg.road.length_m,
        "max_range_m": max_range_m,
        "preset": name,
        "warmup_s": warmup_s,
        "simulated_s": simulated,
        "measured_s": measure_s,
        "import_s": t_import,
        "init_reset_warmup_s": t_reset,
        "run_s": t_run,
        "total_s": t_reset + t_run,
        "wall_s_per_simulated_s": (t_reset + t_run) / simulated,
        "run_s_per_simulated_s": t_run / measure_s,
        "peak_rss_bytes": rss,
        "rss_after_import_bytes": rss_import,
        "memory_estimate_bytes": est,
        "prr_mean": res.metrics.summary()["prr_mean"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 2000, 5000, 10000])
    ap.add_argument("--warmup-s", type=float, default=0.2, help="simulated warm-up (s)")
    ap.add_argument("--measure-s", type=float, default=1.0, help="simulated measurement (s)")
    ap.add_argument("--below-noise-db", type=float, default=10.0)
    ap.add_argument("--max-range-m", type=float, default=None, help="cut-off (m); default from --below-noise-db")
    ap.add_argument(
        "--preset",
        default="highway-legacy",
        choices=["highway-legacy", "highway", "highway-3gpp"],
        help="scenario preset: highway-legacy (the simplified procedures; the tables of docs/performance.md's "
        "'highway' columns), highway (the standard's; its former name highway-3gpp)",
    )
    ap.add_argument("--label", default="current", help="name of this set of rows in the JSON (e.g. before, after)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/bench_scale.json"))
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    max_range = args.max_range_m if args.max_range_m is not None else cutoff_m(args.below_noise_db)
    if args.child is not None:
        print(json.dumps(child(args.child, max_range, args.warmup_s, args.measure_s, args.preset)))
        return

    print(f"cut-off link.max_range_m = {max_range:g} m; warm-up {args.warmup_s:g} s, measured {args.measure_s:g} s")
    print(f"preset {args.preset}")
    head = "| vehicles | simulated (s) | init+reset+warm-up (s) | run (s) | wall s per simulated s | peak RSS (MB) |"
    print("\n" + head + " estimate (MB) |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for n in args.sizes:
        cmd = [sys.executable, __file__, "--child", str(n), "--max-range-m", str(max_range)]
        cmd += ["--warmup-s", str(args.warmup_s), "--measure-s", str(args.measure_s), "--preset", args.preset]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(f"| {n} | failed: {proc.stderr.strip().splitlines()[-1:]} |")
            rows.append({"n_vehicles": n, "error": proc.stderr[-2000:]})
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append(r)
        print(
            f"| {r['n_vehicles']} | {r['simulated_s']:.2f} | {r['init_reset_warmup_s']:.2f} | {r['run_s']:.2f} | "
            f"{r['wall_s_per_simulated_s']:.2f} | {r['peak_rss_bytes'] / 1e6:.0f} | "
            f"{r['memory_estimate_bytes'] / 1e6:.0f} |"
        )
    data: dict = {}
    if args.out.exists():
        data = json.loads(args.out.read_text())
    data.setdefault("runs", {})[args.label] = {
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(),
        },
        "max_range_m": max_range,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(data, indent=2) + "\n")
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
