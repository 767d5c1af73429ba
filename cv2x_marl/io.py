"""File input and output: atomic writes (a temporary file in the same folder, then a rename) and
size-capped reads of input files."""

from __future__ import annotations

import json
import math
import os
import stat
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


class InputFileError(ValueError):
    """An input file that is not a regular file, or is larger than the limit for its kind."""


def _kind_of(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a named pipe"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def read_text_limited(path: str | Path, limit_bytes: int, what: str = "input file") -> str:
    """The text of a regular file of at most ``limit_bytes`` bytes (UTF-8).

    Devices, pipes and folders are refused before they are opened (``/dev/zero`` would never end),
    and no more than ``limit_bytes + 1`` bytes are ever read, whatever the file system says its size is.

    Args:
        path: the file.
        limit_bytes: the largest size accepted, in bytes.
        what: what the file is, for messages (``configuration file``, ``model file``, ...).

    Raises:
        OSError: the file does not exist or cannot be read.
        InputFileError: not a regular file, larger than ``limit_bytes``, or not UTF-8 text; the message
            names ``what``, the file, its size and the limit.
    """
    path = Path(path)
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise InputFileError(f"{what} {path} is {_kind_of(mode)}, not a regular file; give a file")
    with open(path, "rb") as f:
        data = f.read(limit_bytes + 1)
        size = os.fstat(f.fileno()).st_size
    if len(data) > limit_bytes:
        shown = f"{size:,} bytes" if size > limit_bytes else f"more than {limit_bytes:,} bytes"
        raise InputFileError(
            f"{what} {path} is {shown}, above the limit of {limit_bytes:,} bytes ({limit_bytes / 2**20:g} MiB) "
            f"for a {what}"
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(f"{what} {path} is not UTF-8 text: {exc.reason} at byte {exc.start}") from exc
