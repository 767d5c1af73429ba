"""Stage-1 dataset of 10 paper runs plus the stage-2 fit, timed end to end (goal: < 60 s, one core).

Run with ``python benchmarks/bench_regression.py``; writes ``benchmarks/results/bench_regression.json``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from cv2x_marl.config import preset  # noqa: E402
from cv2x_marl.experiments.dataset import build_dataset, run_fit  # noqa: E402
from cv2x_marl.io import write_json  # noqa: E402


def main() -> None:
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "ds"
        t0 = time.perf_counter()
        manifest = build_dataset(preset("paper"), 10, 0, data, progress=False)
        rows["dataset_s"] = time.perf_counter() - t0
        rows["samples"] = manifest["rows"]
        for kind in ("linear", "logistic"):
            t1 = time.perf_counter()
            run_fit(data, Path(tmp) / f"fit-{kind}", kind=kind, figures=False)
            rows[f"fit_{kind}_s"] = time.perf_counter() - t1
        t2 = time.perf_counter()
        run_fit(data, Path(tmp) / "fit-figures", kind="linear", figures=True)
        rows["fit_linear_with_figures_s"] = time.perf_counter() - t2
    rows["dataset_plus_linear_fit_s"] = rows["dataset_s"] + rows["fit_linear_s"]
    for k, v in rows.items():
        print(f"{k}: {v:.3f}" if isinstance(v, float) else f"{k}: {v}")
    write_json(Path("benchmarks/results/bench_regression.json"), rows)


if __name__ == "__main__":
    main()
