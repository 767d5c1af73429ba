"""``cv2x-marl benchmark``: every method of every task on its held-out episodes: table and figure."""

from __future__ import annotations

import argparse

from cv2x_marl.cli.common import COUNT, OVERWRITE_HELP
from cv2x_marl.experiments import benchmark


def add_arguments(p: argparse.ArgumentParser) -> None:
    benchmark.add_arguments(p, COUNT, OVERWRITE_HELP)


def run(args: argparse.Namespace) -> int:
    return benchmark.run_from_args(args)
