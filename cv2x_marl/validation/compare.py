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
    "The authors' Veins results (msepulcre/C-V2X, folder simulations/, MATLAB .fig files) are binary "
    "and could not be read in this environment (no MATLAB/Octave, not in the text index); no Veins "
    "numbers are reported."
)


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


def run_simulator(
    overrides: dict[str, dict[str, Any]], seeds: Sequence[int], extra_sets: Sequence[str] = ()
) -> dict[str, np.ndarray]:
    """Run the simulator once per seed and pool the per-bin counts.

    Args:
        overrides: sections over the ``highway-legacy`` preset (:func:`simulator_overrides`).
        seeds: one run per seed.
        extra_sets: ``section.key=value`` strings applied last (``--set`` of the command line).

    Returns:
        ``n`` [B] link samples per 10 m bin, ``decoded`` [B], and one [B] count per loss cause
        (our names), plus ``n_vehicles`` (0-d).
    """
    cfg = apply_overrides(from_dict(overrides, preset("highway-legacy")), extra_sets)
    n_bins = round(MAX_DISTANCE_M / BIN_M)
    out = {k: np.zeros(n_bins, dtype=np.int64) for k in ("n", "decoded", *(c for c, _ in CAUSES))}
    for seed in seeds:
        sim = Simulator(cfg)
        sim.reset(seed=int(seed))
        acc = sim.run(cfg.sim.n_subframes).metrics
        out["n"] += acc.bin_n[:n_bins]
        out["decoded"] += acc.bin_decoded[:n_bins]
        for name, _ in CAUSES:
            out[name] += acc.bin_causes[CAUSE_CODE[name], :n_bins]
    out["n_vehicles"] = np.asarray(cfg.n_vehicles)
    return out


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
) -> dict[str, Any]:
    """Simulator and analytical model at one density: curves, table rows, loss shares and the mean
    absolute deviation of the paper's eq. 35 (over the 10 m bins, in percentage points)."""
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
    counts = run_simulator(overrides, seeds, extra_sets)
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
                n = row.get("n", "")
                rows.append([r["density_veh_per_m"], source, row["distance_m"], *(row[k] for k in keys), n])
    _write_atomic(paths[1], _csv_bytes(["density_veh_per_m", "source", "distance_m", *keys, "n"], rows))
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
) -> list[Path]:
    """Compare the simulator with the analytical model at each density and write the outputs
    (:func:`write_outputs`) into ``out_dir``; prints a short table per density. What
    ``cv2x-marl validate`` runs (in a run folder).

    Raises:
        ValueError: a setting the matched configuration cannot take (named in the message).
    """
    if n_subframes < 1:
        raise ValueError(f"n_subframes must be >= 1, got {n_subframes}")
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
    results = []
    for rho in densities:
        r = compare_density(
            rho, packets_per_s, tx_power_dbm, n_subchannels, packet_bytes, n_subframes, list(seeds), list(sets)
        )
        results.append(r)
        print(f"density {rho:g} veh/m: {r['n_vehicles']} vehicles, simulator {r['simulator_runtime_s']:.1f} s")
        for t in r["table"]:
            sim, ana = t["simulator"], t["analytical"]
            print(f"  {t['distance_m']:5.0f} m  PDR simulator {sim['pdr']:.3f}  analytical {ana['pdr']:.3f}")
        print(f"  mean |PDR difference| over 0-500 m: {r['mad_pct_0_500m']['pdr']:.2f} percentage points")
    paths = write_outputs(out_dir, settings, results)
    for p in paths:
        print(p)
    return paths
