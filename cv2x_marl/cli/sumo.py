"""``cv2x-marl sumo``: SUMO mobility scenarios (the 'sumo' extra; docs/mobility.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl import runs
from cv2x_marl.cli.common import (
    OVERWRITE_HELP,
    POSITIVE_FLOAT,
    SEED,
    add_scenario_args,
    print_json,
    scenario,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    sumo_sub = p.add_subparsers(dest="sumo_command", required=True)
    p = sumo_sub.add_parser(
        "export", help="write the generated SUMO scenario of a preset and seed (net, routes, .sumocfg, FCD trace)"
    )
    add_scenario_args(p)
    p.add_argument(
        "--seed",
        type=SEED,
        default=0,
        help="run seed (with a preset of vehicles.mobility=sumo, e.g. sumo-grid: the scenario `simulate --seed` runs)",
    )
    p.add_argument(
        "--seconds",
        type=POSITIVE_FLOAT,
        default=None,
        help="SUMO seconds of FCD trace (default: sim.warmup_subframes + sim.n_subframes, plus 60 s); at most "
        "what keeps the trace within 10,000,000 rows (vehicles x SUMO steps; 47,619 s for 21 vehicles at 0.1 s)",
    )
    p.add_argument("--parquet", action="store_true", help="also write the trace as fcd.parquet")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.sumo_export import export_scenario, export_seconds

    cfg = scenario(args)
    export_seconds(cfg, args.seconds)  # the trace's size, refused before the folder is touched
    params = {"seed": args.seed, "seconds": args.seconds, "parquet": args.parquet}
    with runs.run_folder(args.out, "sumo export", overwrite=args.overwrite, parameters=params):
        summary = export_scenario(cfg, args.seed, args.out, args.seconds, args.parquet)
    if args.json:
        print_json(summary)
    else:
        print(
            f"SUMO {summary['sumo_version']} scenario (seed {summary['seed']}, SUMO seed {summary['sumo_seed']}): "
            f"{summary['n_vehicles']} vehicles over {summary['n_timesteps']} steps of {summary['step_s']:g} s"
        )
        for name in summary["files"]:
            print(f"wrote {args.out / name}")
    return 0
