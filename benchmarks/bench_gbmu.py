"""GBMU speed: 144 realisations x 10,000 iterations, vectorised across realisations (goal: <= 5 s, one core).

Snapshot generation (stage-1 resets) is timed apart; the GBMU figure is the climb plus the
ground-truth evaluation of start and end. Writes ``benchmarks/results/bench_gbmu.json``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import time  # noqa: E402
from pathlib import Path  # noqa: E402

from cv2x_marl.config import preset  # noqa: E402
from cv2x_marl.experiments.gbmu_study import _snapshots, gbmu_inputs  # noqa: E402
from cv2x_marl.io import write_json  # noqa: E402
from cv2x_marl.policies.gbmu import climb, gbmu_direction, oracle_direction  # noqa: E402
from cv2x_marl.regression import TwoDistanceModel  # noqa: E402
from cv2x_marl.rng import derive_seeds  # noqa: E402
from cv2x_marl.sim.ground_truth import MoverLinks  # noqa: E402
from cv2x_marl.utility import utility_log  # noqa: E402


def main() -> None:
    cfg = preset("paper")
    model = TwoDistanceModel.paper_table2()
    t0 = time.perf_counter()
    snaps = _snapshots(cfg, derive_seeds(0, 144), progress=False)
    links = MoverLinks.from_snapshots(cfg, snaps, [0] * 144)
    inputs = gbmu_inputs(snaps, [0] * 144, links, 200.0)
    rows = {"snapshots_s": time.perf_counter() - t0}
    for name in ("gbmu", "greedy", "oracle"):
        if name == "oracle":
            direction = oracle_direction(links.success, links.target)
        else:
            direction = gbmu_direction(inputs, model, fairness=name == "gbmu")
        t1 = time.perf_counter()
        res = climb(links.start_m, direction, 1.0, 0.0, 10_000)  # Th_pos = 0: all 10,000 iterations
        utility_log(links.success(links.start_m), links.target)
        utility_log(links.success(res.final_m), links.target)
        rows[f"{name}_144x10000_s"] = time.perf_counter() - t1
    for k, v in rows.items():
        print(f"{k}: {v:.3f}")
    write_json(Path("benchmarks/results/bench_gbmu.json"), rows)


if __name__ == "__main__":
    main()
