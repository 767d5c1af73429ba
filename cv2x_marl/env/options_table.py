"""The table of the env's options (``docs/env.md``'s ``Arguments``), generated from the schema:
``python -m cv2x_marl.env.options_table`` prints it; ``tests/env/test_options.py`` checks the page holds it."""

from __future__ import annotations

import dataclasses
import typing

from cv2x_marl import schema
from cv2x_marl.env.defaults import VERSION_DEFAULTS
from cv2x_marl.env.options import EnvOptions, allowed_text


def options_markdown() -> str:
    """The table of :class:`EnvOptions` (the ``Arguments`` table of ``docs/env.md``)."""
    hints = typing.get_type_hints(EnvOptions)
    lines = ["| argument | role | type | unit | default | allowed | meaning |", "|---|---|---|---|---|---|---|"]
    for f in dataclasses.fields(EnvOptions):
        tp, optional = schema.base_type(hints[f.name])
        if typing.get_origin(tp) is not None:  # Sequence[X]
            tname = "list of " + typing.get_args(tp)[0].__name__
        else:
            tname = tp.__name__
        tname += " or null" if optional else ""
        default = f.metadata["shown"] or ("null" if f.default is None else str(f.default))
        per_version = [f"{v}: {d[f.name]}" for v, d in VERSION_DEFAULTS.items() if f.name in d]
        if per_version:
            default = f"{default} ({', '.join(per_version)})"
        cells = [c.replace("|", "\\|") for c in (allowed_text(f, tp, optional), f.metadata["doc"])]
        unit = f.metadata["unit"] or "-"
        role = f.metadata["role"]
        lines.append(f"| `{f.name}` | {role} | {tname} | {unit} | `{default}` | {cells[0]} | {cells[1]} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    import sys

    sys.stdout.write(options_markdown())
