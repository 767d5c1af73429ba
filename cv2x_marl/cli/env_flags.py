"""Command-line flags of env options, from the options schema (:class:`~cv2x_marl.env.options.EnvOptions`): the
flag's type checks the option's range and its help is the option's meaning, unit and allowed values, so a flag never
restates the schema by hand.

The schema's entries are held here as plain data (:data:`SPECS`, what :func:`cv2x_marl.env.options.flag_spec` gives):
importing the schema would load numpy and numba, and the CLI builds its parsers without them.
``tests/test_cli.py`` checks :data:`SPECS` equals the schema's (regenerate with
``python -m cv2x_marl.cli.env_flags``).
"""

from __future__ import annotations

import argparse
import pprint
from collections.abc import Callable
from typing import Any

from cv2x_marl.cli.common import number_type

#: the flags' options (the schema's :func:`~cv2x_marl.env.options.flag_spec` of each)
SPECS: dict[str, dict[str, Any]] = {
    "max_cycles": {
        "type": "int",
        "lo": 1,
        "lo_open": False,
        "hi": 10000,
        "choices": None,
        "default": 100,
        "unit": "steps",
        "doc": "steps per episode (`MAX_CYCLES` at most); all agents are truncated together, `agents == []` afterwards",
        "allowed": "integer in [1, 10000]",
    },
    "max_step_m": {
        "type": "float",
        "lo": 0.0,
        "lo_open": True,
        "hi": None,
        "choices": None,
        "default": 5.0,
        "unit": "m",
        "doc": "offset of a full action; actions are `Box(-1, 1, (2,), float32)`; at most the "
        "diagonal of the scene's road box (636.4 m for `paper`, 2000.1 m for `highway`: a "
        "longer step leaves the scene). With observation >= 1 in snapshot mode the plan "
        "searches the reachable square (`2 x max_cycles x max_step_m` wide unless "
        "`max_drift_m` or `roi` bound it) on a 20 m grid of at most 4,000,000 points "
        "(`env.planning.MAX_GRID_POINTS`; `max_step_m` up to 199.9 m with 100 steps); a "
        "larger one is refused at construction with the figure",
        "allowed": "finite number > 0",
    },
    "replan_every": {
        "type": "int",
        "lo": 1,
        "lo_open": False,
        "hi": None,
        "choices": None,
        "default": None,
        "unit": "steps",
        "doc": "observation version 2: recompute the sensing plan every `replan_every` steps from "
        "where every vehicle is then, over what is still reachable (null: once, at reset); "
        "the shipped multi-agent models use 50",
        "allowed": "null or integer >= 1",
    },
}


def option_type(name: str) -> Callable[[str], Any]:
    """An argparse ``type`` for env option ``name``: a number in its range, or text."""
    spec = SPECS[name]
    kind = {"int": int, "float": float}.get(spec["type"])
    if kind is None:
        return str
    if spec["lo"] is None:
        return kind
    return number_type(kind, spec["lo"], spec["lo_open"], spec["hi"], high_open=False)


def add_option_flag(p: argparse.ArgumentParser, name: str, flag: str | None = None, note: str = "") -> None:
    """Add ``flag`` (default ``--name-with-dashes``) for env option ``name``: its type, default and help from the
    schema, ``note`` appended (what the command does with it)."""
    spec = SPECS[name]
    unit = f" ({spec['unit']})" if spec["unit"] else ""
    text = f"the env's {name}{unit}: {spec['doc']}; allowed: {spec['allowed']}"
    text += f"; default {spec['default']}" if spec["default"] is not None else ""
    kwargs: dict[str, Any] = {"type": option_type(name), "default": spec["default"]}
    if spec["choices"]:
        kwargs["choices"] = spec["choices"]
    help_text = (text + (f"; {note}" if note else "")).replace("%", "%%")
    p.add_argument(flag or "--" + name.replace("_", "-"), help=help_text, **kwargs)


if __name__ == "__main__":
    from cv2x_marl.env.options import flag_spec

    print(pprint.pformat({n: flag_spec(n) for n in SPECS}, width=110, sort_dicts=False))
