"""Command-line flags of env options, generated from the options schema (:class:`~cv2x_marl.env.options.EnvOptions`):
the flag's type checks the option's range and its help is the option's meaning, unit and allowed values, so a flag
never restates what the schema says."""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections.abc import Callable
from typing import Any

from cv2x_marl import schema
from cv2x_marl.cli.common import number_type
from cv2x_marl.env.options import EnvOptions, allowed_text

_FIELDS = {f.name: f for f in dataclasses.fields(EnvOptions)}


def option_type(name: str) -> Callable[[str], Any]:
    """An argparse ``type`` for env option ``name``: a number in its range, or one of its choices (as text)."""
    f = _FIELDS[name]
    tp, _ = schema.base_type(typing.get_type_hints(EnvOptions)[name])
    meta = f.metadata
    if tp in (int, float) and meta["lo"] is not None:
        return number_type(tp, meta["lo"], bool(meta["lo_open"]), meta["hi"], high_open=False)
    if tp in (int, float):
        return tp
    return str


def add_option_flag(p: argparse.ArgumentParser, name: str, flag: str | None = None, note: str = "") -> None:
    """Add ``flag`` (default ``--name-with-dashes``) for env option ``name``: its type, default and help from the
    schema, ``note`` appended (what the command does with it)."""
    f = _FIELDS[name]
    tp, optional = schema.base_type(typing.get_type_hints(EnvOptions)[name])
    meta = f.metadata
    unit = f" ({meta['unit']})" if meta["unit"] else ""
    text = f"the env's {name}{unit}: {meta['doc']}; allowed: {allowed_text(f, tp, optional)}"
    text += f"; default {f.default}" if f.default is not None else ""
    kwargs: dict[str, Any] = {"type": option_type(name), "default": f.default}
    if meta["choices"]:
        kwargs["choices"] = list(meta["choices"])
    p.add_argument(
        flag or "--" + name.replace("_", "-"), help=(text + (f"; {note}" if note else "")).replace("%", "%%"), **kwargs
    )
