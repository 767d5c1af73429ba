"""``cv2x-marl config``: print the resolved configuration, or the key reference."""

from __future__ import annotations

import argparse
import sys

from cv2x_marl.cli.common import (
    add_scenario_args,
    print_json,
    scenario,
)
from cv2x_marl.config import (
    config_markdown,
    to_dict,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scenario_args(p)
    p.add_argument("--markdown", action="store_true", help="print docs/config.md (every key, unit, default, range)")


def run(args: argparse.Namespace) -> int:
    if args.markdown:
        sys.stdout.write(config_markdown())
    else:
        print_json(to_dict(scenario(args)))
    return 0
