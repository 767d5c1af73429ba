"""How much a resource choice can gain in ``cv2x/Resource-v0`` on other scenarios: ``sps`` against the task's
ceiling (``optimum``) on training-list episodes of each scenario (docs/benchmark.md, "resource").

    python benchmarks/resource_scenarios.py [--episodes 8] [--cycles 100] [--out docs/benchmark/resource_scenarios]

Each scenario is the env's options (preset and overrides, applied after the id's own); the gain is the team's episode-mean utility per
target receiver against ``sps``'s on the same episode (the task's own measure), the PRR the team's episode mean.
Writes ``scenarios.csv`` (one row per scenario, method and episode) and prints the table.
"""

from __future__ import annotations

import argparse
import copy
import csv
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from cv2x_marl.env.registry import make_parallel_env
from cv2x_marl.env.tasks import TRAIN_SEEDS
from cv2x_marl.policies.resource import make_resource_policy

_HIGHWAY = ("sps.selection_window_subframes=20", "sps.reselection_timing=period_end")
#: name -> (the env's options, what it is)
SCENARIOS: dict[str, tuple[dict[str, Any], str]] = {
    "grid (the task)": ({}, "the paper's grid, 21 vehicles, the standard's SPS, T2 = 20 (2 sub-channels)"),
    "grid, paper SPS": (
        {  # after the id's own overrides: the paper preset's values back
            "overrides": (
                "sps.selection=paper",
                "sps.reservation_signalling=always",
                "sps.sci_decoding=always",
                "sps.sci_gates_pssch=false",
            )
        },
        "the paper preset's simplified SPS (k = 3 lowest S-RSSI, every SCI reserves), T2 = 20",
    ),
    "highway ring 210 m": (
        {"preset": "highway", "overrides": ("road.length_m=210", *_HIGHWAY)},
        "3 lanes each way, 0.1 vehicles/m: 21 vehicles, 5 sub-channels",
    ),
    "highway ring 210 m, 1 sub-channel": (
        {"preset": "highway", "overrides": ("road.length_m=210", "sps.n_subchannels=1", *_HIGHWAY)},
        "the same with one sub-channel (a fifth of the resources)",
    ),
    "highway 2 km, 21 vehicles": (
        {
            "preset": "highway",
            "overrides": ("vehicles.density_veh_per_m=null", "vehicles.n_vehicles=21", *_HIGHWAY),
        },
        "21 vehicles on the 2-km ring (0.0105 vehicles/m)",
    ),
}


def team_means(env: Any, name: str, seed: int) -> tuple[float, float]:
    """The team's episode-mean utility and PRR of policy ``name`` on episode ``seed`` (on a copy of the env)."""
    env.reset(seed=seed)
    run = copy.deepcopy(env)
    policy = make_resource_policy(name, run)
    policy.reset(seed)
    obs = run.observations()
    while run.agents:
        obs, *_ = run.step(policy.act(obs))
    return float(run.u_sum.mean() / run.t), float(run.prr_sum.mean() / run.t)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=8, help="training-list episodes per scenario (its first N)")
    p.add_argument("--cycles", type=int, default=100, help="steps per episode (max_cycles)")
    p.add_argument("--out", type=Path, default=None, help="a folder for scenarios.csv (default: print only)")
    args = p.parse_args(argv)
    seeds = TRAIN_SEEDS[: args.episodes]
    rows = []
    print("| scenario | vehicles | sps PRR | ceiling PRR | ceiling gain over sps, mean (%) | min .. max (%) |")
    print("|---|---|---|---|---|---|")
    for label, (options, _) in SCENARIOS.items():
        env = make_parallel_env("cv2x/Resource-v0", max_cycles=args.cycles, **options)
        t0 = time.perf_counter()
        res = {m: np.array([team_means(env, m, s) for s in seeds]) for m in ("sps", "optimum")}
        gain = (res["optimum"][:, 0] - res["sps"][:, 0]) / np.abs(res["sps"][:, 0])
        for m, arr in res.items():
            for s, (u, prr) in zip(seeds, arr, strict=True):
                rows.append({"scenario": label, "method": m, "seed": s, "utility_mean": u, "prr_mean": prr})
        print(
            f"| {label} | {env.n} | {res['sps'][:, 1].mean():.3f} | {res['optimum'][:, 1].mean():.3f} | "
            f"{100 * gain.mean():+.1f} | {100 * gain.min():+.1f} .. {100 * gain.max():+.1f} |",
            flush=True,
        )
        print(f"  ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        with (args.out / "scenarios.csv").open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
