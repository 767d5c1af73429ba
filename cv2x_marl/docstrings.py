"""Docstrings as Markdown, for the generated pages (``docs/envs/``, ``docs/api.md``)."""

from __future__ import annotations

import inspect
import re


def summary(doc: str | None) -> str:
    """The first paragraph of a docstring on one line, its reStructuredText roles (``:func:`~a.b```) and literals
    (````x````) as Markdown code (`` `b` ``, `` `x` ``)."""
    para = inspect.cleandoc(doc or "").split("\n\n", 1)[0]
    line = " ".join(part.strip() for part in para.splitlines())
    line = re.sub(r":\w+:`~?([^`]+)`", lambda m: f"`{m.group(1).rsplit('.', 1)[-1]}`", line)
    return line.replace("``", "`")
