"""The ``cv2x-marl`` command line: one module per command (``cv2x_marl/cli/<command>.py``, each with
``add_arguments(parser)`` and ``run(args) -> int``), listed in :data:`COMMANDS`; a command's module is imported when
the command runs (``cv2x-marl --help`` imports none), so the CLI starts without the libraries the commands use.
:func:`main` turns the package's errors into one line and an exit status (2: refused input, 1: file system,
130: interrupted); :func:`console` is the installed ``cv2x-marl`` script. Shared argument types and the scenario
options are :mod:`cv2x_marl.cli.common`'s.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

from cv2x_marl import interrupts, runs
from cv2x_marl.cli.common import COUNT, DEFAULT_TIMESTEPS, ENV_CHOICES, EVALUATE_EPISODES, MAX_SEED, SEED
from cv2x_marl.config import ConfigError
from cv2x_marl.extras import MissingExtraError

__all__ = [
    "COMMANDS",
    "COUNT",
    "DEFAULT_TIMESTEPS",
    "ENV_CHOICES",
    "EVALUATE_EPISODES",
    "MAX_SEED",
    "SEED",
    "build_parser",
    "console",
    "main",
]

#: every command -> its one-line help; its arguments and its work are in ``cv2x_marl.cli.<command>``
COMMANDS: dict[str, str] = {
    "simulate": "run the stage-1 network simulator",
    "dataset": "stage-1 dataset: K independent runs of link samples",
    "fit": "stage-2 fit of the two-distance model per NSV (eq. 15)",
    "gbmu": "GBMU mobility studies (Fig. 5-10) with greedy and oracle references",
    "evaluate": "evaluate a mover policy on the env (same episodes for the same seed)",
    "benchmark": "every method of every task on its held-out episodes: table and figure",
    "train": "train PPO movers (SB3), MAPPO (algo: mappo), a utility map (algo: utility-map) or a clone of "
    "sensing (algo: imitation)",
    "sweep": "PPO training sweep over seeds and a grid, as Ray Tune trials",
    "reproduce": "dataset, fit, GBMU study, movers vs baselines, REPORT.md",
    "baselines": "every baseline file of a folder on the same held-out episodes",
    "sumo": "SUMO mobility scenarios (the 'sumo' extra; docs/mobility.md)",
    "validate": (
        "PDR(d) and loss causes of the highway simulator against the analytical Mode 4 model of "
        "Gonzalez-Martin et al. (IEEE TVT 2019; docs/validation.md)"
    ),
    "config": "print the resolved configuration, or the key reference",
}


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The argument parser (also used by the docs): every command with its help; the arguments of ``only`` (a
    command name; ``""``: none, for ``--help``) or of every command (None), whose modules are then imported."""
    parser = argparse.ArgumentParser(prog="cv2x-marl", description="Controlled mobility in C-V2X Mode 4 networks")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, help_text in COMMANDS.items():
        p = sub.add_parser(name, help=help_text)
        if only is None or only == name:
            module = importlib.import_module(f"cv2x_marl.cli.{name}")
            module.add_arguments(p)
            if p.get_default("func") is None:  # a command with subcommands sets its own
                p.set_defaults(func=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cv2x-marl`` console script."""
    given = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(only=next((a for a in given if a in COMMANDS), ""))
    args = parser.parse_args(given)
    runs.INVOCATION = ["cv2x-marl", *(sys.argv[1:] if argv is None else argv)]
    runs.INPUTS = _inputs(args)
    previous = interrupts.install_safe_handlers()
    try:
        return int(args.func(args))
    except ConfigError as exc:
        print(f"cv2x-marl: configuration error: {exc}{_notes(exc)}", file=sys.stderr)
        return 2
    except (ValueError, MissingExtraError) as exc:  # ConfigError, DatasetError, FitError, ModelError, TrainError, ...
        print(f"cv2x-marl: error: {exc}{_notes(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a folder that vanished: the run folder was rolled back
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"cv2x-marl: file system error{where}: {exc.strerror or exc}{_notes(exc)}", file=sys.stderr)
        return 1
    except (KeyboardInterrupt, SystemError) as exc:
        # Ctrl-C or SIGTERM; inside a numba kernel the interrupt surfaces as a SystemError caused by it
        if not runs.is_interrupt(exc):
            raise
        detail = f": {exc}" if isinstance(exc, KeyboardInterrupt) and str(exc) else ""
        print(f"\ncv2x-marl: interrupted{detail}{_notes(exc)}", file=sys.stderr)
        return 130
    finally:
        runs.INVOCATION = None
        runs.INPUTS = []
        interrupts.restore_handlers(previous)


def _notes(exc: BaseException) -> str:
    """What happened to the output folder (the notes :class:`cv2x_marl.runs.RunFolder` attached), as ``; ...``."""
    return "".join(f"; {n}" for n in runs.notes(exc))


def _inputs(args: argparse.Namespace) -> list[Path]:
    """The files and folders a command reads (``--config``, ``--data``, ``--model``, ``--models``, the
    file of ``--policy``): its ``--out`` may not be, contain or lie inside one of them."""
    found: list[Path] = []
    for name in ("config", "data", "model", "models"):
        value = getattr(args, name, None)
        if isinstance(value, Path):
            found.append(value)
    policy = getattr(args, "policy", None)
    for spec in [policy] if isinstance(policy, str) else policy or []:
        if spec.startswith("ppo:"):
            found.append(Path(spec[4:]))
        elif spec.endswith((".yaml", ".yml", ".json")):
            found.append(Path(spec))
    return found


def console() -> None:
    """The ``cv2x-marl`` command: :func:`main`, then exit with its status; a signal that arrives after the command
    has ended (a second Ctrl-C) ends the process at once with that status (:func:`interrupts.exit_on_signal`)."""
    status = 1
    try:
        status = main()
    except KeyboardInterrupt:  # a signal while main put its handlers back
        status = 130
    finally:
        interrupts.exit_on_signal(status)
    sys.exit(status)
