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

Every file is written to a temporary name in ``--out`` and renamed into place. The matched setting, the
authors' figures and the simulator's runs are :mod:`cv2x_marl.validation.matched`'s (re-exported here).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.validation.matched import (  # noqa: F401 - re-exported: compare's names before the split
    ASSUMPTIONS,
    BIN_M,
    CAUSES,
    MAX_DISTANCE_M,
    MODEL_ASSUMPTION_SETS,
    PER_CURVE_OF_FORMAT,
    SENSING_THRESHOLD_DBM,
    STUDY_CONFIGURATIONS,
    STUDY_DENSITIES,
    TABLE_DISTANCES_M,
    VEINS_NOTE,
    assumption_sets,
    authors_figures,
    pool_counts,
    run_simulator,
    simulate_many,
    simulate_seed,
    simulator_overrides,
)
from cv2x_marl.validation.mode4_analytical import analytical_pdr


def _check_run_size(n_subframes: int, workers: int) -> None:
    """Refuse a run of fewer than one subframe or one worker, before anything runs or is written."""
    if n_subframes < 1:
        raise ValueError(f"n_subframes must be >= 1, got {n_subframes}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")


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
