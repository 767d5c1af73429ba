"""``cv2x-marl dataset``: stage-1 dataset: K independent runs of link samples."""

from __future__ import annotations

import argparse
from pathlib import Path

from cv2x_marl.cli.common import (
    COUNT,
    OVERWRITE_HELP,
    READINGS,
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
    p.add_argument("--runs", type=COUNT, default=10, help="independent runs (seeds derived from --seed)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--subframes", type=COUNT, help="subframes per run (default: sim.n_subframes)")
    p.add_argument(
        "--aggregate-window-ms",
        type=SEED,
        default=0,
        help="aggregate per (run, link, window, NSV) into an empirical reception rate (0: per transmission)",
    )
    p.add_argument(
        "--reading",
        choices=list(READINGS),
        default="per-packet",
        help="per-packet: one sample per transmission and co-channel NSV (the settings as given); paper: the "
        "paper's Table 3 reading, NSV over every concurrent transmitter (metrics.nsv_scope=concurrent) and one "
        "instance per (run, link, NSV) over the whole run (docs/model.md)",
    )
    p.add_argument("--out", type=Path, required=True, help="dataset folder")
    p.add_argument("--ray", action="store_true", help="run the runs as Ray tasks (a local Ray; the [ray] extra)")
    p.add_argument("--address", help="with --ray: the Ray cluster to use (auto, ray://HOST:10001)")
    p.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    p.add_argument("--json", action="store_true", help="print the manifest as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from cv2x_marl.experiments.dataset import build_dataset

    cfg = scenario(args)
    if args.subframes is not None:
        cfg = apply_overrides(cfg, [f"sim.n_subframes={args.subframes}"])
    window_ms = args.aggregate_window_ms
    if args.reading == "paper":
        if window_ms:
            raise ConfigError("--reading paper aggregates over the whole run; drop --aggregate-window-ms")
        if cfg.metrics.nsv_scope != "concurrent" and any(
            s.split("=", 1)[0].strip() == "metrics.nsv_scope" for s in args.set or []
        ):
            raise ConfigError("--reading paper sets metrics.nsv_scope=concurrent; drop --set metrics.nsv_scope")
        cfg = apply_overrides(cfg, ["metrics.nsv_scope=concurrent"])
        from cv2x_marl.experiments.dataset import WHOLE_RUN

        window_ms = WHOLE_RUN  # one window per run, however long the warm-up (sim.warmup_mode)
    manifest = build_dataset(
        cfg,
        args.runs,
        args.seed,
        args.out,
        window_ms,
        progress=not args.quiet,
        overwrite=args.overwrite,
        ray=args.ray or args.address is not None,
        address=args.address,
    )
    if args.json:
        print_json({k: v for k, v in manifest.items() if k != "config"})
    else:
        print(f"{manifest['rows']} samples from {args.runs} runs in {manifest['runtime_s']:.2f} s")
        print("rows per NSV: " + ", ".join(f"{k}: {v}" for k, v in manifest["rows_per_nsv"].items()))
        print(f"wrote {args.out / 'samples.parquet'} and {args.out / 'manifest.json'}")
    return 0
