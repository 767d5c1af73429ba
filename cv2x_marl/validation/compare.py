"""Simulator vs the analytical Mode 4 model of Gonzalez-Martin et al. (2019): PDR(d) and loss causes.

Runs :class:`cv2x_marl.sim.simulator.Simulator` on a highway configured as closely as the
configuration allows to the analytical model's setting (:func:`simulator_overrides`; the mapping
and what differs is in ``docs/validation.md``), evaluates
:func:`cv2x_marl.validation.mode4_analytical.analytical_pdr` with the same parameters, and writes:

* ``validation.json``: settings, per-density curves (10 m bins) of both, the table distances,
  loss-cause shares, and the note on the authors' Veins results;
* ``pdr_vs_distance.csv``: one row per (density, source, distance bin);
* ``table.csv``: PDR and the four loss shares at 50/100/200/300/400 m;
* ``pdr_<density>.png``: one figure per density (PDR and loss causes, both sources).

Usage (the command line's ``validate``, which runs :func:`run_validation` in a run folder)::

    cv2x-marl validate --out /tmp/validation

Every file is written to a temporary name in ``--out`` and renamed into place.
"""

from __future__ import annotations

import csv
import functools
import io
import json
import math
import os
import tempfile
import time
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.config import apply_overrides, from_dict, preset
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.sim.simulator import Simulator
from cv2x_marl.validation.mode4_analytical import PAPER_FORMATS, analytical_pdr

#: distances of the comparison tables, m
TABLE_DISTANCES_M: tuple[float, ...] = (50.0, 100.0, 200.0, 300.0, 400.0)
#: loss causes: (our metrics name, key of the analytical model)
CAUSES: tuple[tuple[str, str], ...] = (
    ("half_duplex", "delta_hd"),
    ("sensitivity", "delta_sen"),
    ("propagation", "delta_pro"),
    ("collision", "delta_col"),
)
#: the simulator's PER table for each of the paper's (packet bytes, sub-channels) formats
PER_CURVE_OF_FORMAT: dict[tuple[int, int], str] = {
    (190, 4): "r1-160284-190b-r0.7",
    (190, 2): "r1-160284-190b-r0.5",
}
SENSING_THRESHOLD_DBM = -90.5
BIN_M = 10.0
MAX_DISTANCE_M = 500.0
VEINS_NOTE = (
    "The authors' Veins results and MATLAB model curves are read from the figures of their repository "
    "(github.com/msepulcre/C-V2X, fig/ and simulations/, MATLAB .fig files read with scipy.io.loadmat), "
    "shipped as cv2x_marl/validation/data/gonzalez_martin_2019_figures.csv; they exist for the 12 "
    "configurations of STUDY_CONFIGURATIONS x STUDY_DENSITIES, at 0, 25, ..., 500 m."
)
#: the configurations of the authors' figures (and of the study): (sub-channels, packets per s, dBm)
STUDY_CONFIGURATIONS: tuple[tuple[int, float, float], ...] = (
    (4, 10.0, 20.0),
    (2, 10.0, 20.0),
    (4, 20.0, 20.0),
    (4, 10.0, 23.0),
)
#: ... each at these densities, veh/m
STUDY_DENSITIES: tuple[float, ...] = (0.1, 0.2, 0.3)
_FIGURES_CSV = "gonzalez_martin_2019_figures.csv"
#: ``validate --assumptions model``: the analytical model's stated assumptions as simulator switches (over
#: validate's base, which already has the model's propagation, BLER, sensing threshold, keep probability 0,
#: sensing by every SCI above P_SEN and reselection on one sensing map per period, the model's ``1 / tau``
#: chance of selecting at the same time): uniform choice among the candidates (eq. 26), Step 3's threshold
#: raised in 0.1 dB steps as the authors' code does, Step 2 alone with probability alpha(CBR) (eqs. 21-23), each
#: interferer alone (eq. 14). Not switchable: the independent half duplex of eq. 7 and the overlap of two
#: vehicles' candidate sets of eq. 30 (docs/validation.md, "The model's assumptions")
MODEL_ASSUMPTION_SETS: tuple[str, ...] = (
    "sps.selection=uniform",
    "sps.threshold_step_db=0.1",
    "sps.threshold_increase=model_cbr",
    "link.interference=independent",
)
ASSUMPTIONS: tuple[str, ...] = ("simulator", "model")


def assumption_sets(assumptions: str) -> tuple[str, ...]:
    """The ``--set`` strings of ``validate --assumptions``: none for ``simulator``, :data:`MODEL_ASSUMPTION_SETS`
    for ``model``."""
    if assumptions not in ASSUMPTIONS:
        raise ValueError(f"assumptions must be one of {ASSUMPTIONS}, got {assumptions!r}")
    return MODEL_ASSUMPTION_SETS if assumptions == "model" else ()


@functools.cache
def _figures_table() -> np.ndarray:
    text = resources.files("cv2x_marl.validation").joinpath("data", _FIGURES_CSV).read_text()
    rows = [ln for ln in text.splitlines() if ln and not ln.startswith("#")][1:]
    return np.array([[float(v) for v in ln.split(",")] for ln in rows])


def authors_figures(
    n_subchannels: int, packets_per_s: float, tx_power_dbm: float, density_veh_per_m: float
) -> dict[str, np.ndarray] | None:
    """The authors' curves for one configuration of their figures (190 B), or None for another.

    Returns:
        ``distance_m`` [21] (0, 25, ..., 500 m); their Veins simulator's ``pdr`` and unconditional loss
        shares ``delta_hd``, ``delta_sen``, ``delta_pro``, ``delta_col`` (collisions), which sum with
        the PDR to 1; ``sci_lost`` (the figure's "SCI lost" line, drawn beside them: not a fifth share);
        and ``matlab_pdr``, the PDR of their MATLAB implementation of the analytical model.
    """
    t = _figures_table()
    key = np.array([n_subchannels, packets_per_s, tx_power_dbm, density_veh_per_m], dtype=np.float64)
    rows = t[np.all(np.isclose(t[:, :4], key[None, :], rtol=0.0, atol=1e-9), axis=1)]
    if rows.shape[0] == 0:
        return None
    names = ("distance_m", "pdr", "delta_hd", "delta_sen", "delta_pro", "delta_col", "sci_lost", "matlab_pdr")
    return {name: rows[:, 4 + i].copy() for i, name in enumerate(names)}


def simulator_overrides(
    density_veh_per_m: float,
    packets_per_s: float,
    tx_power_dbm: float,
    n_subchannels: int,
    packet_bytes: int,
    n_subframes: int,
) -> dict[str, dict[str, Any]]:
    """Configuration sections (over the ``highway-legacy`` preset, on which docs/validation.md's tables were
    measured: like the analytical model, its sensing counts every SCI above ``P_SEN``; the standard's
    procedures can be set on top with ``--set``) that match the analytical setting.

    Args:
        density_veh_per_m: vehicles per metre of road (both directions together).
        packets_per_s: packet rate; the reservation interval is ``1000 / packets_per_s`` ms.
        tx_power_dbm: transmit power; antenna gains are set to 0 dBi (the model has none).
        n_subchannels: sub-channels per subframe, one per packet.
        packet_bytes: with ``n_subchannels``, one of the paper's formats (190 B with 2 or 4).
        n_subframes: measured subframes.

    Returns:
        Nested sections for :func:`cv2x_marl.config.from_dict`.
    """
    fmt = (int(packet_bytes), int(n_subchannels))
    if fmt not in PAPER_FORMATS:
        raise ValueError(
            f"(packet_bytes, n_subchannels) = {fmt} is not one of the paper's formats {sorted(PAPER_FORMATS)}"
        )
    rri_ms = 1000.0 / packets_per_s
    if rri_ms != round(rri_ms) or not 20 <= rri_ms <= 1000:
        raise ValueError(f"packets_per_s must give a whole reservation interval in [20, 1000] ms, got {packets_per_s}")
    data_rbs = PAPER_FORMATS[fmt][0]
    noise_dbm = -95.0 - 10.0 * math.log10(50.0 / data_rbs)  # over the data RBs, 9 dB noise figure included
    return {
        "road": {"kind": "highway", "length_m": 2000.0, "lanes_per_direction": 1, "wrap_distances": True},
        "vehicles": {"density_veh_per_m": float(density_veh_per_m)},
        "radio": {
            "tx_power_dbm": float(tx_power_dbm),
            "carrier_hz": 5.91e9,
            "noise_dbm": noise_dbm - 9.0,
            "noise_figure_db": 9.0,
            "tx_antenna_gain_dbi": 0.0,
            "rx_antenna_gain_dbi": 0.0,
            "sensitivity_dbm": SENSING_THRESHOLD_DBM,
        },
        "channel": {"pathloss": "winner_b1", "los": "always", "shadowing_std_db": 3.0, "fading": "none"},
        "traffic": {"rri_ms": round(rri_ms), "packet_bytes": int(packet_bytes), "synchronous": False},
        "sps": {
            "n_subchannels": int(n_subchannels),
            "subchannel_rbs": data_rbs,
            "t1_subframes": 1,
            "selection_window_subframes": round(rri_ms),
            # P_SEN is a power over the packet's RBs; the RSRP threshold is per resource element
            "rsrp_threshold_dbm": SENSING_THRESHOLD_DBM - 10.0 * math.log10(12 * data_rbs),
            "selection": "3gpp",
            "min_candidate_fraction": 0.2,
            "keep_probability": 0.0,
        },
        # the analytical model has no in-band emission
        "link": {
            "model": "per_table",
            "per_curve": PER_CURVE_OF_FORMAT[fmt],
            "inband_emission_db": None,
            "inband_emission_model": "flat",
        },
        "metrics": {"prr_bin_m": BIN_M, "max_distance_m": MAX_DISTANCE_M, "record_links": False},
        "sim": {"n_subframes": int(n_subframes), "warmup_subframes": 1000, "warmup_mode": "until_reselected"},
    }


def simulate_seed(
    overrides: dict[str, dict[str, Any]], seed: int, extra_sets: Sequence[str] = ()
) -> dict[str, np.ndarray]:
    """One simulator run (one seed) on the matched highway: its per-bin counts.

    Args:
        overrides: sections over the ``highway-legacy`` preset (:func:`simulator_overrides`).
        seed: the run's seed.
        extra_sets: ``section.key=value`` strings applied last (``--set`` of the command line).

    Returns:
        ``n`` [B] link samples per 10 m bin, ``decoded`` [B], and one [B] count per loss cause (our
        names), plus ``n_vehicles`` (0-d) and ``runtime_s`` (0-d, wall time of the run).
    """
    t0 = time.perf_counter()
    cfg = apply_overrides(from_dict(overrides, preset("highway-legacy")), extra_sets)
    n_bins = round(MAX_DISTANCE_M / BIN_M)
    sim = Simulator(cfg)
    sim.reset(seed=int(seed))
    acc = sim.run(cfg.sim.n_subframes).metrics
    out = {"n": acc.bin_n[:n_bins].copy(), "decoded": acc.bin_decoded[:n_bins].copy()}
    for name, _ in CAUSES:
        out[name] = acc.bin_causes[CAUSE_CODE[name], :n_bins].copy()
    out["n_vehicles"] = np.asarray(cfg.n_vehicles)
    out["runtime_s"] = np.asarray(time.perf_counter() - t0)
    return out


def _simulate_seed_task(task: tuple[dict[str, dict[str, Any]], int, tuple[str, ...]]) -> dict[str, np.ndarray]:
    return simulate_seed(*task)


def _check_run_size(n_subframes: int, workers: int) -> None:
    """Refuse a run of fewer than one subframe or one worker, before anything runs or is written."""
    if n_subframes < 1:
        raise ValueError(f"n_subframes must be >= 1, got {n_subframes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")


def simulate_many(
    tasks: Sequence[tuple[dict[str, dict[str, Any]], int, tuple[str, ...]]], workers: int = 1
) -> list[dict[str, np.ndarray]]:
    """:func:`simulate_seed` of every ``(overrides, seed, extra_sets)`` task, in task order; with
    ``workers > 1`` in that many spawned processes (:func:`cv2x_marl.parallel.map_in_processes`, the
    largest scenes first; each run is independent and seeded, so the results are the same as in one
    process)."""
    from cv2x_marl.parallel import map_in_processes

    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    return list(map_in_processes(_simulate_seed_task, list(tasks), workers, cost=_task_cost))


def _task_cost(task: tuple[dict[str, dict[str, Any]], int, tuple[str, ...]]) -> float:
    """Relative cost of a task: links per subframe x subframes (vehicles squared x packet rate)."""
    ov = task[0]
    n = ov["vehicles"]["density_veh_per_m"] * ov["road"]["length_m"]
    return float(n * n / ov["traffic"]["rri_ms"] * (ov["sim"]["n_subframes"] + ov["sim"]["warmup_subframes"]))


def pool_counts(per_seed: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The per-bin counts of several seeds summed, plus ``pdr_per_seed`` [K, B] (NaN where a seed has no
    sample in a bin) and ``n_vehicles`` (0-d)."""
    keys = ("n", "decoded", *(c for c, _ in CAUSES))
    out = {k: np.sum([r[k] for r in per_seed], axis=0) for k in keys}
    with np.errstate(invalid="ignore", divide="ignore"):
        out["pdr_per_seed"] = np.array([r["decoded"] / np.where(r["n"] > 0, r["n"], np.nan) for r in per_seed])
    out["n_vehicles"] = per_seed[0]["n_vehicles"]
    return out


def run_simulator(
    overrides: dict[str, dict[str, Any]], seeds: Sequence[int], extra_sets: Sequence[str] = (), workers: int = 1
) -> dict[str, np.ndarray]:
    """Run the simulator once per seed (:func:`simulate_seed`) and pool the per-bin counts
    (:func:`pool_counts`); ``workers`` processes (:func:`simulate_many`)."""
    tasks = [(overrides, int(seed), tuple(extra_sets)) for seed in seeds]
    return pool_counts(simulate_many(tasks, workers))


def standard_error_pct(pdr_per_seed: np.ndarray) -> np.ndarray:
    """[B] standard error of the pooled PDR of each bin over seeds, in percentage points:
    ``100 std(PDR_k, ddof=1) / sqrt(K)`` over the K seeds' PDRs (NaN with fewer than two seeds).

    The seeds' runs are independent; within a run the link samples are not (the same vehicles keep
    their resources for 5-15 periods), so the spread between seeds, not the binomial one of the
    pooled samples, measures the uncertainty of a curve.
    """
    k = np.sum(np.isfinite(pdr_per_seed), axis=0)
    if pdr_per_seed.shape[0] < 2:
        return np.full(pdr_per_seed.shape[1], np.nan)
    valid = np.isfinite(pdr_per_seed)
    mean = np.where(valid, pdr_per_seed, 0.0).sum(axis=0) / np.maximum(k, 1)
    dev2 = np.where(valid, (pdr_per_seed - mean[None, :]) ** 2, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.asarray(np.where(k >= 2, 100.0 * np.sqrt(dev2 / (k - 1)) / np.sqrt(k), np.nan))


def _pooled(counts: dict[str, np.ndarray], lo: int, hi: int) -> dict[str, float]:
    """PDR and loss shares over the bins ``[lo, hi)``."""
    n = int(counts["n"][lo:hi].sum())
    row = {"n": float(n), "pdr": float(counts["decoded"][lo:hi].sum() / n) if n else math.nan}
    for name, key in CAUSES:
        row[key] = float(counts[name][lo:hi].sum() / n) if n else math.nan
    return row


def compare_density(
    density_veh_per_m: float,
    packets_per_s: float,
    tx_power_dbm: float,
    n_subchannels: int,
    packet_bytes: int,
    n_subframes: int,
    seeds: Sequence[int],
    extra_sets: Sequence[str] = (),
    counts: dict[str, np.ndarray] | None = None,
    workers: int = 1,
) -> dict[str, Any]:
    """Simulator and analytical model at one density: curves, table rows, loss shares, the mean
    absolute deviation of the paper's eq. 35 (over the 10 m bins, in percentage points), the standard
    error of the simulator's curve over seeds (:func:`standard_error_pct`) and, for the configurations
    of the authors' figures, their Veins simulator's curve and loss shares (:func:`authors_figures`).

    ``counts``: the seeds' pooled counts (:func:`pool_counts`) when already simulated; None: run them
    here in ``workers`` processes."""
    centres = (np.arange(round(MAX_DISTANCE_M / BIN_M)) + 0.5) * BIN_M
    table_d = np.asarray(TABLE_DISTANCES_M)
    ana = analytical_pdr(
        np.concatenate([centres, table_d]),
        1000.0 * density_veh_per_m,
        packets_per_s,
        tx_power_dbm,
        n_subchannels,
        packet_bytes,
        sensing_threshold_dbm=SENSING_THRESHOLD_DBM,
    )
    nb = centres.size
    t0 = time.perf_counter()
    overrides = simulator_overrides(
        density_veh_per_m, packets_per_s, tx_power_dbm, n_subchannels, packet_bytes, n_subframes
    )
    if counts is None:
        counts = run_simulator(overrides, seeds, extra_sets, workers)
    runtime_s = time.perf_counter() - t0
    keys = ["pdr"] + [k for _, k in CAUSES]
    sim_curve = [_pooled(counts, j, j + 1) | {"distance_m": float(c)} for j, c in enumerate(centres)]
    ana_curve = [{"distance_m": float(c)} | {k: float(ana[k][j]) for k in keys} for j, c in enumerate(centres)]
    table = []
    for t, d in enumerate(table_d):
        j = round(d / BIN_M)  # the two bins [d - 10, d + 10)
        table.append(
            {
                "distance_m": float(d),
                "simulator": _pooled(counts, j - 1, j + 1),
                "analytical": {k: float(ana[k][nb + t]) for k in keys},
                "veins": None,
            }
        )
    lost_sim = sum(int(counts[name].sum()) for name, _ in CAUSES)
    lost_ana = float(sum(ana[k][:nb].sum() for _, k in CAUSES))
    shares = {
        "simulator": {k: int(counts[name].sum()) / max(lost_sim, 1) for name, k in CAUSES},
        "analytical": {k: float(ana[k][:nb].sum()) / lost_ana for _, k in CAUSES},
    }
    mad_pct = {
        k: float(100.0 * np.nanmean([abs(s[k] - a[k]) for s, a in zip(sim_curve, ana_curve, strict=True)]))
        for k in keys
    }
    se = standard_error_pct(counts["pdr_per_seed"])
    for row, e in zip(sim_curve, se, strict=True):
        row["se_pct"] = float(e)
    share_diff = max(abs(shares["simulator"][k] - shares["analytical"][k]) for _, k in CAUSES)
    veins = authors_figures(n_subchannels, packets_per_s, tx_power_dbm, density_veh_per_m)
    versus_veins: dict[str, Any] | None = None
    if veins is not None:
        sim_pdr = np.array([r["pdr"] for r in sim_curve])
        ok = np.isfinite(sim_pdr)
        at = veins["distance_m"]
        sim_at = np.interp(at, centres[ok], sim_pdr[ok])  # the 10 m curve at the figures' 25 m points
        ana_at = analytical_pdr(
            at, 1000.0 * density_veh_per_m, packets_per_s, tx_power_dbm, n_subchannels, packet_bytes
        )["pdr"]
        lost_v = float(sum(veins[k].sum() for _, k in CAUSES))
        versus_veins = {
            "distance_m": at.tolist(),
            "veins": {k: veins[k].tolist() for k in ["pdr", *(k for _, k in CAUSES), "sci_lost"]},
            "mad_pct_simulator_vs_veins": float(100.0 * np.mean(np.abs(sim_at - veins["pdr"]))),
            "mad_pct_analytical_vs_veins": float(100.0 * np.mean(np.abs(ana_at - veins["pdr"]))),
            "loss_shares_0_500m": {k: float(veins[k].sum()) / lost_v for _, k in CAUSES},
        }
    return {
        "density_veh_per_m": density_veh_per_m,
        "n_vehicles": int(counts["n_vehicles"]),
        "seeds": [int(s) for s in seeds],
        "simulator_runtime_s": runtime_s,
        "simulator_link_samples": int(counts["n"].sum()),
        "analytical_cbr": float(ana["cbr"]),
        "analytical_alpha": float(ana["alpha"]),
        "analytical_threshold_step3_dbm": float(ana["threshold_step3_dbm"]),
        "curve": {"simulator": sim_curve, "analytical": ana_curve, "veins": None},
        "table": table,
        "loss_shares_0_500m": shares,
        "mad_pct_0_500m": mad_pct,
        "se_pct_0_500m": {
            "mean": float(np.nanmean(se)) if np.any(np.isfinite(se)) else math.nan,
            "max": float(np.nanmax(se)) if np.any(np.isfinite(se)) else math.nan,
        },
        "loss_share_max_abs_diff": float(share_diff),
        "authors_veins": versus_veins,
        "simulator_overrides": overrides,
    }


def _write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file next to ``path``, then rename it into place."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _csv_bytes(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> bytes:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue().encode()


def _figure(result: dict[str, Any], settings: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sim, ana = result["curve"]["simulator"], result["curve"]["analytical"]
    d = [r["distance_m"] for r in sim]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax1.plot(d, [r["pdr"] for r in sim], "b-", label="simulator (cv2x_marl)")
    ax1.plot(d, [r["pdr"] for r in ana], "b--", label="analytical (Gonzalez-Martin 2019)")
    veins = result.get("authors_veins")
    if veins is not None:
        ax1.plot(veins["distance_m"], veins["veins"]["pdr"], "ko", ms=3, label="authors' Veins simulation")
    ax1.set(xlabel="distance [m]", ylabel="PDR", ylim=(0, 1), xlim=(0, MAX_DISTANCE_M))
    ax1.grid(True)
    ax1.legend(loc="lower left")
    for (_, key), colour in zip(CAUSES, ("tab:blue", "tab:purple", "tab:red", "k"), strict=True):
        label = key.removeprefix("delta_").upper()
        ax2.plot(d, [r[key] for r in sim], "-", color=colour, label=f"{label} simulator")
        ax2.plot(d, [r[key] for r in ana], "--", color=colour, label=f"{label} analytical")
    ax2.set(xlabel="distance [m]", ylabel="loss probability", ylim=(0, 1), xlim=(0, MAX_DISTANCE_M))
    ax2.grid(True)
    ax2.legend(loc="upper left", fontsize=8, ncol=2)
    fig.suptitle(
        f"beta = {result['density_veh_per_m']:g} veh/m, lambda = {settings['packets_per_s']:g} Hz, "
        f"Pt = {settings['tx_power_dbm']:g} dBm, S = {settings['n_subchannels']}, B = {settings['packet_bytes']} B"
    )
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    _write_atomic(path, buf.getvalue())


def _json_safe(value: Any) -> Any:
    """``value`` with NaN / inf floats (a distance bin without samples) as null, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def write_outputs(out_dir: Path, settings: dict[str, Any], results: list[dict[str, Any]]) -> list[Path]:
    """Write JSON, the two CSVs and one figure per density into ``out_dir``; return the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    keys = ["pdr"] + [k for _, k in CAUSES]
    doc = _json_safe({"reference": _REFERENCE, "settings": settings, "veins": VEINS_NOTE, "densities": results})
    paths = [out_dir / "validation.json", out_dir / "pdr_vs_distance.csv", out_dir / "table.csv"]
    _write_atomic(paths[0], (json.dumps(doc, indent=2, allow_nan=False) + "\n").encode())
    rows = []
    for r in results:
        for source in ("simulator", "analytical"):
            for row in r["curve"][source]:
                n, se = row.get("n", ""), row.get("se_pct", "")
                rows.append([r["density_veh_per_m"], source, row["distance_m"], *(row[k] for k in keys), n, se])
        veins = r.get("authors_veins")
        if veins is not None:
            for j, d in enumerate(veins["distance_m"]):
                v = veins["veins"]
                rows.append([r["density_veh_per_m"], "veins", d, *(v[k][j] for k in keys), "", ""])
    header = ["density_veh_per_m", "source", "distance_m", *keys, "n", "se_pct"]
    _write_atomic(paths[1], _csv_bytes(header, rows))
    rows = []
    for r in results:
        for t in r["table"]:
            for source in ("simulator", "analytical"):
                rows.append([r["density_veh_per_m"], t["distance_m"], source, *(t[source][k] for k in keys)])
    _write_atomic(paths[2], _csv_bytes(["density_veh_per_m", "distance_m", "source", *keys], rows))
    for r in results:
        p = out_dir / f"pdr_{r['density_veh_per_m']:g}.png"
        _figure(r, settings, p)
        paths.append(p)
    return paths


_REFERENCE = (
    "M. Gonzalez-Martin, M. Sepulcre, R. Molina-Masegosa, J. Gozalvez, 'Analytical Models of the Performance of "
    "C-V2X Mode 4 Vehicular Communications', IEEE Trans. Veh. Technol. 68(2), 2019, DOI 10.1109/TVT.2018.2888704"
)


def run_validation(
    out_dir: Path,
    densities: Sequence[float] = (0.1, 0.2, 0.3),
    packets_per_s: float = 10.0,
    tx_power_dbm: float = 20.0,
    n_subchannels: int = 4,
    n_subframes: int = 5000,
    seeds: Sequence[int] = (1, 2),
    sets: Sequence[str] = (),
    packet_bytes: int = 190,
    workers: int = 1,
) -> list[Path]:
    """Compare the simulator with the analytical model at each density and write the outputs
    (:func:`write_outputs`) into ``out_dir``; prints a short table per density. What
    ``cv2x-marl validate`` runs (in a run folder).

    Raises:
        ValueError: a setting the matched configuration cannot take (named in the message).
    """
    _check_run_size(n_subframes, workers)
    settings = {
        "packets_per_s": packets_per_s,
        "tx_power_dbm": tx_power_dbm,
        "n_subchannels": n_subchannels,
        "packet_bytes": packet_bytes,
        "subframes_per_seed": n_subframes,
        "seeds": list(seeds),
        "simulator_sets": list(sets),
        "sensing_threshold_dbm": SENSING_THRESHOLD_DBM,
        "bin_m": BIN_M,
        "table_window_m": "pooled over [d - 10, d + 10) for the simulator; exactly at d for the analytical model",
    }
    config = (int(n_subchannels), float(packets_per_s), float(tx_power_dbm))
    results = _compare_configurations([config], densities, packet_bytes, n_subframes, seeds, sets, workers)[0]
    paths = write_outputs(out_dir, settings, results)
    for p in paths:
        print(p)
    return paths


def _compare_configurations(
    configurations: Sequence[tuple[int, float, float]],
    densities: Sequence[float],
    packet_bytes: int,
    n_subframes: int,
    seeds: Sequence[int],
    sets: Sequence[str],
    workers: int,
) -> list[list[dict[str, Any]]]:
    """:func:`compare_density` of every (configuration, density), the simulator runs of all of them (one
    per seed) in one pool of ``workers`` processes; prints a short table of each."""
    tasks, index = [], []
    for c, (n_sub, lam, pt) in enumerate(configurations):
        for d, rho in enumerate(densities):
            ov = simulator_overrides(rho, lam, pt, n_sub, packet_bytes, n_subframes)  # refuses bad input first
            for seed in seeds:
                tasks.append((ov, int(seed), tuple(sets)))
                index.append((c, d))
    t0 = time.perf_counter()
    runs = simulate_many(tasks, workers)
    print(f"simulator: {len(tasks)} runs in {time.perf_counter() - t0:.1f} s with {workers} worker(s)")
    out: list[list[dict[str, Any]]] = []
    for c, (n_sub, lam, pt) in enumerate(configurations):
        rows = []
        for d, rho in enumerate(densities):
            per_seed = [r for r, key in zip(runs, index, strict=True) if key == (c, d)]
            counts = pool_counts(per_seed)
            r = compare_density(rho, lam, pt, n_sub, packet_bytes, n_subframes, seeds, sets, counts=counts)
            r["simulator_runtime_s"] = float(sum(float(x["runtime_s"]) for x in per_seed))
            rows.append(r)
            _print_density(r, n_sub, lam, pt)
        out.append(rows)
    return out


def _print_density(r: dict[str, Any], n_sub: int, lam: float, pt: float) -> None:
    se = r["se_pct_0_500m"]
    print(
        f"S={n_sub} {lam:g} Hz {pt:g} dBm, density {r['density_veh_per_m']:g} veh/m: {r['n_vehicles']} vehicles, "
        f"simulator {r['simulator_runtime_s']:.1f} s (CPU, all seeds)"
    )
    veins = r["authors_veins"]
    for t in r["table"]:
        sim, ana = t["simulator"], t["analytical"]
        line = f"  {t['distance_m']:5.0f} m  PDR simulator {sim['pdr']:.3f}  analytical {ana['pdr']:.3f}"
        if veins is not None and t["distance_m"] in veins["distance_m"]:
            line += f"  authors' Veins {veins['veins']['pdr'][veins['distance_m'].index(t['distance_m'])]:.3f}"
        print(line)
    print(
        f"  mean |PDR difference| over 0-500 m: {r['mad_pct_0_500m']['pdr']:.2f} points (standard error of the "
        f"curve over seeds: mean {se['mean']:.2f}, max {se['max']:.2f} points); loss shares off by at most "
        f"{r['loss_share_max_abs_diff']:.3f}"
    )
    if veins is not None:
        print(
            f"  against the authors' Veins: simulator {veins['mad_pct_simulator_vs_veins']:.2f} points, "
            f"analytical {veins['mad_pct_analytical_vs_veins']:.2f} points (25 m points, 0-500 m)"
        )


def run_grid(
    out_dir: Path,
    configurations: Sequence[tuple[int, float, float]] = STUDY_CONFIGURATIONS,
    densities: Sequence[float] = STUDY_DENSITIES,
    n_subframes: int = 5000,
    seeds: Sequence[int] = (1, 2),
    sets: Sequence[str] = (),
    packet_bytes: int = 190,
    workers: int = 1,
) -> list[Path]:
    """Every configuration x density (the study's: :data:`STUDY_CONFIGURATIONS` x :data:`STUDY_DENSITIES`)
    in one pool of ``workers`` processes (``cv2x-marl validate --study``). Writes one folder per
    configuration, ``s<S>_l<lambda>_p<dBm>/``, with :func:`write_outputs`' files, and ``grid.csv`` /
    ``grid.md``: per (configuration, density) the mean absolute PDR difference to the model and to the
    authors' Veins curve, the standard error of the simulator's curve, and the loss shares of all three.

    Raises:
        ValueError: a setting the matched configuration cannot take (named in the message).
    """
    _check_run_size(n_subframes, workers)
    for n_sub, lam, pt in configurations:  # refuse before anything runs or is written
        for rho in densities:
            simulator_overrides(rho, lam, pt, n_sub, packet_bytes, n_subframes)
    t0 = time.perf_counter()
    grid = _compare_configurations(configurations, densities, packet_bytes, n_subframes, seeds, sets, workers)
    paths: list[Path] = []
    summary = []
    for (n_sub, lam, pt), results in zip(configurations, grid, strict=True):
        settings = {
            "packets_per_s": lam,
            "tx_power_dbm": pt,
            "n_subchannels": n_sub,
            "packet_bytes": packet_bytes,
            "subframes_per_seed": n_subframes,
            "seeds": list(seeds),
            "simulator_sets": list(sets),
            "sensing_threshold_dbm": SENSING_THRESHOLD_DBM,
            "bin_m": BIN_M,
        }
        paths += write_outputs(out_dir / f"s{n_sub}_l{lam:g}_p{pt:g}", settings, results)
        summary += [((n_sub, lam, pt), r) for r in results]
    paths += _write_grid_summary(out_dir, summary, n_subframes, seeds, sets, time.perf_counter() - t0, workers)
    for p in paths[-2:]:
        print(p)
    return paths


def _write_grid_summary(
    out_dir: Path,
    summary: list[tuple[tuple[int, float, float], dict[str, Any]]],
    n_subframes: int,
    seeds: Sequence[int],
    sets: Sequence[str],
    wall_s: float,
    workers: int,
) -> list[Path]:
    """``grid.csv`` and ``grid.md`` of :func:`run_grid`."""
    cause_keys = [k for _, k in CAUSES]
    header = [
        "n_subchannels", "packets_per_s", "tx_power_dbm", "density_veh_per_m", "analytical_cbr",
        "mad_pdr_pct_vs_analytical", "se_pct_mean", "se_pct_max", "mad_pdr_pct_vs_veins",
        "mad_pdr_pct_analytical_vs_veins", "pdr200_sim", "pdr200_ana", "pdr200_veins", "pdr300_sim", "pdr300_ana",
        "pdr300_veins", "loss_share_max_abs_diff",
        *(f"share_{k}_{src}" for src in ("sim", "ana", "veins") for k in cause_keys),
    ]  # fmt: skip
    rows, md = [], []
    md.append(
        f"Simulator: {len(seeds)} seeds ({', '.join(map(str, seeds))}) x {n_subframes} subframes, "
        f"sets {list(sets) or 'none'}; {wall_s:.0f} s wall with {workers} worker(s).\n"
    )
    md.append(
        "| S | Hz | dBm | veh/m | CBR (ana) | MAD vs ana | SE mean / max | MAD vs Veins | MAD ana vs Veins "
        "| PDR 200 m sim / ana / Veins | PDR 300 m sim / ana / Veins | shares sim (HD SEN PRO COL) "
        "| shares ana | shares Veins | max share diff |"
    )
    md.append("|" + "---:|" * 15)
    for (n_sub, lam, pt), r in summary:
        veins = r["authors_veins"]
        tab = {t["distance_m"]: t for t in r["table"]}

        def vpdr(d: float, v: dict[str, Any] | None = veins) -> float:
            return v["veins"]["pdr"][v["distance_m"].index(d)] if v is not None else math.nan

        sh = r["loss_shares_0_500m"]
        vsh = veins["loss_shares_0_500m"] if veins is not None else dict.fromkeys(cause_keys, math.nan)
        row = [
            n_sub, lam, pt, r["density_veh_per_m"], r["analytical_cbr"], r["mad_pct_0_500m"]["pdr"],
            r["se_pct_0_500m"]["mean"], r["se_pct_0_500m"]["max"],
            veins["mad_pct_simulator_vs_veins"] if veins is not None else math.nan,
            veins["mad_pct_analytical_vs_veins"] if veins is not None else math.nan,
            tab[200.0]["simulator"]["pdr"], tab[200.0]["analytical"]["pdr"], vpdr(200.0),
            tab[300.0]["simulator"]["pdr"], tab[300.0]["analytical"]["pdr"], vpdr(300.0),
            r["loss_share_max_abs_diff"],
            *(sh["simulator"][k] for k in cause_keys), *(sh["analytical"][k] for k in cause_keys),
            *(vsh[k] for k in cause_keys),
        ]  # fmt: skip
        rows.append(row)

        def f3(xs: Sequence[float]) -> str:
            return " ".join(f"{x:.3f}" for x in xs)

        md.append(
            f"| {n_sub} | {lam:g} | {pt:g} | {r['density_veh_per_m']:g} | {r['analytical_cbr']:.3f} "
            f"| {row[5]:.2f} | {row[6]:.2f} / {row[7]:.2f} | {row[8]:.2f} | {row[9]:.2f} "
            f"| {f3(row[10:13])} | {f3(row[13:16])} | {f3([sh['simulator'][k] for k in cause_keys])} "
            f"| {f3([sh['analytical'][k] for k in cause_keys])} | {f3([vsh[k] for k in cause_keys])} "
            f"| {row[16]:.3f} |"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "grid.csv", out_dir / "grid.md"]
    _write_atomic(paths[0], _csv_bytes(header, rows))
    _write_atomic(paths[1], ("\n".join(md) + "\n").encode())
    return paths
