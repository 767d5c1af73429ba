"""Simulator speed: the paper preset, and highway scaling with vehicle count.

Run with ``make bench`` (or ``python benchmarks/bench_sim.py [--quick]``). Single-threaded BLAS is
forced so the figures are per core. Prints a markdown table and writes ``benchmarks/results/bench_sim.json``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from cv2x_marl.config import apply_overrides, preset  # noqa: E402
from cv2x_marl.io import write_json  # noqa: E402
from cv2x_marl.sim import Simulator  # noqa: E402


def best_of(fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def bench_paper(repeat: int) -> dict:
    cfg = preset("paper")
    sim = Simulator(cfg)

    def once() -> None:
        sim.reset(seed=0)
        sim.run(cfg.sim.n_subframes)

    # run alone (reset and warm-up excluded), with the links table recorded
    def run_only() -> float:
        sim.reset(seed=0)
        t0 = time.perf_counter()
        sim.run(cfg.sim.n_subframes)
        return time.perf_counter() - t0

    run_s = min(run_only() for _ in range(repeat))
    total_s = best_of(once, repeat)
    return {"case": "paper preset, 10240 subframes", "run_s": run_s, "reset_plus_run_s": total_s}


def bench_highway(n_vehicles: int, seconds: float, repeat: int, max_range_m: float) -> dict:
    density = 0.1
    length = n_vehicles / density
    cfg = apply_overrides(
        preset("highway-legacy"),
        [
            f"road.length_m={length}",
            f"link.max_range_m={max_range_m}",
            "metrics.record_links=false",
            "sim.warmup_subframes=0",
        ],
    )
    sim = Simulator(cfg)
    n_sub = int(seconds * 1000)
    times = []
    for _ in range(repeat):
        sim.reset(seed=0)
        t0 = time.perf_counter()
        res = sim.run(n_sub)
        times.append(time.perf_counter() - t0)
    run_s = min(times)
    return {
        "case": f"highway-legacy {n_vehicles} vehicles ({length:g} m, 0.1 veh/m), {seconds:g} s, "
        f"cut-off {max_range_m:g} m",
        "n_vehicles": n_vehicles,
        "simulated_s": seconds,
        "run_s": run_s,
        "real_time_factor": seconds / run_s,
        "prr_mean": res.metrics.summary()["prr_mean"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer repeats and sizes")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/bench_sim.json"))
    args = ap.parse_args()
    repeat = 2 if args.quick else 5
    rows = [bench_paper(repeat)]
    print(
        f"paper preset, 10240 subframes: run {rows[0]['run_s']:.3f} s, "
        f"reset+warm-up+run {rows[0]['reset_plus_run_s']:.3f} s"
    )
    sizes = [100, 500, 1000] if args.quick else [100, 250, 500, 1000, 2000]
    print("\n| vehicles | road (m) | simulated (s) | run time (s) | x real time | us per vehicle-period |")
    print("|---:|---:|---:|---:|---:|---:|")
    for n in sizes:
        r = bench_highway(n, 10.0, 1 if n >= 2000 else max(1, repeat // 2), 1000.0)
        rows.append(r)
        per = r["run_s"] / (n * 100) * 1e6
        print(f"| {n} | {n * 10:g} | 10 | {r['run_s']:.3f} | {r['real_time_factor']:.1f} | {per:.1f} |")
    machine = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
    }
    write_json(args.out, {"machine": machine, "rows": rows})
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
