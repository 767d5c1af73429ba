"""Stage-1 dataset (`cv2x-marl dataset`) and the stage-2 fit (`cv2x-marl fit`).

A dataset folder holds ``samples.parquet`` and ``manifest.json``; the manifest is written last,
so a folder without one is an interrupted or foreign run and is refused.
"""

from __future__ import annotations

import json
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
from cv2x_marl.experiments.simulate import write_parquet
from cv2x_marl.io import write_json
from cv2x_marl.regression import FitData, FitError, TwoDistanceModel, fit_two_distance
from cv2x_marl.rng import derive_seeds
from cv2x_marl.runs import RunFolder, sha256_file
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.metrics import CAUSE_CODE

MANIFEST = "manifest.json"
SAMPLES = "samples.parquet"
TARGETS = ("p_success", "outcome", "rate")


class DatasetError(ValueError):
    """A dataset folder is missing, incomplete or corrupt."""


#: ``aggregate_window_ms`` of one window per run, whatever the warm-up (``--reading paper``)
WHOLE_RUN = -1


def _aggregate(cols: dict[str, np.ndarray], window_ms: int, n_vehicles: int) -> dict[str, np.ndarray]:
    """Group per (run, tx, rx, window, NSV): mean d, l, P; empirical rate; count.
    ``window_ms`` = :data:`WHOLE_RUN`: one window per run (window 0)."""
    subframe = cols["subframe"]
    window = np.zeros_like(subframe) if window_ms == WHOLE_RUN else subframe // window_ms
    nsv = np.minimum(cols["nsv"].astype(np.int64), 255)
    key = (
        ((cols["run"].astype(np.int64) * n_vehicles + cols["tx"]) * n_vehicles + cols["rx"]) * (window.max() + 1)
        + window
    ) * 256 + nsv
    _, first, inv = np.unique(key, return_index=True, return_inverse=True)
    count = np.bincount(inv)

    def mean(x: np.ndarray) -> np.ndarray:
        return np.bincount(inv, weights=x.astype(np.float64)) / count

    return {
        "run": cols["run"][first],
        "tx": cols["tx"][first],
        "rx": cols["rx"][first],
        "window": window[first],
        "nsv": cols["nsv"][first],
        "d_m": mean(cols["d_m"]),
        "l_m": mean(cols["l_m"]),
        "p_success": mean(cols["p_success"]),
        "rate": mean(cols["outcome"]),
        "n": count,
    }


def build_dataset(
    cfg: ScenarioConfig,
    runs: int,
    seed: int,
    out_dir: Path,
    aggregate_window_ms: int = 0,
    progress: bool = True,
    overwrite: bool = False,
    ray: bool = False,
    address: str | None = None,
) -> dict[str, Any]:
    """Run ``runs`` independent stage-1 simulations and write their link samples.

    Samples are the links to target receivers (half-duplex pairs are not targets, paper Sec. 4)
    with ``d_m``, ``l_m``, ``nsv``, ``p_success``, ``outcome`` (per transmission), or, with
    ``aggregate_window_ms > 0``, per (run, link, window, NSV) means with the empirical ``rate``
    (windows of subframes counted from the start of the warm-up; :data:`WHOLE_RUN`: one window,
    the whole measured run, however long the warm-up).
    ``out_dir`` is a run folder (:class:`cv2x_marl.runs.RunFolder`); the manifest records the
    SHA-256 of ``samples.parquet``, checked by :func:`load_dataset`. With ``ray`` the runs are
    Ray tasks (:func:`cv2x_marl.parallel.map_on_ray`; a local Ray, or the cluster at ``address``):
    the same samples, in the same order, as the serial loop.
    """
    if runs < 1:
        raise DatasetError(f"--runs must be >= 1, got {runs}")
    if aggregate_window_ms < 0 and aggregate_window_ms != WHOLE_RUN:
        raise DatasetError(
            f"--aggregate-window-ms must be >= 0 (or {WHOLE_RUN}: the whole run), got {aggregate_window_ms}"
        )
    if not cfg.metrics.record_links:
        raise DatasetError("metrics.record_links=false leaves no link samples; set it to true")
    if aggregate_window_ms and cfg.vehicles.population == "open":
        raise DatasetError(
            "--aggregate-window-ms groups link samples by (tx, rx) slot over a window, and with "
            "vehicles.population=open a slot is reused by different vehicles; use per-packet samples "
            "(--aggregate-window-ms 0) or vehicles.population=fixed"
        )
    params = {"runs": runs, "seed": seed, "aggregate_window_ms": aggregate_window_ms}
    with RunFolder(out_dir, "dataset", overwrite=overwrite, parameters=params):
        return _build_dataset(cfg, runs, seed, Path(out_dir), aggregate_window_ms, progress, ray, address)


def _one_run(cfg: ScenarioConfig, run_id: int, run_seed: int) -> dict[str, np.ndarray]:
    """The link samples of one stage-1 run (a Ray task with ``--ray``)."""
    sim = Simulator(cfg)
    sim.reset(run_seed)
    links = sim.run(cfg.sim.n_subframes).links
    assert links is not None
    target = links["cause"] != CAUSE_CODE["half_duplex"]
    return {
        "run": np.full(int(target.sum()), run_id, dtype=np.int32),
        "tx": links["tx"][target],
        "rx": links["rx"][target],
        "subframe": links["subframe"][target],
        "d_m": links["distance_m"][target],
        "l_m": links["interferer_distance_m"][target],
        "nsv": links["nsv"][target],
        "p_success": links["p_success"][target],
        "outcome": links["outcome"][target],
        "sinr_db": links["sinr_db"][target],
    }


def _build_dataset(
    cfg: ScenarioConfig,
    runs: int,
    seed: int,
    out_dir: Path,
    aggregate_window_ms: int,
    progress: bool,
    ray: bool,
    address: str | None,
) -> dict[str, Any]:
    from tqdm import tqdm

    t0 = time.perf_counter()
    seeds = derive_seeds(seed, runs)
    n_vehicles = cfg.n_slots  # tx / rx are slot numbers
    if ray:
        from cv2x_marl.parallel import map_on_ray

        parts = map_on_ray(_one_run, [(cfg, i, s) for i, s in enumerate(seeds)], address)
    else:
        bar = tqdm(seeds, desc="dataset", unit="run", file=sys.stderr, disable=not progress)
        parts = [_one_run(cfg, run_id, run_seed) for run_id, run_seed in enumerate(bar)]
    cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    if aggregate_window_ms:
        cols = _aggregate(cols, aggregate_window_ms, n_vehicles)
    write_parquet(pa.table(cols), out_dir / SAMPLES)
    nsv_counts = np.bincount(cols["nsv"].astype(np.int64))
    manifest = {
        "kind": "cv2x_marl stage-1 dataset",
        "runs": runs,
        "seed": seed,
        "run_seeds": seeds,
        "aggregate_window_ms": aggregate_window_ms,
        "rows": int(cols["d_m"].shape[0]),
        "rows_per_nsv": {str(k): int(c) for k, c in enumerate(nsv_counts) if c},
        "columns": list(cols),
        "sha256": {SAMPLES: sha256_file(out_dir / SAMPLES)},
        "target_default": "p_success",
        "runtime_s": time.perf_counter() - t0,
        "versions": {
            "cv2x_marl": cv2x_marl.__version__,
            "numpy": np.__version__,
            "pyarrow": pa.__version__,
            "python": platform.python_version(),
        },
        "config": to_dict(cfg),
    }
    write_json(out_dir / MANIFEST, manifest)
    return manifest


def load_dataset(data_dir: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read ``samples.parquet`` and ``manifest.json`` of a dataset folder, with clear errors."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise DatasetError(f"dataset folder {data_dir} does not exist")
    mpath = data_dir / MANIFEST
    if not mpath.exists():
        raise DatasetError(
            f"{data_dir} has no {MANIFEST}: not a complete dataset "
            f"(create one with `cv2x-marl dataset --out {data_dir}`)"
        )
    try:
        manifest = json.loads(mpath.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{mpath} is not valid JSON: {exc}") from exc
    spath = data_dir / SAMPLES
    expected = (manifest.get("sha256") or {}).get(SAMPLES)
    if expected is not None and spath.is_file() and sha256_file(spath) != expected:
        raise DatasetError(
            f"{spath} does not match the SHA-256 in {mpath}: the file was changed or corrupted; rebuild the dataset"
        )
    try:
        table = pq.read_table(spath)
    except (OSError, pa.ArrowInvalid) as exc:
        raise DatasetError(f"cannot read {spath}: {exc}") from exc
    cols = {name: table.column(name).to_numpy() for name in table.column_names}
    missing = {"run", "tx", "rx", "d_m", "l_m", "nsv", "p_success"} - set(cols)
    if missing:
        raise DatasetError(f"{spath} lacks columns {sorted(missing)}")
    if table.num_rows != manifest.get("rows"):
        raise DatasetError(f"{spath} has {table.num_rows} rows, the manifest says {manifest.get('rows')}")
    return cols, manifest


def fit_data(cols: dict[str, np.ndarray], target: str) -> FitData:
    """The fit's arrays from dataset columns; split groups are runs (links when only one run)."""
    if target not in cols:
        raise FitError(f"target {target!r} is not a column of this dataset; columns: {', '.join(cols)}")
    run = cols["run"].astype(np.int64)
    group = run if np.unique(run).size > 1 else cols["tx"].astype(np.int64) * 100_000 + cols["rx"].astype(np.int64)
    return FitData(
        cols["d_m"].astype(np.float64),
        cols["l_m"].astype(np.float64),
        cols["nsv"].astype(np.int64),
        cols[target].astype(np.float64),
        group,
    )


def _table2_md(model: TwoDistanceModel) -> str:
    ks = range(model.nsv_cap + 1)
    head = "| NSV | " + " | ".join(str(k) + ("+" if k == model.nsv_cap else "") for k in ks) + " |"
    lines = [f"Table 2 - NSV-specific coefficients ({model.kind}, log10 of metres)", "", head]
    lines.append("|---" * (model.nsv_cap + 2) + "|")
    for name, vals in (("alpha", model.alpha), ("beta", model.beta), ("gamma", model.gamma)):
        lines.append(f"| {name} | " + " | ".join(f"{v:.2f}" for v in vals) + " |")
    fb = [s["nsv"] for s in model.stats if s.get("fallback_from") is not None]
    if fb:
        lines += [
            "",
            "Fallback (too few samples, coefficients borrowed): "
            + ", ".join(
                f"NSV {s['nsv']} from NSV {s['fallback_from']}"
                for s in model.stats
                if s.get("fallback_from") is not None
            ),
        ]
    return "\n".join(lines) + "\n"


def _table3_md(model: TwoDistanceModel) -> str:
    ks = range(model.nsv_cap + 1)
    head = "| NSV | " + " | ".join(str(k) + ("+" if k == model.nsv_cap else "") for k in ks) + " |"
    lines = [f"Table 3 - Regression statistics ({model.kind})", "", head, "|---" * (model.nsv_cap + 2) + "|"]

    def fmt(v: Any) -> str:
        return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.2f}"

    lines.append("| Instances | " + " | ".join(str(s["instances"]) for s in model.stats) + " |")
    lines.append("| R Square (train) | " + " | ".join(fmt(s["r2"]) for s in model.stats) + " |")
    lines.append("| R Square (held out) | " + " | ".join(fmt(s["r2_test"]) for s in model.stats) + " |")
    lines.append("| Brier (held out) | " + " | ".join(fmt(s["brier_test"]) for s in model.stats) + " |")
    return "\n".join(lines) + "\n"


MODEL = "model.json"


def run_fit(
    data_dir: Path,
    out_dir: Path,
    kind: str = "linear",
    target: str | None = None,
    nsv_cap: int = 6,
    test_fraction: float = 0.2,
    seed: int = 0,
    min_samples: int = 30,
    compare: bool = False,
    figures: bool = True,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Fit the dataset of ``data_dir`` and write the fit folder ``out_dir``.

    ``out_dir`` (a run folder, :class:`cv2x_marl.runs.RunFolder`) receives ``model.json``,
    ``table2.md``, ``table3.md``, with ``compare`` ``model_comparison.{md,json}``, and the
    figures ``fig2_surface.png`` and ``fit_quality.png``; the dataset folder is only read.
    ``target`` None: ``rate`` for an aggregated dataset (the paper's reading), else ``p_success``.
    """
    out_dir = Path(out_dir)
    if out_dir.suffix == ".json":
        raise FitError(
            f"fit --out is a folder (it receives {MODEL}, tables and figures), got the file name {out_dir}; "
            f"use e.g. --out {out_dir.with_suffix('')}"
        )
    cols, manifest = load_dataset(data_dir)  # a bad dataset is refused before the folder is touched
    if target is None:
        target = "rate" if manifest.get("aggregate_window_ms") else "p_success"
    params = {"data": str(data_dir), "kind": kind, "target": target, "nsv_cap": nsv_cap, "seed": seed}
    with RunFolder(out_dir, "fit", overwrite=overwrite, parameters=params):
        return _fit(
            cols,
            manifest,
            Path(data_dir),
            out_dir,
            kind,
            target,
            nsv_cap,
            test_fraction,
            seed,
            min_samples,
            compare,
            figures,
        )


def _fit(
    cols: dict[str, np.ndarray],
    manifest: dict[str, Any],
    data_dir: Path,
    out_dir: Path,
    kind: str,
    target: str,
    nsv_cap: int,
    test_fraction: float,
    seed: int,
    min_samples: int,
    compare: bool,
    figures: bool,
) -> dict[str, Any]:
    from cv2x_marl.io import atomic_write

    data = fit_data(cols, target)
    kinds = [kind] + ([k for k in ("linear", "logistic") if k != kind] if compare else [])
    models = {k: fit_two_distance(data, k, nsv_cap, test_fraction, seed, min_samples) for k in kinds}
    model = models[kind]
    model.provenance.update(
        {
            "dataset": str(data_dir.resolve()),
            "dataset_rows": manifest.get("rows"),
            "dataset_runs": manifest.get("runs"),
            "dataset_seed": manifest.get("seed"),
            "dataset_sha256": (manifest.get("sha256") or {}).get(SAMPLES),
            "aggregate_window_ms": manifest.get("aggregate_window_ms"),
            "target": target,
            "nsv_cap": nsv_cap,
        }
    )
    model_path = out_dir / MODEL
    model.save(model_path)
    atomic_write(out_dir / "table2.md", lambda p: p.write_text(_table2_md(model)))
    atomic_write(out_dir / "table3.md", lambda p: p.write_text(_table3_md(model)))
    result: dict[str, Any] = {"model": str(model_path), "kind": kind, "per_nsv": model.to_dict()["per_nsv"]}
    result["overall_test"] = model.provenance["overall_test"]
    if compare:
        result["comparison"] = {k: m.provenance["overall_test"] for k, m in models.items()}
        rows = ["| model | R^2 held out | Brier held out | log-loss held out |", "|---|---:|---:|---:|"]
        for k, m in models.items():
            o = m.provenance["overall_test"]
            rows.append(f"| {k} | {o['r2']:.3f} | {o['brier']:.4f} | {o['log_loss']:.4f} |")
        atomic_write(out_dir / "model_comparison.md", lambda p: p.write_text("\n".join(rows) + "\n"))
        write_json(out_dir / "model_comparison.json", result["comparison"])
    if figures:
        from cv2x_marl.plotting import plot_fit_quality, plot_surface

        plot_surface(model, out_dir / "fig2_surface.png")
        plot_fit_quality(model, out_dir / "fit_quality.png")
    return result


def load_model(path: Path | str) -> TwoDistanceModel:
    """Load a model: ``paper-table2`` (the preset), a fit folder (its ``model.json``) or a model file."""
    if str(path) == "paper-table2":
        return TwoDistanceModel.paper_table2()
    path = Path(path)
    if path.is_dir():
        path = path / MODEL
    return TwoDistanceModel.load(path)
