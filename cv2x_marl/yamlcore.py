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

Limits, so that no document can exhaust memory or the stack (each refusal is a
:class:`yaml.YAMLError` or ``ValueError`` naming the limit):

* :data:`MAX_FILE_BYTES`: configuration files are regular files of at most 10 MiB
  (``--config /dev/zero`` is refused before it is opened);
* :data:`MAX_DEPTH`: mappings and lists nest at most 100 levels deep (YAML and JSON alike,
  counted after aliases are expanded);
* :data:`MAX_NODES`: a YAML document has at most 100,000 nodes once its aliases are expanded
  (a 400-byte "billion laughs" document of nested aliases stands for 10^8 values; it is refused
  while it is composed, before any value is built);
* integers have at most 4,300 digits (Python's limit for converting text to an integer).
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

import yaml

from cv2x_marl.io import InputFileError, read_text_limited

__all__ = [
    "MAX_DEPTH",
    "MAX_FILE_BYTES",
    "MAX_NODES",
    "CoreLoader",
    "YAMLError",
    "load",
    "load_json",
    "load_mapping",
    "load_path",
    "parse_scalar",
]

YAMLError = yaml.YAMLError

#: the largest configuration file read, in bytes (10 MiB)
MAX_FILE_BYTES = 10 * 2**20
#: the deepest nesting of mappings and lists in a document (after alias expansion)
MAX_DEPTH = 100
#: the most nodes (scalars, mappings, lists) a YAML document may have once its aliases are expanded
MAX_NODES = 100_000

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
    """A safe PyYAML loader with YAML 1.2 core-schema scalars, no duplicate keys, and the limits
    :data:`MAX_DEPTH` and :data:`MAX_NODES` checked while the document is composed."""

    def __init__(self, stream: Any) -> None:
        super().__init__(stream)
        self._depth = 0  # nodes being composed, the current one included
        self._expanded: dict[int, tuple[int, int]] = {}  # id(node) -> (nodes, depth) with aliases expanded

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):  # the anchored node, already composed (and measured)
            return super().compose_node(parent, index)
        mark = self.peek_event().start_mark
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise yaml.composer.ComposerError(
                    None, None, f"mappings and lists nest more than {MAX_DEPTH} levels deep (the limit)", mark
                )
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        if node is not None:
            self._measure(node, mark)
        return node

    def _measure(self, node: yaml.Node, mark: Any) -> None:
        """Record the node count and depth of ``node`` with its aliases expanded; refuse the limits."""
        if isinstance(node, yaml.MappingNode):
            children = [c for pair in node.value for c in pair]
        elif isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        else:
            children = []
        nodes, depth = 1, 1
        for child in children:
            sub = self._expanded.get(id(child))
            if sub is None:  # an alias to a node still being composed: the node contains itself
                raise yaml.composer.ComposerError(
                    None, None, "an alias refers to a node that contains it (a recursive document)", mark
                )
            nodes += sub[0]
            depth = max(depth, sub[1] + 1)
        if nodes > MAX_NODES:
            raise yaml.composer.ComposerError(
                None,
                None,
                f"the document has more than {MAX_NODES:,} values once its aliases are expanded (the limit)",
                mark,
            )
        if depth > MAX_DEPTH:
            raise yaml.composer.ComposerError(
                None,
                None,
                f"mappings and lists nest more than {MAX_DEPTH} levels deep once aliases are expanded (the limit)",
                mark,
            )
        self._expanded[id(node)] = (nodes, depth)

    def construct_yaml_int(self, node: yaml.ScalarNode) -> int:
        text = str(self.construct_scalar(node))
        try:
            if text.startswith("0o"):
                return int(text[2:], 8)
            if text.startswith("0x"):
                return int(text[2:], 16)
            return int(text, 10)
        except ValueError:  # more digits than Python converts (sys.get_int_max_str_digits)
            raise yaml.constructor.ConstructorError(
                None,
                None,
                f"an integer of {len(text):,} characters; integers have at most {sys.get_int_max_str_digits():,} "
                "digits (the limit)",
                node.start_mark,
            ) from None

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


def load(text: str, name: str | None = None) -> Any:
    """Parse a YAML document with the YAML 1.2 core schema (:class:`CoreLoader`).

    Args:
        text: the document.
        name: where it came from (a file name), for the positions in error messages.

    Raises:
        yaml.YAMLError: malformed YAML, a repeated mapping key, or a limit of the document
            (:data:`MAX_DEPTH`, :data:`MAX_NODES`, integer digits).
    """
    loader = CoreLoader(text)
    if name is not None:
        loader.name = name
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def parse_scalar(text: str) -> Any:
    """The value of ``KEY=VALUE`` text (``--set``): ``3e-4`` -> 0.0003, ``010`` -> 10, ``[1, 2]`` -> list."""
    return load(text) if text.strip() else None


def _json_depth(data: Any) -> int:
    """The nesting depth of parsed JSON (1 for a scalar), without recursion."""
    deepest, stack = 0, [(data, 1)]
    while stack:
        value, depth = stack.pop()
        deepest = max(deepest, depth)
        if deepest > MAX_DEPTH:
            break
        if isinstance(value, dict):
            stack.extend((v, depth + 1) for v in value.values())
        elif isinstance(value, list):
            stack.extend((v, depth + 1) for v in value)
    return deepest


def load_json(text: str) -> Any:
    """Parse JSON text, refusing documents that nest deeper than :data:`MAX_DEPTH`.

    Raises:
        ValueError: malformed JSON (``json.JSONDecodeError``), too deep a document, or an integer of
            more digits than Python converts.
    """
    try:
        data = json.loads(text)
    except RecursionError:
        data = None
    else:
        if _json_depth(data) <= MAX_DEPTH:
            return data
    raise ValueError(f"objects and arrays nest more than {MAX_DEPTH} levels deep (the limit)")


def load_path(path: str | Path, what: str = "configuration file") -> Any:
    """Read a configuration file: JSON when it ends in ``.json``, else YAML (:func:`load`).

    The file must be a regular file of at most :data:`MAX_FILE_BYTES` bytes
    (:func:`cv2x_marl.io.read_text_limited`).

    Raises:
        OSError: the file cannot be read.
        cv2x_marl.io.InputFileError: not a regular file, or too large (the message names ``what``).
        ValueError: malformed JSON (``json.JSONDecodeError``) or too deep a JSON document.
        yaml.YAMLError: malformed YAML, a repeated mapping key, or a limit of the YAML document.
    """
    path = Path(path)
    text = read_text_limited(path, MAX_FILE_BYTES, what)
    return load_json(text) if path.suffix == ".json" else load(text, str(path))


def load_mapping(path: str | Path, what: str, error: type[Exception] = ValueError) -> dict[str, Any]:
    """:func:`load_path` for files that must hold a mapping (an empty file is ``{}``).

    Args:
        path: the file.
        what: what the file is, for messages (``training config``, ``baseline file``, ...).
        error: the exception type raised, with a message naming ``what`` and ``path``.
    """
    try:
        data = load_path(path, what)
    except InputFileError as exc:  # the message names the file and the limit
        raise error(str(exc)) from exc
    except (OSError, ValueError, YAMLError) as exc:
        raise error(f"cannot read {what} {path}: {exc}") from exc
    data = data or {}
    if not isinstance(data, dict):
        raise error(f"{what} {path} must be a mapping, got {type(data).__name__}")
    return data
