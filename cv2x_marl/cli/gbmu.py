"""``cv2x-marl gbmu``: GBMU mobility studies (Fig. 5-10) with greedy and oracle references."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.cli.common import (
    COUNT,
    OVERWRITE_HELP,
    POSITIVE_FLOAT,
    SEED,
    add_scenario_args,
    print_json,
    scenario,
)
from cv2x_marl.config import (
    TRUTH_LOS,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scenario_args(p)
    p.add_argument("--case", default="realizations", choices=["seven-node", "snapshot", "realizations"])
    p.add_argument("--realizations", type=COUNT, default=144, help="snapshots in the realizations case")
    p.add_argument("--iterations", type=COUNT, default=10_000, help="iteration cap")
    p.add_argument("--step", type=POSITIVE_FLOAT, default=1.0, help="step size delta")
    p.add_argument("--th-pos", type=POSITIVE_FLOAT, default=1e-4, help="stop when a move is shorter than this (m)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument(
        "--model",
        type=Path,
        default=Path("paper-table2"),
        help="fit folder or model.json (from `cv2x-marl fit`), paper-table2 (default), or a shipped model: "
        "linear-fit, logistic-fit",
    )
    p.add_argument(
        "--methods",
        default="gbmu,greedy,oracle,planner,optimum",
        help="comma-separated: gbmu, greedy, oracle, planner (the steering model's best reachable position), "
        "optimum (the best reachable position under the judge); variants beyond the paper: gbmu-logistic, "
        "planner-logistic (the shipped logistic-fit model), gbmu-schedule (Armijo backtracking step), "
        "gbmu-logistic-schedule",
    )
    p.add_argument(
        "--truth-los",
        default="snapshot",
        choices=TRUTH_LOS,
        help="LOS state of the mover's links in the ground truth",
    )
    p.add_argument(
        "--judge",
        default="simulator",
        choices=["simulator", "model"],
        help="who scores utility and PRR: the link model (default) or the steering regression model",
    )
    p.add_argument("--out", type=Path, help="output folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.gbmu_study import check_methods, run_study
    from cv2x_marl.regression.model import load_model, resolve_model

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    check_methods(methods, args.methods)  # before the model is read
    cfg = scenario(args)
    model = load_model(resolve_model(str(args.model)))
    summary = run_study(
        args.case,
        cfg,
        model,
        args.out,
        seed=args.seed,
        realizations=args.realizations,
        iterations=args.iterations,
        delta=args.step,
        th_pos_m=args.th_pos,
        truth_los=args.truth_los,
        methods=methods,
        progress=not args.quiet,
        overwrite=args.overwrite,
        judge=args.judge,
    )
    if args.json:
        print_json({k: v for k, v in summary.items() if k != "config"})
    else:
        print(f"case {args.case}, {summary['n_realizations']} realisation(s), model {model.kind}, judge {args.judge}")
        for name, m in summary["methods"].items():
            share = m.get("share_of_optimum")
            share_txt = "" if share is None else f", {share:.1%} of the optimum's gain"
            print(
                f"{name:>7}: effectiveness {m['effectiveness']:.1%}, utility gain {m['mean_utility_gain']:+.1%}, "
                f"PRR gain {m['mean_prr_gain']:+.1%}, PRR drops {m['n_prr_drop']}, moved {m['mean_moved_m']:.1f} m"
                + share_txt
            )
        if args.out:
            print(f"wrote {args.out}/summary.json, realizations.csv and figures")
    return 0
