"""``cv2x-marl train``: train PPO movers (SB3, parameter sharing), MAPPO (TorchRL, algo: mappo) or a learned
utility map (algo: utility-map) or a clone of the sensing planner (algo: imitation)."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.cli.common import (
    COUNT,
    DEFAULT_TIMESTEPS,
    ENV_CHOICES,
    OVERWRITE_HELP,
    SEED,
    print_json,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", default=None, choices=ENV_CHOICES)
    p.add_argument(
        "--algo",
        default=None,
        help="ppo | mappo | utility-map | imitation (default: the --config file's algo, else ppo)",
    )
    p.add_argument(
        "--timesteps",
        type=COUNT,
        default=None,
        help=f"total agent-steps (default: the --config file's timesteps, else {DEFAULT_TIMESTEPS:,})",
    )
    p.add_argument("--seed", type=SEED, default=None, help="training seed (default: the --config file's, else 0)")
    p.add_argument("--copies", type=COUNT, default=None, help="env copies (each mover of each copy is a sub-env)")
    p.add_argument("--config", type=Path, help="YAML/JSON: env_id, copies, env, ppo, checkpoint_every, eval_*")
    p.add_argument("--out", type=Path, required=True, help="run folder")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its newest checkpoint (to --timesteps)"
    )
    p.add_argument("--json", action="store_true")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.rl.mappo_config import config_algo
    from cv2x_marl.rl.train import load_train_config, run_settings, train

    algo = config_algo(args.config, args.algo)
    if algo == "mappo":  # docs/rl.md, "MAPPO"
        from cv2x_marl.rl.mappo import cli_train

        return cli_train(args, DEFAULT_TIMESTEPS, print_json)
    if algo == "utility-map":  # docs/rl.md, "The learned utility map"
        from cv2x_marl.rl.utility_map import cli_train as map_train

        return map_train(args, DEFAULT_TIMESTEPS, print_json)
    if algo == "imitation":  # docs/rl.md, "Imitation of sensing"
        from cv2x_marl.rl.imitation import cli_train as imitation_train

        return imitation_train(args, DEFAULT_TIMESTEPS, print_json)
    cfg = load_train_config(args.config, env_id=args.env, copies=args.copies)
    from_file = run_settings(args.config)  # a run folder's train_config.json names its seed and length
    timesteps = args.timesteps if args.timesteps is not None else from_file.get("timesteps", DEFAULT_TIMESTEPS)
    seed = args.seed if args.seed is not None else from_file.get("seed", 0)
    quiet, resume, overwrite = args.quiet, args.resume, args.overwrite
    record = train(cfg, timesteps, seed, args.out, resume=resume, progress=not quiet, overwrite=overwrite)
    if args.json:
        print_json(record)
    else:
        fe = record["final_eval"]
        print(
            f"trained {record['timesteps']} steps in {record['wall_s']:.1f} s ({record['steps_per_s']:.0f} steps/s); "
            f"eval: utility gain {fe['mean_utility_gain']:+.1%}, effectiveness {fe['effectiveness']:.1%}, "
            f"PRR gain {fe['mean_prr_gain']:+.1%}"
        )
        if record.get("backend") == "torchrl":
            print(f"wrote {args.out / 'model.pt'}, record.json, curve.csv, curve.png, eval.csv")
        else:
            print(f"wrote {args.out / 'model.zip'}, record.json, eval.csv, checkpoints/, tb/")
    return 0
