"""``cv2x-marl evaluate``: evaluate a mover policy on the env (same episodes for the same seed)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from cv2x_marl.cli.common import (
    COUNT,
    ENV_CHOICES,
    EVALUATE_EPISODES,
    OVERWRITE_HELP,
    POSITIVE_FLOAT,
    PRESET_CHOICES,
    SEED,
    print_json,
)
from cv2x_marl.cli.env_flags import add_option_flag
from cv2x_marl.env.registry import DEFAULT_ENV_ID


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--env",
        default=None,
        choices=ENV_CHOICES,
        help=f"default: the env a ppo:PATH model or a baseline file names, else {DEFAULT_ENV_ID}",
    )
    p.add_argument(
        "--policy",
        action="append",
        help="static | random | gbmu | greedy | oracle | planner | sensing | optimum | best-response | "
        "sequential-best-response | sequential-sensing | sequential-team | ppo:PATH | baselines/NAME.yaml (default "
        "gbmu); repeated, or a ppo:PATTERN glob: the training runs of one method, pooled",
    )
    p.add_argument(
        "--seeds",
        help="episode seeds: integers separated by commas, or heldout | train (the --env task's lists, "
        "docs/benchmark.md); adds IQM and 95%% bootstrap CIs (default: --episodes from --seed)",
    )
    p.add_argument("--env-option", action="append", metavar="KEY=VALUE", help="env argument, YAML value (repeatable)")
    p.add_argument("--vs-optimum", action="store_true", help="also the optimum on every episode: share_of_optimum")
    p.add_argument(
        "--episodes",
        type=COUNT,
        default=None,
        help=f"episodes (default {EVALUATE_EPISODES}); with --seeds, the first N of them; x movers at most "
        "1,000,000 (rows kept in memory)",
    )
    p.add_argument(
        "--seed", type=SEED, default=None, help="episode k resets with the k-th seed derived from it (default 0)"
    )
    p.add_argument(
        "--preset", default=None, choices=PRESET_CHOICES, help="scenario preset (default: the env id's, paper)"
    )
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="scenario override (repeatable)")
    add_option_flag(p, "max_cycles")
    add_option_flag(p, "max_step_m", "--max-step")
    add_option_flag(p, "replan_every", note="default: a ppo:PATH model's setting, else once")
    p.add_argument(
        "--model",
        type=Path,
        default=Path("paper-table2"),
        help="two-distance model for gbmu/greedy/planner: a fit folder, a model.json, paper-table2 or a shipped "
        "model (linear-fit, logistic-fit)",
    )
    p.add_argument("--delta", type=POSITIVE_FLOAT, default=100.0, help="GBMU/greedy/oracle step size per env step")
    p.add_argument("--out", type=Path, help="output folder (episodes.csv, summary.json)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments import evaluate as ev
    from cv2x_marl.regression.model import resolve_model

    env_kwargs: dict[str, Any] = {"max_cycles": args.max_cycles}
    if args.preset is not None:  # else the id's own (paper)
        env_kwargs["preset"] = args.preset
    if args.set:  # after the id's own overrides, where it has some (cv2x/Resource-v0)
        env_kwargs["overrides"] = args.set
    env_kwargs["max_step_m"] = args.max_step
    if args.replan_every is not None:
        env_kwargs["replan_every"] = args.replan_every
    env_kwargs.update(ev.parse_env_options(args.env_option or [], ev.EVALUATE_FLAGS))
    policies = ev.expand_policies(args.policy or ["gbmu"])
    seeds = ev.cli_seeds(args.seeds, args.episodes, args.seed, args.env, policies)
    summary = ev.evaluate(
        args.env,
        policies if len(policies) > 1 else policies[0],
        EVALUATE_EPISODES if args.episodes is None else args.episodes,
        0 if args.seed is None else args.seed,
        args.out,
        env_kwargs,
        model_path=resolve_model(str(args.model)),
        delta=args.delta,
        progress=not args.quiet,
        vs_optimum=args.vs_optimum,
        overwrite=args.overwrite,
        seeds=seeds,
    )
    if args.json:
        print_json(summary)
    else:
        print(ev.format_summary(summary, ", ".join(args.policy or ["gbmu"])))
    return 0
