"""Atomic file output: write to a temporary file in the same folder, then rename."""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


def atomic_write(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp_path)`` then rename onto ``path``; nothing half-written is left on failure."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        write(tmp_path)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp creates 0600; give the file the usual mode
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise
    return path


def strict(data: Any) -> Any:
    """``data`` with every NaN or infinite float (numpy ones too) replaced by None and numpy scalars
    and arrays turned into Python values, so it serialises as strict JSON (RFC 8259 has no NaN)."""
    if isinstance(data, dict):
        return {k: strict(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [strict(v) for v in data]
    if hasattr(data, "tolist") and not isinstance(data, str | bytes):  # numpy scalar or array
        return strict(data.tolist())
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def dumps_json(data: Any) -> str:
    """Indented strict JSON of ``data`` (:func:`strict`: NaN and infinities as null)."""
    return json.dumps(strict(data), indent=2, allow_nan=False)


def write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented strict JSON (NaN and infinities as null), atomically."""
    text = dumps_json(data) + "\n"
    return atomic_write(path, lambda p: p.write_text(text))
