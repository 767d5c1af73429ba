"""``cv2x-marl sweep``: PPO training sweep over seeds and a grid, as Ray Tune trials."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.cli.common import (
    COUNT,
    ENV_CHOICES,
    OVERWRITE_HELP,
    SEED,
    print_json,
)
from cv2x_marl.rl.errors import TrainError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", type=Path, help="training config (as for train) the grid modifies")
    p.add_argument("--env", default=None, choices=ENV_CHOICES, help="env id (default: the config's)")
    p.add_argument("--seeds", default="0", help="training seeds, comma-separated (default: 0)")
    p.add_argument(
        "--grid",
        action="append",
        metavar="KEY=V1,V2",
        help="a training-config key and its values, e.g. ppo.learning_rate=1e-4,3e-4 or env.replan_every=25,50 "
        "(repeatable: the trials are seeds x every combination)",
    )
    p.add_argument("--timesteps", type=COUNT, default=50_000, help="agent-steps per trial")
    p.add_argument("--eval-episodes", type=COUNT, default=48, help="held-out episodes per trial")
    p.add_argument("--eval-seed", type=SEED, default=2026, help="seed of the held-out episodes")
    p.add_argument("--vs-optimum", action="store_true", help="also report each trial's share of the optimum")
    p.add_argument("--address", help="Ray cluster address (auto, ray://HOST:10001); default: a local Ray")
    p.add_argument("--out", type=Path, required=True, help="sweep folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help='print {"trials": [...], "points": [...]} as JSON')
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.rl.sweep import parse_grid, run_sweep
    from cv2x_marl.rl.train import load_train_config

    cfg = load_train_config(args.config, env_id=args.env)
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        raise TrainError(f"--seeds expects integers separated by commas, got {args.seeds!r}") from None
    if any(s < 0 for s in seeds):
        raise TrainError(f"--seeds must be integers >= 0, got {args.seeds!r}")
    result = run_sweep(
        cfg,
        seeds,
        parse_grid(args.grid or []),
        args.timesteps,
        args.out,
        address=args.address,
        eval_episodes=args.eval_episodes,
        eval_seed=args.eval_seed,
        vs_optimum=args.vs_optimum,
        overwrite=args.overwrite,
        progress=not args.quiet,
    )
    if args.json:
        print_json(result)
    else:
        for p in result["points"]:
            sd = "" if p["std_utility_gain"] is None else f" +- {p['std_utility_gain']:.1%}"
            gain = "failed" if p["mean_utility_gain"] is None else f"{p['mean_utility_gain']:+.1%}{sd}"
            print(f"{p['label']}: held-out utility gain {gain} over {p['trials']} seed(s)")
        print(f"wrote {args.out / 'trials.csv'}, results.json, sweep.png and trials/ ({result['wall_s']:.0f} s)")
    return 0
