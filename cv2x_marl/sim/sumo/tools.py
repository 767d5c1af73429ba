"""Finding SUMO and running its tools; the content-keyed cache of generated files (issue 14).

The ``sumo`` extra (the ``eclipse-sumo`` wheel) holds SUMO's binaries and Python tools:
:func:`sumo_home` finds them, :func:`run_tool` / :func:`run_python_tool` run them as children that
die with this process, :func:`import_libsumo` imports libsumo quietly. Generated files are cached
under a content-hash key in :func:`cache_dir` (``$CV2X_MARL_SUMO_CACHE``, else
``$XDG_CACHE_HOME/cv2x_marl/sumo`` or ``~/.cache/cv2x_marl/sumo``), written into a temporary folder
and renamed into place (:func:`cached`).
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from cv2x_marl.extras import missing_extra, require

#: environment variable that overrides where generated scenarios are cached
CACHE_ENV = "CV2X_MARL_SUMO_CACHE"


class SumoError(ValueError):
    """A SUMO scenario or trace cannot be used (the message names the file or key)."""


# ------------------------------------------------------------------------------------------ install
def sumo_home() -> Path:
    """The SUMO installation of the ``eclipse-sumo`` wheel (binaries under ``bin/``).

    Raises:
        MissingExtraError: the ``sumo`` extra is not installed.
    """
    mod = require("sumo", "vehicles.mobility=sumo")
    home = getattr(mod, "SUMO_HOME", None)
    if home is None:
        raise missing_extra(
            "sumo", "vehicles.mobility=sumo (the importable 'sumo' module is not the eclipse-sumo wheel)"
        )
    return Path(home)


def sumo_version() -> str:
    """Version of the installed ``eclipse-sumo`` wheel."""
    import importlib.metadata

    try:
        return importlib.metadata.version("eclipse-sumo")
    except importlib.metadata.PackageNotFoundError:
        sumo_home()  # raises the missing-extra error
        return "unknown"


def _tool(name: str) -> Path:
    path = sumo_home() / "bin" / name
    if not path.is_file():
        raise SumoError(f"SUMO tool {name} not found at {path}; reinstall the 'sumo' extra")
    return path


def _die_with_parent() -> None:  # pragma: no cover - runs in the child
    """Linux: the child gets SIGKILL when this process dies, so no SUMO process outlives ours."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def run_tool(name: str, args: Sequence[str], cwd: Path | None = None) -> None:
    """Run a SUMO binary (``netgenerate``, ``sumo``) to completion.

    The child dies with this process (Linux, ``PR_SET_PDEATHSIG``; set only while this process has a
    single thread, because code run between fork and exec can deadlock in a threaded parent), and
    ``subprocess.run`` kills it on an interrupt.

    Raises:
        SumoError: the tool failed (its error output is in the message).
    """
    cmd = [str(_tool(name)), *args]
    _run(name, cmd, cwd)


def run_python_tool(name: str, args: Sequence[str], cwd: Path | None = None) -> None:
    """Run one of SUMO's Python tools (``randomTrips.py``) with this interpreter, like :func:`run_tool`."""
    script = sumo_home() / "tools" / name
    if not script.is_file():
        raise SumoError(f"SUMO tool {name} not found at {script}; reinstall the 'sumo' extra")
    _run(name, [sys.executable, str(script), *args], cwd)


def _run(name: str, cmd: list[str], cwd: Path | None) -> None:
    env = dict(os.environ, SUMO_HOME=str(sumo_home()))
    import threading

    preexec = _die_with_parent if threading.active_count() == 1 else None
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, preexec_fn=preexec)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip()[-2000:]
        raise SumoError(f"{name} failed (exit {proc.returncode}): {' '.join(cmd)}\n{tail}")


def import_libsumo() -> Any:
    """``libsumo``, imported quietly (its import prints a pyarrow ABI note we do not need:
    libsumo's own parquet output is not used)."""
    if "libsumo" in sys.modules:
        return sys.modules["libsumo"]
    with contextlib.redirect_stdout(io.StringIO()):
        return require("libsumo", "vehicles.mobility=sumo")


# ------------------------------------------------------------------------------------------- cache
def cache_dir() -> Path:
    """Where generated scenarios are cached: ``$CV2X_MARL_SUMO_CACHE``, else the user cache dir; an
    absolute path (SUMO's tools run in temporary folders and are handed paths into it)."""
    env = os.environ.get(CACHE_ENV)
    if env:
        return Path(env).resolve()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return (Path(base) / "cv2x_marl" / "sumo").resolve()


def content_key(data: Any) -> str:
    """Hex SHA-256 (24 digits) of ``data`` as canonical JSON."""
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:24]


def cached(kind: str, key_data: Any, build: Callable[[Path], None]) -> Path:
    """The cache folder for ``key_data``, built by ``build(folder)`` when absent.

    ``build`` writes into a temporary folder, renamed into place when it returns, so a folder in
    the cache is always complete; of two processes building the same key, one rename wins.
    """
    root = cache_dir()
    final = root / f"{kind}-{content_key(key_data)}"
    if final.is_dir():
        return final
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=root))
    try:
        build(tmp)
        (tmp / "key.json").write_text(json.dumps(key_data, sort_keys=True, indent=1) + "\n")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp creates 0700; give the folder the usual mode
        try:
            os.rename(tmp, final)
        except OSError:
            if not final.is_dir():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return final
