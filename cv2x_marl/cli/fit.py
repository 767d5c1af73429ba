"""``cv2x-marl fit``: stage-2 fit of the two-distance model per NSV (eq. 15)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.cli.common import (
    COUNT,
    FRACTION,
    OVERWRITE_HELP,
    SEED,
    print_json,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="dataset folder (from `cv2x-marl dataset`)")
    p.add_argument("--out", type=Path, required=True, help="fit folder: model.json, table2.md, table3.md, figures")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--model", default="linear", choices=["linear", "logistic"], help="model family")
    p.add_argument(
        "--target",
        default=None,
        choices=["p_success", "outcome", "rate"],
        help="what eq. 15 fits (default: rate for an aggregated dataset, e.g. --reading paper; else p_success)",
    )
    p.add_argument("--nsv-cap", type=COUNT, default=6, help="NSV values above are pooled into the cap")
    p.add_argument("--test-fraction", type=FRACTION, default=0.2, help="share of runs held out")
    p.add_argument("--min-samples", type=COUNT, default=30, help="below this an NSV borrows a neighbour's fit")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the held-out split")
    p.add_argument("--compare", action="store_true", help="also fit the other family and compare on held-out data")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--json", action="store_true", help="print per-NSV coefficients and statistics as JSON")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.dataset import run_fit

    result = run_fit(
        args.data,
        args.out,
        kind=args.model,
        target=args.target,
        nsv_cap=args.nsv_cap,
        test_fraction=args.test_fraction,
        seed=args.seed,
        min_samples=args.min_samples,
        compare=args.compare,
        figures=not args.no_figures,
        overwrite=args.overwrite,
    )
    if args.json:
        print_json(result)
    else:
        print(f"{'NSV':>4} {'alpha':>7} {'beta':>7} {'gamma':>7} {'R2':>6} {'R2test':>7} {'instances':>9}")
        for r in result["per_nsv"]:
            fb = f"  (from NSV {r['fallback_from']})" if r.get("fallback_from") is not None else ""
            print(
                f"{r['nsv']:>4} {r['alpha']:7.3f} {r['beta']:7.3f} {r['gamma']:7.3f} {r['r2']:6.3f} "
                f"{r['r2_test']:7.3f} {r['instances']:9d}{fb}"
            )
        for k, o in result.get("comparison", {}).items():
            print(f"held out, {k}: R2 {o['r2']:.3f}, Brier {o['brier']:.4f}, log-loss {o['log_loss']:.4f}")
        print(f"wrote {result['model']}, table2.md, table3.md and figures in {args.out}")
    return 0
