"""Run folders as units: one run writes a folder, and everything in it came from that run.

Every command that writes an output folder (``simulate``, ``dataset``, ``fit``, ``gbmu``,
``evaluate``, ``train``, ``reproduce``) writes it through :class:`RunFolder`:

* **One writer.** The run holds an exclusive lock (``flock``) on ``<parent>/.<name>.lock``
  for its whole life; a second run on the same folder is refused with the holder's pid, host,
  command and start time. The lock dies with the process, so a killed run never blocks a
  later one.
* **No mixing.** A folder that is not empty is refused unless ``overwrite`` (replace a
  previous run folder as a whole) or ``resume`` (``train --resume`` continues its own run) is
  given. A folder with files but no ``run.json`` is never replaced: it was not written by a
  run, and we do not delete what we did not write.
* **Nothing half-done.** With ``overwrite`` the previous run is moved aside
  (``.<name>.old-<pid>``) and only deleted when the new run completes; a run that fails or is
  interrupted is removed and the previous one restored (``keep_on_failure`` runs, i.e.
  training, keep their checkpoints instead and are marked ``interrupted``). Leftovers of a run
  killed with SIGKILL are repaired by the next run that takes the lock.
* **A manifest.** ``run.json`` records the command, its arguments, versions, start and end
  times, the status (``running``, ``complete``, ``interrupted``, ``failed``) and, once the run
  ends, every file with its size and SHA-256 (:func:`verify` checks them).
* **Writable first.** The folder is created and ``run.json`` written before any computing.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
import shutil
import socket
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path
from types import TracebackType
from typing import Any

from cv2x_marl.io import write_json

try:  # POSIX; on other systems runs are not locked (documented in docs/reliability.md)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

MANIFEST = "run.json"
STATUSES = ("running", "complete", "interrupted", "failed")

#: the command line of this process when it is the ``cv2x-marl`` CLI (set by :func:`cv2x_marl.cli.main`)
INVOCATION: list[str] | None = None


class RunFolderError(ValueError):
    """An output folder cannot be used: in use, not empty, not writable, or corrupt."""


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def file_entries(folder: str | Path) -> dict[str, dict[str, Any]]:
    """``{relative path: {"bytes", "sha256"}}`` of every file under ``folder`` (sorted; the
    top-level ``run.json`` and hidden temporary files excluded)."""
    folder = Path(folder)
    out: dict[str, dict[str, Any]] = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if not p.is_file() or rel == MANIFEST or p.name.endswith(".tmp"):
            continue
        out[rel] = {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
    return out


def read_manifest(folder: str | Path) -> dict[str, Any] | None:
    """The ``run.json`` of a folder, or None when it has none (or it is unreadable)."""
    try:
        data = json.loads((Path(folder) / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def verify(folder: str | Path, names: list[str] | None = None) -> None:
    """Check files of a finished run folder against the checksums of its ``run.json``.

    Args:
        folder: the run folder.
        names: relative paths to check (default: every file the manifest lists).

    Raises:
        RunFolderError: a listed file is missing or its bytes differ (naming the file).
    """
    folder = Path(folder)
    manifest = read_manifest(folder)
    if manifest is None or "files" not in manifest:
        raise RunFolderError(f"{folder} has no {MANIFEST} with checksums (not a finished run folder)")
    files: dict[str, Any] = manifest["files"]
    for name in names if names is not None else list(files):
        entry = files.get(name)
        path = folder / name
        if entry is None:
            raise RunFolderError(f"{path} is not listed in {folder / MANIFEST}")
        if not path.is_file():
            raise RunFolderError(f"{path} is missing (listed in {folder / MANIFEST})")
        if path.stat().st_size != entry["bytes"] or sha256_file(path) != entry["sha256"]:
            raise RunFolderError(
                f"{path} does not match its checksum in {folder / MANIFEST}: the file was changed or corrupted"
            )


def check_file(path: str | Path) -> None:
    """Verify ``path`` when the ``run.json`` beside it lists it (files of older runs pass).

    Raises:
        RunFolderError: the file's bytes differ from the recorded checksum.
    """
    path = Path(path)
    manifest = read_manifest(path.parent)
    if manifest is not None and path.name in manifest.get("files", {}):
        verify(path.parent, [path.name])


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


class _Lock:
    """An exclusive ``flock`` on a lock file holding the holder's description (JSON)."""

    def __init__(self, path: Path, holder: dict[str, Any]) -> None:
        self.path = path
        self.holder = holder
        self.fd: int | None = None

    def acquire(self) -> None:
        if fcntl is None:  # pragma: no cover - Windows
            return
        for _ in range(100):
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                raise RunFolderError(self._busy_message()) from None
            try:  # the previous holder may have removed the file between our open and flock
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                os.ftruncate(fd, 0)
                os.write(fd, json.dumps(self.holder).encode())
                self.fd = fd
                return
            os.close(fd)
        raise RunFolderError(f"could not lock {self.path}: it keeps being replaced")  # pragma: no cover

    def _busy_message(self) -> str:
        try:
            h = json.loads(self.path.read_text())
            who = f"pid {h['pid']} on {h['host']} (`cv2x-marl {h['command']}`, since {h['started_utc']})"
        except (OSError, ValueError, KeyError, TypeError):
            who = "another process"
        folder = self.path.parent / self.path.name[1 : -len(".lock")]
        return f"output folder {folder} is in use by {who}; wait for it to finish or choose another --out"

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)  # while still holding it: see acquire's inode check
        finally:
            os.close(self.fd)
            self.fd = None


def _lock_folder(folder: Path, command: str, started_utc: str) -> _Lock:
    """Take the run lock of ``folder`` (``<parent>/.<name>.lock``) for ``command``.

    Raises:
        RunFolderError: another run holds it, or the lock file cannot be created.
    """
    holder = {"pid": os.getpid(), "host": socket.gethostname(), "command": command, "started_utc": started_utc}
    lock = _Lock(folder.parent / f".{folder.resolve().name}.lock", holder)
    try:
        lock.acquire()
    except OSError as exc:
        raise RunFolderError(f"cannot lock output folder {folder}: {exc.strerror or exc}") from exc
    return lock


class RunFolder:
    """Context manager that makes ``path`` the output folder of one run (see the module docstring).

    Args:
        path: the output folder (created if needed).
        command: the command name recorded in ``run.json`` (``simulate``, ``train``, ...).
        overwrite: replace a previous run folder at ``path`` (only once this run completes).
        resume: continue the run already in ``path`` (``train --resume``); requires its ``run.json``.
        keep_on_failure: on an exception or interrupt keep what was written (status
            ``interrupted`` or ``failed``) instead of removing it (training keeps checkpoints).
        parameters: run parameters recorded in ``run.json`` (seed, counts, ...).

    Raises:
        RunFolderError: ``path`` is a file, cannot be created or written, is locked by another
            run, or is not empty and neither ``overwrite`` nor ``resume`` is given.
    """

    def __init__(
        self,
        path: str | Path,
        command: str,
        *,
        overwrite: bool = False,
        resume: bool = False,
        keep_on_failure: bool = False,
        parameters: dict[str, Any] | None = None,
    ) -> None:
        self.path = Path(path).absolute()  # `--out .` has a name and a parent
        self.command = command
        self.overwrite = overwrite
        self.resume = resume
        self.keep_on_failure = keep_on_failure or resume  # a resumed run is never removed
        self.parameters = dict(parameters or {})
        self.manifest: dict[str, Any] = {}
        self._old: Path | None = None
        self._lock: _Lock | None = None

    # -- entering -----------------------------------------------------------------------------
    def __enter__(self) -> RunFolder:
        path = self.path
        if path.exists() and not path.is_dir():
            raise RunFolderError(f"output folder {path} is a file; choose a folder name for --out")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunFolderError(f"cannot create output folder {path}: {exc.strerror or exc}") from exc
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise RunFolderError(f"cannot write output folder {path}: {path.parent} is not writable")
        started = _now()
        lock = self._lock = _lock_folder(path, self.command, started)
        try:
            self._repair()
            previous = read_manifest(path) if path.is_dir() else None
            if self.resume:
                if not path.is_dir() or not any(path.iterdir()):
                    raise RunFolderError(f"--resume: {path} holds no run; nothing to resume")
            elif path.is_dir() and any(path.iterdir()):
                if not self.overwrite:
                    what = (
                        f"a previous `{previous.get('command')}` run ({previous.get('status')}, "
                        f"{previous.get('finished_utc') or previous.get('started_utc')})"
                        if previous
                        else "files"
                    )
                    raise RunFolderError(
                        f"output folder {path} is not empty: it holds {what}; "
                        "pass --overwrite to replace it, or choose another --out"
                    )
                if previous is None:
                    raise RunFolderError(
                        f"output folder {path} holds files that no cv2x-marl run wrote (no {MANIFEST}); "
                        "refusing to replace them even with --overwrite: choose another --out"
                    )
                self._old = path.parent / f".{path.name}.old-{os.getpid()}"
                os.replace(path, self._old)
                if self.keep_on_failure:  # nothing to restore for runs that keep their partial state
                    shutil.rmtree(self._old, ignore_errors=True)
                    self._old = None
            path.mkdir(exist_ok=True)
            self.manifest = {
                "kind": "cv2x_marl run",
                "command": self.command,
                "argv": INVOCATION,
                "parameters": self.parameters,
                "status": "running",
                "started_utc": started,
                "finished_utc": None,
                "pid": os.getpid(),
                "host": socket.gethostname(),
                "versions": _versions(),
            }
            if self.resume and previous is not None:
                self.manifest["segments"] = [*previous.get("segments", []), _segment(previous)]
            write_json(path / MANIFEST, self.manifest)
        except BaseException as exc:
            self._restore_old()
            lock.release()
            self._lock = None
            if isinstance(exc, OSError):
                raise RunFolderError(f"cannot write output folder {path}: {exc.strerror or exc}") from exc
            raise
        return self

    def _repair(self) -> None:
        """Undo what a run killed without cleanup left (we hold the lock, so it is dead)."""
        for old in sorted(self.path.parent.glob(f".{self.path.name}.old-*")):
            if not old.is_dir():
                continue
            partial = read_manifest(self.path) if self.path.is_dir() else None
            if self.path.is_dir() and (partial is None or partial.get("status") == "running"):
                shutil.rmtree(self.path)
            if not self.path.exists():
                os.replace(old, self.path)
            else:
                shutil.rmtree(old, ignore_errors=True)

    def _restore_old(self) -> None:
        if self._old is None:
            return
        shutil.rmtree(self.path, ignore_errors=True)
        os.replace(self._old, self.path)
        self._old = None

    # -- leaving ------------------------------------------------------------------------------
    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            if exc_type is None:
                self._finish("complete")
                if self._old is not None:
                    shutil.rmtree(self._old, ignore_errors=True)
                    self._old = None
            elif self.keep_on_failure:
                interrupted = issubclass(exc_type, KeyboardInterrupt)
                try:
                    self._finish("interrupted" if interrupted else "failed", error=None if interrupted else exc)
                except OSError:
                    pass  # the original error is the one to report
            else:
                shutil.rmtree(self.path, ignore_errors=True)
                self._restore_old()
        finally:
            if self._lock is not None:
                self._lock.release()
                self._lock = None

    def finish(self, status: str = "complete") -> None:
        """Record the files and their checksums now (also done on leaving the context)."""
        self._finish(status)

    def _finish(self, status: str, error: BaseException | None = None) -> None:
        self.manifest.update(
            {
                "status": status,
                "finished_utc": _now(),
                "files": file_entries(self.path),
            }
        )
        if error is not None:
            self.manifest["error"] = f"{type(error).__name__}: {error}"
        write_json(self.path / MANIFEST, self.manifest)


def _segment(previous: dict[str, Any]) -> dict[str, Any]:
    return {k: previous.get(k) for k in ("argv", "parameters", "status", "started_utc", "finished_utc")}


def _versions() -> dict[str, str]:
    import numpy as np

    import cv2x_marl

    return {"cv2x_marl": cv2x_marl.__version__, "numpy": np.__version__, "python": platform.python_version()}


def run_folder(
    path: str | Path | None,
    command: str,
    *,
    overwrite: bool = False,
    parameters: dict[str, Any] | None = None,
) -> Any:
    """A :class:`RunFolder` for ``path``, or a no-op context when ``path`` is None (no output)."""

    if path is None:
        return nullcontext()
    return RunFolder(path, command, overwrite=overwrite, parameters=parameters)


@contextmanager
def locked(folder: str | Path, command: str) -> Iterator[None]:
    """Hold the run lock of ``folder`` (which must exist) without treating it as a run folder:
    for commands that add result files to a folder of inputs (``cv2x-marl baselines``).

    Raises:
        RunFolderError: another run holds the folder.
    """
    lock = _lock_folder(Path(folder), command, _now())
    try:
        yield
    finally:
        lock.release()
