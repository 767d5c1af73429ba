"""`cv2x-marl gbmu`: the paper's mobility studies (Fig. 5-10) for GBMU, greedy and the oracle.

Every method starts from the same snapshot positions; the true utility and PRR after each move
come from the simulator's link model (:class:`cv2x_marl.sim.ground_truth.MoverLinks`), never from the
regression model that steers GBMU.

Beyond the paper (issue 15), named variants split GBMU's gap to the optimum into the model and the
algorithm (:data:`VARIANTS`, selected with ``--methods``):

* ``gbmu-logistic``: GBMU steered by the shipped logistic two-distance model (``logistic-fit``)
  instead of the ``--model`` one; ``planner-logistic``: the global search over that model;
* ``gbmu-schedule``: GBMU with the step-size schedule :data:`VARIANT_SCHEDULE` (Armijo
  backtracking on the steering model's predicted utility) instead of the constant step;
* ``gbmu-logistic-schedule``: both.
"""

from __future__ import annotations

import csv
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cv2x_marl.config import ConfigError, ScenarioConfig, apply_overrides, show_text, show_value, to_dict
from cv2x_marl.env.planning import ModelRow, ReachableSet, best_reachable
from cv2x_marl.io import atomic_write, write_json
from cv2x_marl.policies.gbmu import (
    ClimbResult,
    GbmuInputs,
    SteeringUtility,
    StepSchedule,
    climb,
    gbmu_direction,
    oracle_direction,
)
from cv2x_marl.regression.model import TwoDistanceModel, load_shipped_model
from cv2x_marl.rng import derive_seeds
from cv2x_marl.runs import run_folder
from cv2x_marl.sim import Simulator, Snapshot
from cv2x_marl.sim.ground_truth import MoverLinks
from cv2x_marl.sim.road import Road
from cv2x_marl.utility import jain_fairness, normalised_gain, per_node_prr, utility_log

CASES = ("seven-node", "snapshot", "realizations")
METHODS = ("gbmu", "greedy", "oracle", "planner", "optimum")
#: named variants beyond the paper (module docstring); not run unless asked for
VARIANTS = ("gbmu-logistic", "gbmu-schedule", "gbmu-logistic-schedule", "planner-logistic")
#: every method ``--methods`` accepts
ALL_METHODS = METHODS + VARIANTS
#: the shipped model that steers the ``-logistic`` variants
VARIANT_MODEL = "logistic-fit"
#: the step schedule of the ``-schedule`` variants (and of ``baselines/gbmu-schedule.yaml``)
VARIANT_SCHEDULE = StepSchedule("backtracking")

#: most memory the realisations of one study may hold (snapshots, links, trajectories), bytes
MAX_STUDY_BYTES = 2_000_000_000
#: memory per realisation: bytes per vehicle pair of its snapshot (shadowing, LOS, links: 9.3 measured on
#: highway), a fixed part (positions, resources: 4 kB measured on paper) and bytes per recorded
#: iteration of each method (trajectory and utility curve)
STUDY_PAIR_BYTES, STUDY_FIXED_BYTES, STUDY_RECORD_BYTES = 10, 4_096, 24


def record_interval(case: str, iterations: int) -> int:
    """Iterations between two recorded points of the climbs (about 100 per climb in the realizations case)."""
    return max(1, iterations // 1000) if case != "realizations" else max(1, iterations // 100)


def study_bytes(cfg: ScenarioConfig, realizations: int, iterations: int, n_methods: int) -> tuple[int, int]:
    """Estimated memory of a realizations study: ``(total, per realisation)`` bytes."""
    n = cfg.n_vehicles
    records = iterations // record_interval("realizations", iterations) + 2
    per = n * n * STUDY_PAIR_BYTES + STUDY_FIXED_BYTES + n_methods * records * STUDY_RECORD_BYTES
    return realizations * per, per


def scene_diagonal_m(cfg: ScenarioConfig) -> tuple[float, str]:
    """The diagonal of the scenario's road box (m) and the box in words."""
    box = np.asarray(Road.from_config(cfg.road).box_m, dtype=np.float64)
    box = np.where(np.isfinite(box), box, box[0])
    return float(np.hypot(*box)), f"{box[0]:g} m x {box[1]:g} m"


def check_study(
    case: str, cfg: ScenarioConfig, realizations: int, iterations: int, delta: float, n_methods: int
) -> None:
    """Refuse a step larger than the scene and realisations whose memory would exceed :data:`MAX_STUDY_BYTES`
    (a ValueError naming the option and the figure), before anything is run or written."""
    scene_m, box = scene_diagonal_m(cfg)
    if not np.isfinite(delta) or not 0 < delta <= scene_m:
        raise ValueError(
            f"--step must be > 0 and at most {scene_m:.1f} m (the diagonal of the scene, road box {box}: a longer "
            f"step leaves it), got {delta:g}"
        )
    if case != "realizations":
        return
    total, per = study_bytes(cfg, realizations, iterations, n_methods)
    if per > MAX_STUDY_BYTES:  # one realisation is too large: the vehicle count is the culprit
        rest = per - cfg.n_vehicles**2 * STUDY_PAIR_BYTES
        most = math.isqrt(max(0, MAX_STUDY_BYTES - rest) // STUDY_PAIR_BYTES)
        raise ValueError(
            f"vehicles.n_vehicles {cfg.n_vehicles:,}: one realisation would hold about {per / 1e9:,.1f} GB "
            f"({cfg.n_vehicles} x {cfg.n_vehicles} vehicle pairs), above the limit of {MAX_STUDY_BYTES / 1e9:g} GB "
            f"for the whole study; lower vehicles.n_vehicles to at most {most:,}"
        )
    if total > MAX_STUDY_BYTES:
        raise ValueError(
            f"--realizations {realizations:,} would hold about {total / 1e9:,.1f} GB ({per / 1e3:,.1f} kB per "
            f"realisation: {cfg.n_vehicles} x {cfg.n_vehicles} vehicle pairs and {n_methods} method(s)' "
            f"trajectories), above the limit of {MAX_STUDY_BYTES / 1e9:g} GB; lower --realizations to at most "
            f"{MAX_STUDY_BYTES // per:,} for this scenario"
        )


# The illustrative network of Fig. 3: transmitter UE0, receivers UE1-UE3 in three directions with
# d03 > d01 > d02, interferers I4-I6 on UE0's resource with l2 > l1 > l3 (metres).
SEVEN_NODE_POSITIONS_M = np.array(
    [
        [0.0, 0.0],  # UE0, the mover
        [60.0, 40.0],  # UE1: d01 = 72.1 m
        [-40.0, 20.0],  # UE2: d02 = 44.7 m
        [10.0, -110.0],  # UE3: d03 = 110.5 m
        [140.0, 80.0],  # I4, main interferer of UE1: l1 = 89.4 m
        [-190.0, 20.0],  # I5, main interferer of UE2: l2 = 150.0 m
        [60.0, -130.0],  # I6, main interferer of UE3: l3 = 53.9 m
    ]
)


def seven_node_snapshot(n_subchannels: int = 2) -> Snapshot:
    """Fig. 3 as a snapshot: UE0 and I4-I6 share slot 1 / subchannel 0, UE1-UE3 receive in slots 2-4.

    Open area: every link LOS, no shadowing, so the case is deterministic.
    """
    n = SEVEN_NODE_POSITIONS_M.shape[0]
    slot = np.array([1, 2, 3, 4, 1, 1, 1])
    return Snapshot(
        subframe=0,
        positions_m=SEVEN_NODE_POSITIONS_M.copy(),
        velocities_mps=np.zeros((n, 2)),
        slot=slot,
        subchannel=np.zeros(n, dtype=np.int64),
        generation_slot=np.zeros(n, dtype=np.int64),
        counter=np.ones(n, dtype=np.int64),
        los=np.ones((n, n), dtype=bool),
        shadowing_db=np.zeros((n, n)),
        rri_ms=100,
        n_subchannels=n_subchannels,
    )


def gbmu_inputs(snapshots: Sequence[Snapshot], movers: Sequence[int], links: MoverLinks, th_i_m: float) -> GbmuInputs:
    """One-hop knowledge of each mover: receiver positions, their main-interferer distance and NSV
    (counted as ``metrics.nsv_scope`` says: the mover's co-channel or all its concurrent transmitters)."""
    b, n = links.target.shape
    l_m = np.full((b, n), th_i_m)
    nsv = np.zeros((b, n), dtype=np.int64)
    concurrent = links.config.metrics.nsv_scope == "concurrent"
    for k, (snap, i) in enumerate(zip(snapshots, movers, strict=True)):
        res = snap.slot if concurrent else snap.slot * snap.n_subchannels + snap.subchannel
        co = np.flatnonzero((res == res[i]) & (np.arange(n) != i))
        if co.size:
            dist = np.hypot(*(snap.positions_m[:, None, :] - snap.positions_m[co][None, :, :]).transpose(2, 0, 1))
            dist[co, np.arange(co.size)] = np.inf  # a co-channel vehicle is not its own interferer
            near = dist <= th_i_m
            nsv[k] = near.sum(axis=1)
            l_m[k] = np.where(near.any(axis=1), np.where(near, dist, np.inf).min(axis=1), th_i_m)
    return GbmuInputs(links.rx_pos_m, np.maximum(l_m, 1e-3), nsv, links.target)


@dataclass
class MethodRun:
    """One method's climb and its ground truth."""

    climb: ClimbResult
    u0: NDArray[np.float64]
    u_final: NDArray[np.float64]
    prr0: NDArray[np.float64]
    prr_final: NDArray[np.float64]
    jain0: NDArray[np.float64]
    jain_final: NDArray[np.float64]
    utility_curve: NDArray[np.float64]  # [T, B] true utility at the recorded iterations

    @property
    def utility_gain(self) -> NDArray[np.float64]:
        return normalised_gain(self.u_final, self.u0)

    @property
    def prr_gain(self) -> NDArray[np.float64]:
        return normalised_gain(self.prr_final, self.prr0)


JUDGES = ("simulator", "model")


class Judge:
    """Who scores the positions: P of each mover link at positions [B, 2] (``success``), which links
    count (``target``) and one mover's utility at many positions (``row``, for the optimum).

    ``simulator`` (default): the link model on each snapshot (:class:`MoverLinks`: path loss,
    shadowing, the snapshot's interference; what the env rewards). ``model``: the steering
    regression model, ``P_hat(d_j(x), l_j, NSV_j)`` with the receivers, their main-interferer
    distance and NSV as observed at the start: one reading of the paper's "the new position is used
    to calculate the path loss and so on the P_ij(k)" (issue 15). Under ``model`` GBMU follows the
    judge's own gradient, and ``oracle`` and ``optimum`` use the judge too.
    """

    def __init__(self, kind: str, links: MoverLinks, inputs: GbmuInputs, model: TwoDistanceModel) -> None:
        if kind not in JUDGES:
            raise ValueError(f"unknown judge {kind!r}; judges: {', '.join(JUDGES)}")
        self.kind, self.links, self.inputs, self.model = kind, links, inputs, model
        self.target = links.target if kind == "simulator" else inputs.mask

    def success(self, pos_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """[B, N] P of each mover link with the movers at ``pos_m`` [B, 2] (0 where not a target)."""
        if self.kind == "simulator":
            return self.links.success(pos_m)
        rx = self.inputs.rx_m
        d = np.maximum(np.hypot(rx[..., 0] - pos_m[:, None, 0], rx[..., 1] - pos_m[:, None, 1]), 1.0)
        return np.where(self.target, self.model.predict(d, self.inputs.l_m, self.inputs.nsv), 0.0)

    def row(self, b: int) -> Any:
        """Mover ``b``'s utility at many positions, for :func:`~cv2x_marl.policies.optimum.best_reachable`."""
        if self.kind == "simulator":
            return _SnapshotRow(self.links, b)
        i = self.inputs
        return ModelRow(i.rx_m[b], i.l_m[b], i.nsv[b], i.mask[b], self.model)


def run_methods(
    links: MoverLinks,
    inputs: GbmuInputs,
    model: TwoDistanceModel,
    delta: float,
    th_pos_m: float,
    iterations: int,
    record_every: int,
    methods: Sequence[str] = METHODS,
    progress: bool = False,
    oracle_h_m: float = 5.0,
    judge: str = "simulator",
) -> dict[str, MethodRun]:
    """Run each method from the snapshot positions and score it with the judge along the way
    (:class:`Judge`: the simulator's link model, or the steering model)."""
    from tqdm import tqdm

    p_min = model.p_min
    jd = Judge(judge, links, inputs, model)
    variant_model: TwoDistanceModel | None = None
    if any("logistic" in name for name in methods):
        variant_model = load_shipped_model(VARIANT_MODEL)
    out: dict[str, MethodRun] = {}
    for name in methods:
        steering = variant_model if variant_model is not None and "logistic" in name else model
        if name == "optimum":
            res = optimum_climb(links, p_min, delta * iterations, iterations, progress, judge=jd)
        elif name.startswith("planner"):  # GBMU's knowledge and model, a global search instead of gradient steps
            steer = Judge("model", links, inputs, steering)
            res = optimum_climb(links, p_min, delta * iterations, iterations, progress, judge=steer)
        else:
            schedule, utility = None, None
            if name == "oracle":
                direction = oracle_direction(jd.success, jd.target, p_min, oracle_h_m)
            else:
                direction = gbmu_direction(inputs, steering, fairness=name != "greedy")
                if name.endswith("-schedule"):
                    schedule, utility = VARIANT_SCHEDULE, SteeringUtility(inputs, steering)
            with tqdm(total=iterations, desc=name, unit="it", file=sys.stderr, disable=not progress) as bar:
                res = climb(
                    links.start_m,
                    direction,
                    delta,
                    th_pos_m,
                    iterations,
                    record_every,
                    progress=bar.update,
                    schedule=schedule,
                    utility=utility,
                )
        p0 = jd.success(links.start_m)
        pf = jd.success(res.final_m)
        curve = np.array([utility_log(jd.success(pos), jd.target, p_min) for pos in res.trajectory_m])
        out[name] = MethodRun(
            res,
            utility_log(p0, jd.target, p_min),
            utility_log(pf, jd.target, p_min),
            per_node_prr(p0, jd.target),
            per_node_prr(pf, jd.target),
            jain_fairness(p0, jd.target),
            jain_fairness(pf, jd.target),
            curve,
        )
    return out


class _SnapshotRow:
    """The mover of snapshot ``b`` as a :class:`~cv2x_marl.sim.ground_truth.MoverRow`-like object for
    :func:`~cv2x_marl.policies.optimum.best_reachable`: the study's own truth utility of M positions."""

    def __init__(self, links: MoverLinks, b: int) -> None:
        self.links, self.b = links, b

    def utility(self, positions_m: NDArray[np.float64], p_min: float) -> NDArray[np.float64]:
        view = self.links.take(np.full(positions_m.shape[0], self.b, dtype=np.int64))
        return utility_log(view.success(positions_m), view.target, p_min)


class _Shifted:
    """A utility row in a frame moved by ``origin_m`` (the search's box starts at 0)."""

    def __init__(self, row: Any, origin_m: NDArray[np.float64]) -> None:
        self.row, self.origin_m = row, origin_m

    def utility(self, positions_m: NDArray[np.float64], p_min: float) -> NDArray[np.float64]:
        return np.asarray(self.row.utility(positions_m + self.origin_m, p_min))


def optimum_climb(
    links: MoverLinks,
    p_min: float,
    reach_m: float,
    iterations: int,
    progress: bool = False,
    grid_m: float = 5.0,
    refine: int = 8,
    judge: Judge | None = None,
) -> ClimbResult:
    """The ``optimum`` method: each mover's best position under the study's truth utility.

    ``judge`` (:class:`Judge`) scores positions; None: the simulator's link model. The search
    (:func:`~cv2x_marl.policies.optimum.best_reachable`: a ``grid_m`` grid, the
    ``refine`` best points refined twice to a hundredth of the pitch) covers what the climbing
    methods can reach: the disc of radius ``reach_m`` (iteration cap x step) around the start,
    within the bounding box of the target receivers (and the start). With the LOS states of the
    mover's links fixed (``truth_los`` snapshot or always), and for the regression judge (P falls
    with d), nothing outside that box can be better: projecting a position onto it shortens every
    link to a receiver. Returned as a :class:`ClimbResult` that jumps to the optimum at
    iteration 1 and stays there, so its curve is the level the climbers are measured against.
    """
    from tqdm import tqdm

    start = links.start_m
    target = links.target if judge is None else judge.target
    final = start.copy()
    for b in tqdm(range(start.shape[0]), desc="optimum", unit="snap", file=sys.stderr, disable=not progress):
        pts = np.concatenate([links.rx_pos_m[b][target[b]], start[b][None]])
        lo, hi = pts.min(axis=0), pts.max(axis=0)  # the receivers' box: the search works in its frame
        reach = ReachableSet(start[b] - lo, reach_m, reach_m, hi - lo)
        row = _Shifted(_SnapshotRow(links, b) if judge is None else judge.row(b), lo)
        found, _ = best_reachable(row, reach, p_min, grid_m=grid_m, refine=refine)
        final[b] = found + lo
    n = start.shape[0]
    return ClimbResult(
        final,
        np.ones(n, dtype=np.int64),
        np.ones(n, dtype=bool),
        np.stack([start, final, final]),
        np.array([0, 1, max(iterations, 1)]),
    )


def summarize(runs: dict[str, MethodRun]) -> dict[str, Any]:
    """Effectiveness, mean gains and PRR drops per method (GBMU's also at the top level)."""
    methods: dict[str, dict[str, Any]] = {}
    for name, r in runs.items():
        ug, pg = r.utility_gain, r.prr_gain
        moved = np.hypot(*(r.climb.final_m - r.climb.trajectory_m[0]).T)
        methods[name] = {
            "effectiveness": float(np.mean(ug > 1e-9)),
            "mean_utility_gain": float(np.nanmean(ug)),
            "median_utility_gain": float(np.nanmedian(ug)),
            "mean_prr_gain": float(np.nanmean(pg)),
            "mean_prr_before": float(np.nanmean(r.prr0)),
            "mean_prr_after": float(np.nanmean(r.prr_final)),
            "n_prr_drop": int(np.sum(pg < -1e-9)),
            "n_utility_drop": int(np.sum(ug < -1e-9)),
            "mean_jain_before": float(np.nanmean(r.jain0)),
            "mean_jain_after": float(np.nanmean(r.jain_final)),
            "mean_moved_m": float(np.mean(moved)),
            "mean_iterations": float(np.mean(r.climb.iterations)),
            "share_converged": float(np.mean(r.climb.converged)),
            "n_realizations": int(ug.shape[0]),
        }
    if "optimum" in runs:  # every method against the best reachable position, on the same snapshots
        best = methods["optimum"]["mean_utility_gain"]
        u_opt = runs["optimum"].u_final
        for name, r in runs.items():
            m = methods[name]
            m["share_of_optimum"] = m["mean_utility_gain"] / best if best else None
            m["n_beats_optimum"] = int(np.sum(r.u_final > u_opt + 1e-9 * np.abs(u_opt)))
    top: dict[str, Any] = dict(methods.get("gbmu", next(iter(methods.values()))))
    top["methods"] = methods
    return top


def _snapshots(cfg: ScenarioConfig, seeds: Sequence[int], progress: bool) -> list[Snapshot]:
    from tqdm import tqdm

    snaps = []
    for s in tqdm(seeds, desc="snapshots", unit="snap", file=sys.stderr, disable=not progress):
        snaps.append(Simulator(cfg).reset(s))
    return snaps


def _write_csv(path: Path, runs: dict[str, MethodRun], seeds: Sequence[int]) -> None:
    header = [
        "realization",
        "seed",
        "method",
        "utility_before",
        "utility_after",
        "utility_gain",
        "prr_before",
        "prr_after",
        "prr_gain",
        "jain_before",
        "jain_after",
        "iterations",
        "converged",
        "moved_m",
        "x0_m",
        "y0_m",
        "x_m",
        "y_m",
    ]

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            for name, r in runs.items():
                start = r.climb.trajectory_m[0]
                for b in range(r.u0.shape[0]):
                    w.writerow(
                        [
                            b,
                            seeds[b],
                            name,
                            r.u0[b],
                            r.u_final[b],
                            r.utility_gain[b],
                            r.prr0[b],
                            r.prr_final[b],
                            r.prr_gain[b],
                            r.jain0[b],
                            r.jain_final[b],
                            int(r.climb.iterations[b]),
                            bool(r.climb.converged[b]),
                            float(np.hypot(*(r.climb.final_m[b] - start[b]))),
                            start[b, 0],
                            start[b, 1],
                            r.climb.final_m[b, 0],
                            r.climb.final_m[b, 1],
                        ]
                    )

    atomic_write(path, write)


def check_methods(methods: Sequence[str], given: str | None = None) -> None:
    """Refuse an empty or unknown method list, naming ``--methods`` (``given``: the text as typed).

    Raises:
        ConfigError: no method, or a name not in :data:`ALL_METHODS` (listed in the message).
    """
    unknown = [m for m in methods if m not in ALL_METHODS]
    if methods and not unknown:
        return
    got = f"unknown method(s) {', '.join(show_text(m) for m in unknown)}" if unknown else "no method"
    typed = show_value(given if given is not None else ",".join(methods))
    raise ConfigError(
        f"--methods {typed} names {got}; give one or more of, separated by commas: " + ", ".join(ALL_METHODS)
    )


def run_study(
    case: str,
    cfg: ScenarioConfig,
    model: TwoDistanceModel,
    out_dir: Path | None,
    seed: int = 0,
    realizations: int = 144,
    iterations: int = 10_000,
    delta: float = 1.0,
    th_pos_m: float = 1e-4,
    truth_los: str = "snapshot",
    methods: Sequence[str] = METHODS,
    progress: bool = True,
    overwrite: bool = False,
    judge: str = "simulator",
) -> dict[str, Any]:
    """Run one of the paper's cases and write CSV, figures and ``summary.json`` into ``out_dir``.

    ``judge`` scores utility and PRR: ``simulator`` (the link model) or ``model`` (the steering
    regression model, :class:`Judge`). ``delta`` is at most the diagonal of the scenario's road box and
    the realisations' estimated memory at most :data:`MAX_STUDY_BYTES` (:func:`check_study`); both are
    checked before ``out_dir`` is touched."""
    if case not in CASES:
        raise ValueError(f"unknown case {case!r}; cases: {', '.join(CASES)}")
    if judge not in JUDGES:
        raise ValueError(f"unknown judge {judge!r}; judges: {', '.join(JUDGES)}")
    check_methods(methods)
    check_study(case, cfg, realizations, iterations, delta, len(methods))
    params = {"case": case, "seed": seed, "realizations": realizations, "iterations": iterations, "judge": judge}
    with run_folder(out_dir, "gbmu", overwrite=overwrite, parameters=params):
        t0 = time.perf_counter()
        if case == "seven-node":
            cfg = apply_overrides(cfg, ["channel.los=always"])
            snaps = [seven_node_snapshot(cfg.sps.n_subchannels)]
            movers = [0]
            seeds = [seed]
            truth_los = "always"
        elif case == "snapshot":
            seeds = [seed]
            snaps = _snapshots(cfg, seeds, progress)
            pos = snaps[0].positions_m
            movers = [int(np.argmax(np.hypot(*(pos - pos.mean(axis=0)).T)))]  # the most off-centre vehicle
        else:
            seeds = derive_seeds(seed, realizations)
            snaps = _snapshots(cfg, seeds, progress)
            movers = [0] * len(snaps)
        links = MoverLinks.from_snapshots(cfg, snaps, movers, truth_los=truth_los)
        inputs = gbmu_inputs(snaps, movers, links, cfg.metrics.interferer_range_m)
        runs = run_methods(
            links,
            inputs,
            model,
            delta,
            th_pos_m,
            iterations,
            record_interval(case, iterations),
            methods,
            progress,
            judge=judge,
        )
        summary = summarize(runs)
        summary.update(
            {
                "case": case,
                "seed": seed,
                "iterations": iterations,
                "step": delta,
                "th_pos_m": th_pos_m,
                "truth_los": truth_los,
                "judge": judge,
                "movers": movers,
                "model": {"kind": model.kind, "provenance": model.provenance},
                "runtime_s": time.perf_counter() - t0,
                "config": to_dict(cfg),
            }
        )
        if out_dir is not None:
            out_dir = Path(out_dir)
            _write_csv(out_dir / "realizations.csv", runs, seeds)
            write_json(out_dir / "summary.json", summary)
            from cv2x_marl import plotting

            if case == "realizations":
                plotting.plot_realization_gains(runs, out_dir / "fig9_fig10_gains.png", judge)
            else:
                target = links.target[0] if judge == "simulator" else inputs.mask[0]
                plotting.plot_trajectories(snaps[0], movers[0], target, runs, out_dir / "trajectory.png", case, judge)
                plotting.plot_gain_curves(runs, out_dir / "gain_vs_iteration.png", case, judge)
        return summary
