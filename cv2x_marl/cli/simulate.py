"""``cv2x-marl simulate``: run the stage-1 network simulator."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cv2x_marl.cli.common import (
    COUNT,
    OVERWRITE_HELP,
    SEED,
    add_scenario_args,
    print_json,
    scenario,
)
from cv2x_marl.config import (
    ConfigError,
    apply_overrides,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scenario_args(p)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--subframes", type=COUNT, help="subframes to simulate (default: sim.n_subframes)")
    p.add_argument("--out", type=Path, help="output folder for links.parquet, summary.json, prr_vs_distance.png")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument(
        "--links",
        choices=("auto", "on", "off"),
        default="auto",
        help="links.parquet: auto (default) writes it up to 2,000,000 expected rows (about 60 MB) and "
        "skips it above with a note; on: always (as metrics.record_links says); off: never",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.simulate import simulate

    cfg = scenario(args)
    n = args.subframes if args.subframes is not None else cfg.sim.n_subframes
    if n < 1:
        raise ConfigError(f"--subframes must be >= 1, got {n}")
    if n != cfg.sim.n_subframes:  # the memory check (and run.json's config) see the run's real length
        cfg = apply_overrides(cfg, [f"sim.n_subframes={n}"])
    summary = simulate(cfg, args.seed, n, args.out, progress=not args.quiet, overwrite=args.overwrite, links=args.links)
    if "links_table" in summary:
        note = summary["links_table"]
        print(f"links.parquet not written: {note['expected_rows']:,} rows expected; {note['why']}", file=sys.stderr)
    if args.json:
        print_json(summary)
    else:
        pop = summary.get("population")
        vehicles = (
            f"{summary['n_vehicles']} vehicles"
            if pop is None
            else f"{pop['n_vehicles_seen']} vehicles ({pop['present_mean']:.1f} present on average)"
        )
        print(
            f"PRR mean {summary['prr_mean']:.4f} (expected {summary['prr_mean_expected']:.4f}) over "
            f"{vehicles}, {summary['n_transmissions']} transmissions, {summary['runtime_s']:.3f} s"
        )
        print("PRR at " + ", ".join(f"{d} m: {p:.3f}" for d, p in summary["prr_at_m"].items()))
        print("loss causes: " + ", ".join(f"{k} {v:.1%}" for k, v in summary["loss_cause_shares"].items()))
        if args.out:
            for name in ("links.parquet", "slots.parquet", "summary.json", "prr_vs_distance.png"):
                if (args.out / name).exists():
                    print(f"wrote {args.out / name}")
    return 0
