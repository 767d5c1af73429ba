"""``cv2x-marl reproduce``: dataset, fit, GBMU study, movers vs baselines, REPORT.md."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.cli.common import (
    OVERWRITE_HELP,
    SEED,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("results"))
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--quick", action="store_true", help="smaller settings: about four minutes on 2 cores")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument(
        "--models",
        type=Path,
        default=Path("agents/models"),
        help="folder of the PPO models, single_seed<N>/model.zip and multi_seed<N>/model.zip (checked before "
        "anything runs); none: no PPO rows",
    )
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.reproduce import NO_MODELS, reproduce

    report = reproduce(
        args.out,
        quick=args.quick,
        seed=args.seed,
        models_dir=None if str(args.models) == NO_MODELS else args.models,
        progress=not args.quiet,
        overwrite=args.overwrite,
    )
    print(f"wrote {args.out / 'REPORT.md'} and report.json ({report['runtime_s']:.0f} s)")
    return 0
