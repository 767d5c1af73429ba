"""Run folders as units: one run writes a folder, and everything in it came from that run.

Every command that writes an output folder (``simulate``, ``dataset``, ``fit``, ``gbmu``,
``evaluate``, ``train``, ``sweep``, ``reproduce``, ``validate``, ``sumo export``) writes it
through :class:`RunFolder`:

* **One writer.** The run holds an exclusive lock (``flock``) on ``<parent>/.<name>.lock``
  (``.cv2x-lock-<digest>`` for names too long for that) for its whole life; a second run on the
  same folder is refused with the holder's pid, host, command and start time. The lock dies with
  the process, so a killed run never blocks a later one.
* **The real folder.** ``--out`` is resolved (``..``, symbolic links) before anything else: a
  symbolic link's target is the run folder, and the link stays.
* **No mixing.** A folder that is not empty is refused unless ``overwrite`` (replace a
  previous run folder as a whole) or ``resume`` (``train --resume`` continues its own run) is
  given.
* **We only replace what we wrote.** ``overwrite`` replaces a folder only when its ``run.json``
  carries this package's marker (``"kind": "cv2x_marl run"``) and the folder holds no file that
  run did not list (a note a user added, another tool's output); otherwise it is refused, naming
  the files. An output folder that is, contains or lies inside an input of the run (``fit --data``,
  a ``ppo:PATH`` model, ``--config``, ...) is refused, and so is one that contains the current
  directory or is a mount point.
* **Nothing half-done.** With ``overwrite`` the previous run is moved aside to a short sibling
  name on the same file system (``.cv2x-old-<digest>-<pid>``) and only deleted when the new run
  completes; if it cannot be moved, the run is refused before anything changed. A run that fails
  or is interrupted is removed and the previous one restored; this holds for every command,
  training included. Without a previous run, ``keep_on_failure`` runs (training) keep their
  checkpoints instead and are marked ``interrupted`` or ``failed``. What happened to the folder is
  attached to the exception as a note (:pep:`678`) that the CLI prints. Leftovers of a run killed
  with SIGKILL are repaired by the next run that takes the lock; until then
  :func:`previous_run_aside` names where the previous run is.
* **A manifest.** ``run.json`` records the command, its arguments, versions, start and end
  times, the status (``running``, ``complete``, ``interrupted``, ``failed``) and, once the run
  ends, every file with its size and SHA-256 (:func:`verify` checks them).
* **Writable first.** The folder is created and ``run.json`` written before any computing.

The manifest's marker, reading and checksums and :class:`RunFolderError` are :mod:`cv2x_marl.run_manifest`'s
(re-exported here).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
import shutil
import socket
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, nullcontext
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2x_marl
from cv2x_marl.io import write_json
from cv2x_marl.run_manifest import (  # noqa: F401 - re-exported: runs' names before the split
    KIND,
    MANIFEST,
    STATUSES,
    RunFolderError,
    check_file,
    file_entries,
    is_ours,
    read_manifest,
    sha256_file,
    unlisted_files,
    verify,
)

try:  # POSIX; on other systems runs are not locked (documented in docs/reliability.md)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

#: longest folder name for which the lock file is ``.<name>.lock`` (file names have 255 bytes)
_LONG_NAME = 200

#: the command line of this process when it is the ``cv2x-marl`` CLI (set by :func:`cv2x_marl.cli.main`)
INVOCATION: list[str] | None = None
#: input files and folders of the CLI command being run (set by :func:`cv2x_marl.cli.main`); every
#: :class:`RunFolder` refuses an output that is, contains or lies inside one of them
INPUTS: list[Path] = []


def is_interrupt(exc: BaseException | None) -> bool:
    """Whether ``exc`` is a Ctrl-C / SIGTERM interrupt.

    Also true for the ``SystemError`` ("returned a result with an exception set") that a numba
    kernel's dispatcher raises when the signal's ``KeyboardInterrupt`` arrives while compiled code
    runs: the interrupt is its ``__cause__`` or ``__context__``.
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        if not isinstance(exc, SystemError):
            return False
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _digest(name: str) -> str:
    return hashlib.sha256(name.encode("utf-8", "surrogateescape")).hexdigest()[:12]


def _aside_prefix(folder: Path) -> str:
    """Prefix of the sibling names a previous run of ``folder`` is moved aside to (short, fixed length)."""
    return f".cv2x-old-{_digest(folder.name)}-"


def _lock_path(folder: Path) -> Path:
    name = folder.name
    short = f".{name}.lock" if len(name.encode("utf-8", "surrogateescape")) <= _LONG_NAME else None
    return folder.parent / (short or f".cv2x-lock-{_digest(name)}")


def _asides(folder: Path) -> list[Path]:
    """Previous runs of ``folder`` moved aside by runs that did not finish (newest name last)."""
    found = list(folder.parent.glob(_aside_prefix(folder) + "*"))
    found += folder.parent.glob(f".{folder.name}.old-*")  # the names of versions before 0.2
    return sorted(p for p in found if p.is_dir() and not p.is_symlink())


def previous_run_aside(folder: str | Path) -> Path | None:
    """Where the previous run of ``folder`` lies when a run that replaced it was killed (SIGKILL)
    before it finished, or None. The next run on ``folder`` puts it back; until then readers can
    name it in their errors."""
    folder = Path(os.path.realpath(folder))
    asides = _asides(folder) if folder.parent.is_dir() else []
    return asides[-1] if asides else None


def _inside(child: Path, parent: Path) -> bool:
    return child == parent or parent in child.parents


def check_not_an_input(out: str | Path, inputs: Sequence[str | Path]) -> None:
    """Refuse an output folder that is, contains or lies inside one of ``inputs``.

    Args:
        out: the output folder (need not exist).
        inputs: files and folders the run reads; names that do not exist are skipped.

    Raises:
        RunFolderError: naming the output, the input and how they overlap.
    """
    out_real = Path(os.path.realpath(out))
    for item in inputs:
        if not os.path.lexists(item):
            continue
        real = Path(os.path.realpath(item))
        if out_real == real:
            how = "is"
        elif _inside(real, out_real):
            how = "contains"
        elif _inside(out_real, real):
            how = "lies inside"
        else:
            continue
        raise RunFolderError(
            f"output folder {out} {how} the input {item} of this run; writing it would change or delete "
            "what the run reads: choose another --out"
        )


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


class _Lock:
    """An exclusive ``flock`` on a lock file holding the holder's description (JSON)."""

    def __init__(self, path: Path, holder: dict[str, Any], folder: Path) -> None:
        self.path = path
        self.holder = holder
        self.folder = folder
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
        return f"output folder {self.folder} is in use by {who}; wait for it to finish or choose another --out"

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
    folder = Path(os.path.realpath(folder))
    holder = {"pid": os.getpid(), "host": socket.gethostname(), "command": command, "started_utc": started_utc}
    lock = _Lock(_lock_path(folder), holder, folder)
    try:
        lock.acquire()
    except OSError as exc:
        raise RunFolderError(f"cannot lock output folder {folder}: {exc.strerror or exc}") from exc
    return lock


def _describe(manifest: dict[str, Any]) -> str:
    when = manifest.get("finished_utc") or manifest.get("started_utc") or "unknown time"
    return f"a previous `{manifest.get('command')}` run ({manifest.get('status')}, {when})"


class RunFolder:
    """Context manager that makes ``path`` the output folder of one run (see the module docstring).

    Args:
        path: the output folder (created if needed; ``..`` and symbolic links are resolved).
        command: the command name recorded in ``run.json`` (``simulate``, ``train``, ...).
        overwrite: replace a previous run folder at ``path`` (only once this run completes).
        resume: continue the run already in ``path`` (``train --resume``); requires its ``run.json``.
        keep_on_failure: on an exception or interrupt keep what was written (status
            ``interrupted`` or ``failed``) instead of removing it (training keeps checkpoints);
            never when a previous run was moved aside, which is then restored instead.
        parameters: run parameters recorded in ``run.json`` (seed, counts, ...).
        inputs: files and folders the run reads; ``path`` may not be, contain or lie inside one
            (:data:`INPUTS`, set by the CLI, is checked too).

    Raises:
        RunFolderError: ``path`` is a file, cannot be created or written, is locked by another
            run, is not empty and neither ``overwrite`` nor ``resume`` is given, holds files no
            run of ours wrote, overlaps an input, or its previous run cannot be moved aside.
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
        inputs: Sequence[str | Path] = (),
    ) -> None:
        self.given = Path(path)
        self.path = Path(os.path.realpath(path))  # `--out .`/`..` have a name and a parent; links are followed
        self.command = command
        self.overwrite = overwrite
        self.resume = resume
        self.keep_on_failure = keep_on_failure or resume  # a resumed run is never removed
        self.parameters = dict(parameters or {})
        self.inputs = [*inputs]
        self.manifest: dict[str, Any] = {}
        self._old: Path | None = None
        self._lock: _Lock | None = None

    # -- entering -----------------------------------------------------------------------------
    def __enter__(self) -> RunFolder:
        path = self.path
        if path.exists() and not path.is_dir():
            raise RunFolderError(f"output folder {path} is a file; choose a folder name for --out")
        if not self.resume:
            check_not_an_input(path, [*self.inputs, *INPUTS])
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
                self._move_previous_aside(previous)
            path.mkdir(exist_ok=True)
            self.manifest = {
                "kind": KIND,
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
            self._roll_back(exc)
            lock.release()
            self._lock = None
            if isinstance(exc, OSError):
                raise RunFolderError(f"cannot write output folder {path}: {exc.strerror or exc}") from exc
            raise
        return self

    def _move_previous_aside(self, previous: dict[str, Any] | None) -> None:
        """Check that the non-empty folder may be replaced, then move it aside (or refuse, unchanged)."""
        path = self.path
        if not is_ours(previous):
            raise RunFolderError(
                f"output folder {path} holds files that no cv2x-marl run wrote (no {MANIFEST} of ours); "
                "refusing to replace them even with --overwrite: choose another --out"
            )
        assert previous is not None
        if not self.overwrite:
            raise RunFolderError(
                f"output folder {path} is not empty: it holds {_describe(previous)}; "
                "pass --overwrite to replace it, or choose another --out"
            )
        extra = unlisted_files(path, previous)
        if extra:
            shown = ", ".join(extra[:5]) + (f" and {len(extra) - 5} more" if len(extra) > 5 else "")
            raise RunFolderError(
                f"output folder {path} holds {_describe(previous)} and files that run did not write ({shown}); "
                "refusing to replace them even with --overwrite: move them out or choose another --out"
            )
        if os.path.ismount(path):
            raise RunFolderError(
                f"output folder {path} is a mount point: the previous run cannot be moved aside and kept until "
                "this run completes; choose a folder inside it for --out"
            )
        if _inside(Path(os.path.realpath(os.getcwd())), path):
            raise RunFolderError(
                f"output folder {path} contains the current directory; replacing it would pull the directory "
                "from under this shell: run from outside it or choose another --out"
            )
        aside = path.parent / f"{_aside_prefix(path)}{os.getpid()}"
        try:
            os.replace(path, aside)
        except OSError as exc:
            raise RunFolderError(
                f"cannot move the previous run in {path} aside to {aside} ({exc.strerror or exc}); nothing was "
                "changed: choose another --out"
            ) from None
        self._old = aside

    def _repair(self) -> None:
        """Undo what a run killed without cleanup left (we hold the lock, so it is dead): a partial
        run of ours (status ``running``) gives way to the previous run it had moved aside; a run that
        completed before it was killed keeps its place and the previous run goes. Anything else is
        left as it is."""
        for old in _asides(self.path):
            current = read_manifest(self.path) if self.path.is_dir() else None
            if current is not None and is_ours(current) and current.get("status") == "running":
                shutil.rmtree(self.path)
            elif self.path.is_dir() and not any(self.path.iterdir()):
                self.path.rmdir()
            if not self.path.exists():
                os.replace(old, self.path)
            elif current is not None and is_ours(current) and is_ours(read_manifest(old)):
                shutil.rmtree(old, ignore_errors=True)

    def _roll_back(self, exc: BaseException) -> None:
        """Put the previous run back in place of the partial one; say what happened in a note on ``exc``."""
        if self._old is None:
            return
        old, self._old = self._old, None
        shutil.rmtree(self.path, ignore_errors=True)
        try:
            os.replace(old, self.path)
        except OSError as err:
            _note(exc, f"the previous run could not be put back ({err.strerror or err}); it is in {old}")
            return
        _note(exc, f"the previous run in {self.path} was restored")

    # -- leaving ------------------------------------------------------------------------------
    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            if exc is None:
                try:
                    self._finish("complete")
                except BaseException as err:  # a full disk while listing the files: the run did not complete
                    self._fail(err)
                    raise
                if self._old is not None:
                    shutil.rmtree(self._old, ignore_errors=True)
                    self._old = None
            else:
                self._fail(exc)
        finally:
            if self._lock is not None:
                self._lock.release()
                self._lock = None

    def _fail(self, exc: BaseException) -> None:
        if self._old is not None:
            self._roll_back(exc)
        elif self.keep_on_failure:
            interrupted = is_interrupt(exc)
            status = "interrupted" if interrupted else "failed"
            try:
                self._finish(status, error=None if interrupted else exc)
                _note(exc, f"what the run wrote is kept in {self.path} (status {status})")
            except OSError as err:
                _note(
                    exc,
                    f"what the run wrote is kept in {self.path}, but its {MANIFEST} could not be updated "
                    f"({err.strerror or err})",
                )
        else:
            shutil.rmtree(self.path, ignore_errors=True)
            _note(exc, f"nothing was left in {self.path}")

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


def _note(exc: BaseException, text: str) -> None:
    """Attach what happened to the output folder to ``exc`` (printed by the CLI); once per text."""
    if text not in getattr(exc, "__notes__", []):
        exc.add_note(text)


def notes(exc: BaseException) -> list[str]:
    """The notes :class:`RunFolder` attached to ``exc`` (and to the exceptions it was raised from)."""
    out: list[str] = []
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        out += [n for n in getattr(e, "__notes__", []) if n not in out]
        e = e.__cause__ or e.__context__
    return out


def _segment(previous: dict[str, Any]) -> dict[str, Any]:
    return {k: previous.get(k) for k in ("argv", "parameters", "status", "started_utc", "finished_utc")}


def _versions() -> dict[str, str]:
    import numpy as np

    return {"cv2x_marl": cv2x_marl.__version__, "numpy": np.__version__, "python": platform.python_version()}


def run_folder(
    path: str | Path | None,
    command: str,
    *,
    overwrite: bool = False,
    parameters: dict[str, Any] | None = None,
    inputs: Sequence[str | Path] = (),
) -> Any:
    """A :class:`RunFolder` for ``path``, or a no-op context when ``path`` is None (no output)."""

    if path is None:
        return nullcontext()
    return RunFolder(path, command, overwrite=overwrite, parameters=parameters, inputs=inputs)


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
