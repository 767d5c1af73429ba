"""The analytical Mode 4 model's setting matched in the simulator, and the simulator's runs on it.

The constants of the comparison (table distances, loss causes, the PER table of each of the paper's formats,
``P_SEN``, the 10 m bins, the study's configurations and densities, ``validate --assumptions``), the authors'
figure curves (package data), :func:`simulator_overrides` (the highway configured as closely as the
configuration allows to the analytical model's setting) and the seeds' runs with their per-bin counts
(:func:`simulate_seed`, :func:`simulate_many`, :func:`pool_counts`, :func:`run_simulator`).
:mod:`cv2x_marl.validation.compare` compares them with the model and writes the outputs; it re-exports these
names.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence
from importlib import resources
from typing import Any

import numpy as np

from cv2x_marl.config import apply_overrides, from_dict, preset
from cv2x_marl.parallel import map_in_processes
from cv2x_marl.sim.metrics import CAUSE_CODE
from cv2x_marl.sim.simulator import Simulator
from cv2x_marl.validation.mode4_analytical import PAPER_FORMATS

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


def simulate_many(
    tasks: Sequence[tuple[dict[str, dict[str, Any]], int, tuple[str, ...]]], workers: int = 1
) -> list[dict[str, np.ndarray]]:
    """:func:`simulate_seed` of every ``(overrides, seed, extra_sets)`` task, in task order; with
    ``workers > 1`` in that many spawned processes (:func:`cv2x_marl.parallel.map_in_processes`, the
    largest scenes first; each run is independent and seeded, so the results are the same as in one
    process)."""
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
