"""Declared, validated option schemas: the machinery behind config.py's sections and the env's options.

A schema is a frozen dataclass (:class:`Section`) whose fields carry their documentation, unit and allowed
range or values in their metadata (:func:`key_field`). That metadata drives validation on construction
(:meth:`Section.__post_init__`: a bad value raises :class:`ConfigError` naming ``section.key`` and the
allowed values), the refusal of unknown keys by their users, and the generated reference tables
(:func:`markdown_rows`), so the three never disagree. :mod:`cv2x_marl.config` (the scenario) and
:mod:`cv2x_marl.env.options` (the env's options) are built on it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


class ConfigError(ValueError):
    """A configuration key is unknown, has the wrong type, or is out of range."""


#: characters of a value an error message shows before it cuts the value short
SHOWN_CHARS = 60


def show_text(text: str) -> str:
    """``text`` unquoted for an error message: its first :data:`SHOWN_CHARS` characters and its length
    when it is longer (``abc... (100,000 characters)``)."""
    return text if len(text) <= SHOWN_CHARS else f"{text[:SHOWN_CHARS]}... ({len(text):,} characters)"


def show_value(value: Any) -> str:
    """``value`` for an error message, never longer than about :data:`SHOWN_CHARS` characters.

    A long string shows its first characters and its length (``'xxxx...' ... (100000 characters)``),
    a huge integer its number of digits, a list or mapping its first items: a large or deeply shared
    value (a YAML alias bomb) is never formatted in full.
    """
    import reprlib
    import sys

    if isinstance(value, str):
        if len(value) <= SHOWN_CHARS:
            return repr(value)
        return f"{value[:SHOWN_CHARS]!r}... ({len(value):,} characters)"
    if isinstance(value, bytes | bytearray):
        return show_value(value.decode("utf-8", "replace"))
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 3 * SHOWN_CHARS:
        limit = sys.get_int_max_str_digits()
        if limit and value.bit_length() > 3.33 * limit:
            return f"an integer of more than {limit:,} digits"
        return f"an integer of {len(str(abs(value))):,} digits"
    short = reprlib.Repr()
    short.maxlevel, short.maxstring, short.maxother, short.maxlong = 3, SHOWN_CHARS, SHOWN_CHARS, SHOWN_CHARS
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = 6
    try:
        text = short.repr(value)
    except ValueError:  # an integer inside it too long to convert to text
        return f"a {type(value).__name__}"
    return text if len(text) <= SHOWN_CHARS + 20 else f"{text[:SHOWN_CHARS]}... (cut short)"


def key_field(
    default: Any,
    doc: str,
    unit: str = "",
    lo: float | None = None,
    hi: float | None = None,
    choices: tuple[str, ...] | None = None,
    lo_open: bool = False,
    allowed: str | None = None,
) -> Any:
    """A dataclass field carrying its documentation and its allowed range (``allowed``: the
    allowed values in words, for free-text keys such as file paths)."""
    meta = {"doc": doc, "unit": unit, "lo": lo, "hi": hi, "choices": choices, "lo_open": lo_open, "allowed": allowed}
    return field(default=default, metadata=meta)


def allowed_text(meta: Mapping[str, Any]) -> str:
    if meta.get("allowed"):
        return str(meta["allowed"])
    if meta["choices"]:
        return " | ".join(meta["choices"])
    lo, hi = meta["lo"], meta["hi"]
    left = "(" if meta["lo_open"] else "["
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    return f"{left}{lo_s}, {hi_s}]"


def base_type(tp: Any) -> tuple[type, bool]:
    """(scalar type, optional) for a field annotation such as ``float | None``."""
    if isinstance(tp, types.UnionType) or typing.get_origin(tp) is typing.Union:
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0], True
    return tp, False


@dataclass(frozen=True)
class Section:
    """Base class: validates every field against its metadata after construction."""

    _name = ""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            key = f"{self._name}.{f.name}"
            tp, optional = base_type(hints[f.name])
            if value is None:
                if not optional:
                    raise ConfigError(f"{key}: a value is required (allowed: {allowed_text(f.metadata)})")
                continue
            value = coerce(key, value, tp, f.metadata)
            object.__setattr__(self, f.name, value)
        self._check()

    def _check(self) -> None:
        """Cross-key checks of the section (overridden where needed)."""


def coerce(key: str, value: Any, tp: type, meta: Mapping[str, Any]) -> Any:
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {show_value(value)}")
        return value
    if tp is int:
        if isinstance(value, float) and math.isfinite(value) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer in {allowed_text(meta)}, got {show_value(value)}")
        # a Python int of any size compares exactly with the float bounds below (no OverflowError)
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: expected a number in {allowed_text(meta)}, got {show_value(value)}")
        try:
            value = float(value)
        except OverflowError:  # an integer beyond the float range (above about 1.8e308)
            raise ConfigError(
                f"{key}: {show_value(value)} is out of range; allowed range: {allowed_text(meta)}"
            ) from None
        if not math.isfinite(value):
            raise ConfigError(f"{key}: expected a finite number in {allowed_text(meta)}, got {show_value(value)}")
    elif tp is str:
        if not isinstance(value, str):
            what = allowed_text(meta) if meta.get("allowed") else f"one of {allowed_text(meta)}"
            raise ConfigError(f"{key}: expected {what}, got {show_value(value)}")
        if meta["choices"] and value not in meta["choices"]:
            raise ConfigError(f"{key}: {show_value(value)} is not allowed; allowed values: {allowed_text(meta)}")
        return value
    lo, hi = meta["lo"], meta["hi"]
    if lo is not None and (value < lo or (meta["lo_open"] and value == lo)):
        raise ConfigError(f"{key}: {show_value(value)} is out of range; allowed range: {allowed_text(meta)}")
    if hi is not None and value > hi:
        raise ConfigError(f"{key}: {show_value(value)} is out of range; allowed range: {allowed_text(meta)}")
    return value


def markdown_rows(name: str, cls: type[Section]) -> list[str]:
    """The reference table of schema ``cls`` (keys shown as ``name.key``; ``name`` empty: bare keys), in Markdown."""
    hints = typing.get_type_hints(cls)
    lines = ["| key | type | unit | default | allowed | meaning |", "|---|---|---|---|---|---|"]
    for f in dataclasses.fields(cls):
        tp, optional = base_type(hints[f.name])
        tname = tp.__name__ + (" or null" if optional else "")
        unit = f.metadata["unit"] or "-"
        default = json.dumps(f.default)
        allowed = allowed_text(f.metadata) if tp is not bool else "true | false"
        cells = [c.replace("|", "\\|") for c in (allowed, f.metadata["doc"])]  # a | inside a cell splits it
        shown = f"{name}.{f.name}" if name else f.name
        lines.append(f"| `{shown}` | {tname} | {unit} | `{default}` | {cells[0]} | {cells[1]} |")
    return lines
