"""``cv2x-marl validate``: PDR(d) and loss causes of the highway simulator against the analytical Mode 4
model of Gonzalez-Martin et al. (IEEE TVT 2019; docs/validation.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl import runs
from cv2x_marl.cli.common import (
    COUNT,
    OVERWRITE_HELP,
    POSITIVE_FLOAT,
    SEED,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--out", type=Path, required=True, help="output folder: validation.json, CSVs, one figure per density"
    )
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--densities", type=POSITIVE_FLOAT, nargs="+", default=[0.1, 0.2, 0.3], help="veh/m")
    p.add_argument("--packets-per-s", type=POSITIVE_FLOAT, default=10.0, help="packets per second per vehicle")
    p.add_argument("--tx-power-dbm", type=float, default=20.0, help="transmit power (dBm)")
    p.add_argument("--subchannels", type=int, default=4, choices=(2, 4), help="sub-channels per subframe")
    p.add_argument("--subframes", type=COUNT, default=5000, help="measured subframes per seed")
    p.add_argument("--seeds", type=SEED, nargs="+", default=[1, 2], help="simulator seeds (pooled)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a simulator key (repeatable)")
    p.add_argument("--study", action="store_true", help="every configuration of the study (docs/validation.md)")
    p.add_argument("--workers", type=COUNT, default=1, help="simulator runs in this many processes")
    assume = "model: the simulator under the analytical model's stated assumptions, before --set (docs/validation.md)"
    p.add_argument("--assumptions", choices=("simulator", "model"), default="simulator", help=assume)


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.validation.compare import assumption_sets, run_grid, run_validation

    params = {k: v for k, v in vars(args).items() if k not in ("func", "out", "overwrite", "command")}
    sets = [*assumption_sets(args.assumptions), *(args.set or [])]  # --set last: it overrides
    run = dict(n_subframes=args.subframes, seeds=args.seeds, sets=sets, workers=args.workers)
    with runs.run_folder(args.out, "validate", overwrite=args.overwrite, parameters=params):
        if args.study:
            run_grid(args.out, densities=args.densities, **run)
        else:
            run_validation(args.out, args.densities, args.packets_per_s, args.tx_power_dbm, args.subchannels, **run)
    return 0
