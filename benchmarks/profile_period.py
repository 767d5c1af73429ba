"""Where a corridor-scale period spends its time (issue 13): cProfile of the simulator's run, and the pair
step with and without the Verlet list.

The scenario is ``benchmarks/bench_scale.py``'s (the preset at 0.1 veh/m, links table off, the cut-off
``--max-range-m``). After ``reset`` (0.2 s warm-up; ``highway``'s runs until every vehicle reselected), it
profiles ``run`` for ``--seconds`` simulated seconds and prints the functions by own time (each numba
kernel is one line), then times ``Simulator._pairs`` for ``--periods`` periods in two simulators, one with
the Verlet list (``pair_skin_m`` 5 % of the cut-off) and one sweeping every period (``pair_skin_m = 0``).

Run with ``python benchmarks/profile_period.py [--vehicles 10000] [--max-range-m 2800] [--preset highway]``.
The figures in docs/performance.md ("Tiles, a Verlet list and a radix sort") come from it. Single-threaded
BLAS is forced so the figures are per core.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import cProfile  # noqa: E402
import pstats  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from bench_scale import config_for  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vehicles", type=int, default=10000)
    ap.add_argument("--max-range-m", type=float, default=2800.0, help="cut-off (m)")
    ap.add_argument("--preset", default="highway-legacy", choices=["highway-legacy", "highway"])
    ap.add_argument("--seconds", type=float, default=0.5, help="simulated seconds profiled")
    ap.add_argument("--periods", type=int, default=10, help="periods of the pair-step timing")
    ap.add_argument("--top", type=int, default=15, help="functions listed")
    args = ap.parse_args()

    from cv2x_marl.sim import Simulator, mobility

    cfg = config_for(args.vehicles, args.max_range_m, 0.2, args.preset)
    t0 = time.perf_counter()
    sim = Simulator(cfg)
    sim.reset(1)
    print(f"{args.preset}, {args.vehicles} vehicles, cut-off {args.max_range_m:g} m")
    print(f"set-up, reset and warm-up: {time.perf_counter() - t0:.2f} s")
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    sim.run(round(args.seconds * 1000))
    prof.disable()
    print(f"run of {args.seconds:g} simulated s: {time.perf_counter() - t0:.2f} s")
    pstats.Stats(prof).sort_stats("tottime").print_stats(args.top)

    sims = {}
    for name, skin in (("Verlet list", None), ("sweep every period", 0.0)):
        s = Simulator(cfg)
        if skin is not None:
            s.pair_skin_m = skin
        s.reset(1)
        sims[name] = s
    times: dict[str, list[float]] = {name: [] for name in sims}
    for _ in range(args.periods):
        for name, s in sims.items():
            pos = mobility.positions_m(s.road, s.state) + s.offsets_m
            t0 = time.perf_counter()
            s._pairs(pos)
            times[name].append(time.perf_counter() - t0)
            s.run(s.rri)
    for name, ts in times.items():
        print(f"pair step, {name}: median {1e3 * np.median(ts):.1f} ms, max {1e3 * max(ts):.1f} ms per period")


if __name__ == "__main__":
    main()
