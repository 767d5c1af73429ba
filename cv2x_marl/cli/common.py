"""What the ``cv2x-marl`` commands share: argument types with named ranges, the scenario options, constants."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cv2x_marl.config import (
    PRESET_ALIASES,
    PRESETS,
    ScenarioConfig,
    apply_overrides,
    load_config_file,
    preset,
    show_value,
)
from cv2x_marl.env.registry import ENV_IDS
from cv2x_marl.io import dumps_json

#: agent-steps of `cv2x-marl train` when neither --timesteps nor the config file says
DEFAULT_TIMESTEPS = 200_000
#: dataset readings: ``per-packet`` (the settings as given) or ``paper`` (the paper's Table 3 instances)
READINGS = ("per-packet", "paper")
#: the env ids `evaluate`, `train`, `sweep` and `baselines` accept, newest first (the registry imports
#: no env code, so `--help` stays fast)
ENV_CHOICES = ENV_IDS[::-1]
#: the `--preset` choices
PRESET_CHOICES = sorted([*PRESETS, *PRESET_ALIASES])


def number_type(
    kind: type, low: float, low_open: bool, high: float | None = None, high_open: bool = True
) -> Callable[[str], Any]:
    """An argparse ``type`` that accepts finite ``kind`` values in the range and names the rule otherwise
    (the text shown cut to 60 characters; integers of any length are compared exactly)."""

    def fmt(x: float) -> str:
        return str(int(x)) if kind is int else f"{x:g}"

    lo = f"{'>' if low_open else '>='} {fmt(low)}"
    rule = f"{'an integer' if kind is int else 'a finite number'} {lo}"
    if high is not None:
        rule += f" and {'<' if high_open else '<='} {fmt(high)}"

    def parse(text: str) -> float | int:
        refusal = f"must be {rule}, got {show_value(text)}"
        try:
            value = kind(text)
        except ValueError:
            try:  # an integer written in scientific notation (--timesteps 1e5)
                as_float = float(text)
            except ValueError:
                raise argparse.ArgumentTypeError(refusal) from None
            if kind is not int or not as_float.is_integer():  # inf and NaN are not integers
                raise argparse.ArgumentTypeError(refusal) from None
            value = int(as_float)
        ok = (kind is int or math.isfinite(value)) and (value > low if low_open else value >= low)
        if high is not None:
            ok = ok and (value < high if high_open else value <= high)
        if not ok:
            raise argparse.ArgumentTypeError(refusal)
        return value

    return parse


OVERWRITE_HELP = (
    "replace a previous run in --out (kept until this run completes); without it a non-empty --out is refused"
)

POSITIVE_FLOAT = number_type(float, 0.0, True)
FRACTION = number_type(float, 0.0, True, 1.0, True)
COUNT = number_type(int, 1, False)
#: ``evaluate``'s episodes without ``--episodes`` or ``--seeds``
EVALUATE_EPISODES = 144
#: the largest seed: seeds are 32-bit (numpy's legacy seeding, which stable-baselines3 calls, takes < 2**32)
MAX_SEED = 2**32 - 1
SEED = number_type(int, 0, False, MAX_SEED, False)


def print_json(data: object) -> None:
    sys.stdout.write(dumps_json(data) + "\n")


def scenario(args: argparse.Namespace) -> ScenarioConfig:
    """``--preset`` (default paper), then the ``--config`` file (whose ``preset:`` line, if any, must
    name the same preset as a given ``--preset``), then the ``--set`` overrides."""
    cfg = preset(args.preset or "paper")
    if args.config:
        cfg = load_config_file(args.config, cfg, given_preset=args.preset)
    return apply_overrides(cfg, args.set or [])


def add_scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--preset",
        default=None,
        choices=PRESET_CHOICES,
        help="base configuration (default: paper, or the --config file's preset: line; naming two "
        "different presets is refused)",
    )
    p.add_argument("--config", type=Path, help="YAML/JSON file of configuration sections applied over the preset")
    p.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override one key, e.g. --set sps.n_subchannels=4 (repeatable)",
    )
