"""Stage-1 dataset (`cv2x-marl dataset`) and the stage-2 fit (`cv2x-marl fit`).

A dataset folder holds ``samples.parquet`` and ``manifest.json``; the manifest is written last,
so a folder without one is an interrupted or foreign run and is refused.
"""

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
from cv2x_marl.config import ConfigError, ScenarioConfig, show_value, to_dict
from cv2x_marl.experiments.simulate import expected_link_rows, write_parquet
from cv2x_marl.io import InputFileError, atomic_write, read_text_limited, write_json
from cv2x_marl.parallel import map_on_ray
from cv2x_marl.regression import MAX_NSV_CAP, FitData, FitError, TwoDistanceModel, fit_two_distance
from cv2x_marl.regression.model import MODEL_FILE

# re-exported for env/mobility_env.py only (it imports it from here); every other caller imports
# cv2x_marl.regression.model.load_model; drop this line once mobility_env.py does too
from cv2x_marl.rng import derive_seeds
from cv2x_marl.runs import RunFolder, previous_run_aside, sha256_file
from cv2x_marl.sim import Simulator
from cv2x_marl.sim.memory import ENV_LIMIT, estimate_memory_bytes, memory_limit
from cv2x_marl.sim.memory import format_bytes as _gb
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.yamlcore import load_json

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
    check_dataset_memory(cfg, runs, aggregate_window_ms != 0)
    params = {"runs": runs, "seed": seed, "aggregate_window_ms": aggregate_window_ms}
    with RunFolder(out_dir, "dataset", overwrite=overwrite, parameters=params):
        return _build_dataset(cfg, runs, seed, Path(out_dir), aggregate_window_ms, progress, ray, address)


#: bytes of one sample row while the dataset is built: the column dtypes of :func:`_one_run`
#: (run, tx, rx int32; subframe int64; d_m, l_m, p_success, sinr_db float64; nsv int16; outcome bool)
SAMPLE_ROW_BYTES = 3 * 4 + 8 + 4 * 8 + 2 + 1
#: bytes per row of the aggregation's temporaries (window, key, unique's order, first index, inverse: int64)
AGGREGATE_ROW_BYTES = 5 * 8
#: bytes per run besides its samples: its seed in lists and the manifest, its part's arrays
RUN_OVERHEAD_BYTES = 2_000


def estimate_dataset_bytes(cfg: ScenarioConfig, runs: int, aggregate: bool = False) -> dict[str, int]:
    """Peak memory of :func:`build_dataset`, from the configuration alone (nothing is allocated).

    Every run's samples are kept until the end, then concatenated (two copies at once), and aggregated
    with ``aggregate``; the simulator of one run comes on top
    (:func:`cv2x_marl.sim.memory.estimate_memory_bytes`). Sample rows per run are the links-table rows
    of the memory model (:func:`cv2x_marl.experiments.simulate.expected_link_rows`: every transmission
    to every receiver in range, half-duplex pairs included, so an upper bound).

    Returns:
        ``rows_per_run``, ``rows`` (all runs), ``samples`` (bytes of the samples and their
        concatenation), ``simulator`` (bytes of one run's simulator) and ``total`` (bytes).
    """
    per_run = expected_link_rows(cfg, cfg.sim.n_subframes)
    rows = runs * per_run
    samples = rows * (2 * SAMPLE_ROW_BYTES + (AGGREGATE_ROW_BYTES if aggregate else 0)) + runs * RUN_OVERHEAD_BYTES
    simulator = estimate_memory_bytes(cfg)["total"]
    return {
        "rows_per_run": per_run,
        "rows": rows,
        "samples": samples,
        "simulator": simulator,
        "total": samples + simulator,
    }


def check_dataset_memory(cfg: ScenarioConfig, runs: int, aggregate: bool = False) -> dict[str, int]:
    """Refuse a dataset whose estimated peak memory (:func:`estimate_dataset_bytes`) exceeds the limit.

    The limit is ``CV2X_MARL_MEMORY_LIMIT_GB`` (GB) when set, else the memory available now
    (:func:`cv2x_marl.sim.memory.available_memory_bytes`; not read for estimates below 256 MiB).

    Raises:
        ConfigError: naming ``--runs``, the estimate, the limit and how many runs fit.
    """
    est = estimate_dataset_bytes(cfg, runs, aggregate)
    checked = memory_limit(est["total"])
    if checked is None or est["total"] <= checked[0]:
        return est
    limit, source = checked
    per_run = (est["samples"] + runs - 1) // runs
    fit = max(0, (limit - est["simulator"]) // max(1, per_run))
    fits = f"about {fit:,} runs fit" if fit >= 1 else "not one run fits"
    raise ConfigError(
        f"dataset --runs {runs:,}: {runs:,} runs x up to {est['rows_per_run']:,} link samples per run "
        f"({cfg.n_vehicles} vehicles, sim.n_subframes={cfg.sim.n_subframes}) = {est['rows']:,} samples, "
        f"estimated {_gb(est['total'])} of memory, above the limit of {_gb(limit)} ({source}); {fits}: lower "
        f"--runs, --subframes or the vehicle count, or set {ENV_LIMIT}"
    )


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
        if data_dir.exists():
            raise DatasetError(
                f"dataset folder {data_dir} is a file, not a folder: give the folder `cv2x-marl dataset --out` wrote"
            )
        raise DatasetError(f"dataset folder {data_dir} does not exist")
    mpath = data_dir / MANIFEST
    if not mpath.exists():
        aside = previous_run_aside(data_dir)
        hint = (
            f"; a run that was replacing it was killed: the previous dataset is intact in {aside}, and the next "
            f"`cv2x-marl dataset --out {data_dir}` (or any run with that --out) puts it back first"
            if aside is not None
            else f" (create one with `cv2x-marl dataset --out {data_dir}`)"
        )
        raise DatasetError(f"{data_dir} has no {MANIFEST}: not a complete dataset{hint}")
    try:
        manifest = load_json(read_text_limited(mpath, MAX_MANIFEST_BYTES, "dataset manifest"))
    except InputFileError as exc:
        raise DatasetError(str(exc)) from exc
    except ValueError as exc:  # json.JSONDecodeError, too deep a document
        raise DatasetError(f"{mpath} is not valid JSON: {exc}") from exc
    if not isinstance(manifest, dict):
        raise DatasetError(
            f"{mpath} holds a JSON {type(manifest).__name__}, not the object of a dataset manifest: not a dataset "
            f"written by `cv2x-marl dataset`; rebuild it"
        )
    spath = data_dir / SAMPLES
    checksums = manifest.get("sha256")
    expected = checksums.get(SAMPLES) if isinstance(checksums, dict) else None
    if not isinstance(expected, str):
        raise DatasetError(
            f"{mpath} has no SHA-256 of {SAMPLES} (key sha256.{SAMPLES}): the manifest was edited or is not "
            "from `cv2x-marl dataset`; rebuild the dataset"
        )
    if not spath.is_file():
        what = "is a folder, not a file" if spath.is_dir() else "is missing"
        raise DatasetError(f"{spath} {what}: the dataset is incomplete or was changed; rebuild the dataset")
    if sha256_file(spath) != expected:
        raise DatasetError(
            f"{spath} does not match the SHA-256 in {mpath}: the file was changed or corrupted; rebuild the dataset"
        )
    try:
        table = pq.read_table(spath)
    except (OSError, pa.ArrowInvalid) as exc:
        raise DatasetError(f"cannot read {spath}: {exc}") from exc
    missing = {"run", "tx", "rx", "d_m", "l_m", "nsv", "p_success"} - set(table.column_names)
    if missing:
        raise DatasetError(f"{spath} lacks columns {sorted(missing)}")
    if table.num_rows != manifest.get("rows"):
        raise DatasetError(f"{spath} has {table.num_rows} rows, the manifest says {show_value(manifest.get('rows'))}")
    return _numeric_columns(table, spath), manifest


#: the largest ``manifest.json`` read, in bytes (a manifest lists one seed per run: some 30 bytes each)
MAX_MANIFEST_BYTES = 256 * 2**20
#: the columns a dataset may hold; all of them are numbers (``outcome`` true/false)
NUMERIC_COLUMNS = ("run", "tx", "rx", "subframe", "window", "d_m", "l_m", "nsv", "p_success", "outcome", "rate", "n")


def _numeric_columns(table: pa.Table, spath: Path) -> dict[str, np.ndarray]:
    """The columns of ``table`` as arrays, refusing (naming the file, the column and the count of bad rows)
    a known column that holds no numbers, and any empty (null), NaN or infinite value in a numeric column."""
    cols: dict[str, np.ndarray] = {}
    rows = table.num_rows
    for name in table.column_names:
        column = table.column(name)
        kind = column.type
        numeric = pa.types.is_integer(kind) or pa.types.is_floating(kind) or pa.types.is_boolean(kind)
        if not numeric:
            if name in NUMERIC_COLUMNS:
                raise DatasetError(
                    f"{spath}: column {name!r} holds {kind} values, not numbers; a dataset written by "
                    "`cv2x-marl dataset` holds numbers only: rebuild it"
                )
            continue  # a column of the user's own; the fit reads only the columns it knows
        if column.null_count:
            raise DatasetError(
                f"{spath}: column {name!r} has {column.null_count:,} of {rows:,} rows empty (null); a dataset holds "
                "a number in every row: rebuild it"
            )
        values = column.to_numpy()
        if pa.types.is_floating(kind):
            bad = int(np.count_nonzero(~np.isfinite(values)))
            if bad:
                raise DatasetError(
                    f"{spath}: column {name!r} has {bad:,} of {rows:,} rows that are NaN or infinite; a dataset "
                    "holds finite numbers: rebuild it"
                )
        cols[name] = values
    return cols


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
            f"fit --out is a folder (it receives {MODEL_FILE}, tables and figures), got the file name {out_dir}; "
            f"use e.g. --out {out_dir.with_suffix('')}"
        )
    if not 0 <= nsv_cap <= MAX_NSV_CAP:
        raise FitError(
            f"--nsv-cap {show_value(nsv_cap)} is out of range: NSV values 0 to the cap get their own coefficients "
            f"(the paper: 6); allowed range: [0, {MAX_NSV_CAP}]"
        )
    cols, manifest = load_dataset(data_dir)  # a bad dataset is refused before the folder is touched
    if target is None:
        target = "rate" if manifest.get("aggregate_window_ms") else "p_success"
    params = {"data": str(data_dir), "kind": kind, "target": target, "nsv_cap": nsv_cap, "seed": seed}
    with RunFolder(out_dir, "fit", overwrite=overwrite, parameters=params, inputs=[data_dir]):
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
    model_path = out_dir / MODEL_FILE
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
