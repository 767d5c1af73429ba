"""The ``cv2x-marl`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from cv2x_marl.config import (
    PRESETS,
    ConfigError,
    ScenarioConfig,
    apply_overrides,
    config_markdown,
    load_config_file,
    preset,
    to_dict,
)


def _scenario(args: argparse.Namespace) -> ScenarioConfig:
    cfg = preset(args.preset)
    if args.config:
        cfg = load_config_file(args.config, cfg)
    return apply_overrides(cfg, args.set or [])


def _add_scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default="paper", choices=sorted(PRESETS), help="base configuration (default: paper)")
    p.add_argument("--config", type=Path, help="YAML/JSON file of configuration sections applied over the preset")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override one key, e.g. --set sps.n_subchannels=4 (repeatable)",
    )


def _cmd_simulate(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.simulate import simulate

    cfg = _scenario(args)
    n = args.subframes if args.subframes is not None else cfg.sim.n_subframes
    if n < 1:
        raise ConfigError(f"--subframes must be >= 1, got {n}")
    summary = simulate(cfg, args.seed, n, args.out, progress=not args.quiet)
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(
            f"PRR mean {summary['prr_mean']:.4f} (expected {summary['prr_mean_expected']:.4f}) over "
            f"{summary['n_vehicles']} vehicles, {summary['n_transmissions']} transmissions, "
            f"{summary['runtime_s']:.3f} s"
        )
        print("PRR at " + ", ".join(f"{d} m: {p:.3f}" for d, p in summary["prr_at_m"].items()))
        print("loss causes: " + ", ".join(f"{k} {v:.1%}" for k, v in summary["loss_cause_shares"].items()))
        if args.out:
            for name in ("links.parquet", "summary.json", "prr_vs_distance.png"):
                if (args.out / name).exists():
                    print(f"wrote {args.out / name}")
    return 0


def _cmd_config(args: argparse.Namespace) -> int:
    if args.markdown:
        sys.stdout.write(config_markdown())
    else:
        json.dump(to_dict(_scenario(args)), sys.stdout, indent=2)
        sys.stdout.write("\n")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (also used by the docs)."""
    parser = argparse.ArgumentParser(prog="cv2x-marl", description="Controlled mobility in C-V2X Mode 4 networks")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="run the stage-1 network simulator")
    _add_scenario_args(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--subframes", type=int, help="subframes to simulate (default: sim.n_subframes)")
    p.add_argument("--out", type=Path, help="output folder for links.parquet, summary.json, prr_vs_distance.png")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("config", help="print the resolved configuration, or the key reference")
    _add_scenario_args(p)
    p.add_argument("--markdown", action="store_true", help="print docs/config.md (every key, unit, default, range)")
    p.set_defaults(func=_cmd_config)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cv2x-marl`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except ConfigError as exc:
        print(f"cv2x-marl: configuration error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
