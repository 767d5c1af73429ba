"""``cv2x-marl baselines``: every baseline file of a folder on the same held-out episodes."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.cli.common import (
    COUNT,
    ENV_CHOICES,
    SEED,
    print_json,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dir", type=Path, default=Path("baselines"), help="folder of baseline files (*.yaml)")
    p.add_argument("--episodes", type=COUNT, default=144)
    p.add_argument("--seed", type=SEED, default=2026)
    p.add_argument("--env", default=None, choices=ENV_CHOICES, help="default: each file's env_id")
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.baselines import run_baselines

    result = run_baselines(args.dir, args.episodes, args.seed, args.env, progress=not args.quiet)
    if args.json:
        print_json(result)
    else:
        for r in result["rows"]:
            share = "" if r["share_of_optimum"] is None else f", {r['share_of_optimum']:.0%} of the optimum"
            print(f"{r['baseline']:10s} {r['env']}: utility gain {r['mean_utility_gain']:+.1%}{share}")
        print(f"wrote {args.dir / 'results.json'} and {args.dir / 'results.md'}")
    return 0
