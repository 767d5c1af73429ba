"""One value parser for every YAML the package reads: the YAML 1.2 core schema.

PyYAML resolves plain scalars with YAML 1.1 rules, which surprise users of configuration
files: ``3e-4`` and ``5.9e9`` stay strings, ``010`` is 8 (octal), ``1:40`` is 100
(sexagesimal), ``2_3`` is 23, ``yes``/``on`` are booleans and ``2001-12-14`` is a date.
:class:`CoreLoader` resolves plain scalars with the YAML 1.2 core schema instead
(https://yaml.org/spec/1.2.2/#1032-tag-resolution), as YAML 1.2 parsers do:

=========  ==========================================================================
null       ``null``, ``Null``, ``NULL``, ``~``, empty
bool       ``true``/``True``/``TRUE``, ``false``/``False``/``FALSE`` (not yes/no/on/off)
int        ``[-+]?[0-9]+`` in base 10 (``010`` is 10), ``0o17`` octal, ``0x1F`` hex
float      ``[-+]?(.[0-9]+|[0-9]+(.[0-9]*)?)([eE][-+]?[0-9]+)?`` (``1e3``, ``3e-4``, ``5.9e9``),
           ``.inf``, ``-.inf``, ``.nan``
string     everything else (``1:40``, ``2_3``, ``yes``, ``2001-12-14``)
=========  ==========================================================================

A mapping that repeats a key is an error (PyYAML silently keeps the last one). Used by
``--set``, ``--config`` files, training configurations and baseline files.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import yaml

__all__ = ["CoreLoader", "YAMLError", "load", "load_mapping", "load_path", "parse_scalar"]

YAMLError = yaml.YAMLError

_NULL = re.compile(r"^(?:null|Null|NULL|~|)$")
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")
_INT = re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$")
_FLOAT = re.compile(
    r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
    r"|[-+]?(?:\.inf|\.Inf|\.INF)|\.nan|\.NaN|\.NAN)$"
)
_YAML11_TAGS = {
    "tag:yaml.org,2002:bool",
    "tag:yaml.org,2002:int",
    "tag:yaml.org,2002:float",
    "tag:yaml.org,2002:null",
    "tag:yaml.org,2002:timestamp",
}


class CoreLoader(yaml.SafeLoader):
    """A safe PyYAML loader with YAML 1.2 core-schema scalars and no duplicate keys."""

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        text = str(self.construct_scalar(node))
        if text.startswith("0o"):
            return int(text[2:], 8)
        if text.startswith("0x"):
            return int(text[2:], 16)
        return int(text, 10)

    def construct_yaml_float(self, node: yaml.ScalarNode) -> float:
        text = str(self.construct_scalar(node)).lower()
        if text.endswith(".inf"):
            return float("-inf") if text.startswith("-") else float("inf")
        if text == ".nan":
            return float("nan")
        return float(text)

    def construct_yaml_bool(self, node: yaml.ScalarNode) -> bool:
        return str(self.construct_scalar(node)).lower() == "true"

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                hash(key)
            except TypeError:
                continue  # let PyYAML report the unhashable key
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping",
                    node.start_mark,
                    f"found duplicate key {key!r}",
                    key_node.start_mark,
                )
            seen[key] = True
        return super().construct_mapping(node, deep=deep)


# Drop PyYAML's YAML 1.1 resolvers, then register the core schema's.
CoreLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag not in _YAML11_TAGS]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
CoreLoader.add_implicit_resolver("tag:yaml.org,2002:null", _NULL, ["n", "N", "~", ""])
CoreLoader.add_implicit_resolver("tag:yaml.org,2002:bool", _BOOL, list("tTfF"))
CoreLoader.add_implicit_resolver("tag:yaml.org,2002:int", _INT, list("-+0123456789"))
CoreLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list("-+0123456789."))
CoreLoader.add_constructor("tag:yaml.org,2002:int", CoreLoader.construct_yaml_int)
CoreLoader.add_constructor("tag:yaml.org,2002:float", CoreLoader.construct_yaml_float)
CoreLoader.add_constructor("tag:yaml.org,2002:bool", CoreLoader.construct_yaml_bool)


def load(text: str) -> Any:
    """Parse a YAML document with the YAML 1.2 core schema (:class:`CoreLoader`).

    Raises:
        yaml.YAMLError: malformed YAML or a repeated mapping key.
    """
    return yaml.load(text, Loader=CoreLoader)


def parse_scalar(text: str) -> Any:
    """The value of ``KEY=VALUE`` text (``--set``): ``3e-4`` -> 0.0003, ``010`` -> 10, ``[1, 2]`` -> list."""
    return load(text) if text.strip() else None


def load_path(path: str | Path) -> Any:
    """Read a configuration file: JSON when it ends in ``.json``, else YAML (:func:`load`).

    Raises:
        OSError: the file cannot be read.
        ValueError: malformed JSON (``json.JSONDecodeError``).
        yaml.YAMLError: malformed YAML or a repeated mapping key.
    """
    path = Path(path)
    text = path.read_text()
    return json.loads(text) if path.suffix == ".json" else load(text)


def load_mapping(path: str | Path, what: str, error: type[Exception] = ValueError) -> dict[str, Any]:
    """:func:`load_path` for files that must hold a mapping (an empty file is ``{}``).

    Args:
        path: the file.
        what: what the file is, for messages (``training config``, ``baseline file``, ...).
        error: the exception type raised, with a message naming ``what`` and ``path``.
    """
    try:
        data = load_path(path)
    except (OSError, ValueError, YAMLError) as exc:
        raise error(f"cannot read {what} {path}: {exc}") from exc
    data = data or {}
    if not isinstance(data, dict):
        raise error(f"{what} {path} must be a mapping, got {type(data).__name__}")
    return data
