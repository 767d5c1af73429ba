"""Ctrl-C and SIGTERM around compiled calls: the signal is held until the call has returned.

A Python signal handler runs at the interpreter's next check, in whatever Python code runs next. numba's
dispatcher runs Python code while it unboxes a ``numpy.random.Generator`` argument (``ctypes.cast`` on the
bit generator's function pointers) and ignores a failure there: a ``KeyboardInterrupt`` raised by the
handler at that moment leaves null function pointers in the compiled generator, and its first draw
crashes the process (SIGSEGV, no message, the run folder left ``running``). The same handler running while
the dispatcher boxes the results surfaces as a ``SystemError``.

:func:`signals_deferred` closes that window: while it is open (on the main thread, where Python runs its
signal handlers), SIGINT and SIGTERM are recorded by a handler that only takes note; when the outermost
block ends, the handlers are put back and a signal that came in is handed to the handler that was in
place (``KeyboardInterrupt`` for Ctrl-C, the CLI's ``KeyboardInterrupt`` for SIGTERM, the default action
where none was set). Every compiled call that takes a ``Generator`` runs inside one
(:func:`cv2x_marl.sim.kernels.period_chunk`, the sparse shadowing step, the env's measurement draws).
Cost per outermost block: about 3 us where the CLI's handlers are installed (they take note themselves while
a block is open: two ``signal.getsignal`` calls), about 12 us elsewhere (the handlers are swapped and put back).

The CLI's handlers (:func:`raise_at_a_safe_point`, for both signals) go further: a signal that arrives
while Python code of numba, llvmlite or ctypes runs (compiling a kernel, loading it from the cache, a
``ctypes`` callback, all of which swallow or mishandle an exception raised there) is handed back to the
main thread every :data:`RETRY_S` seconds until it lands in other code, where it raises
``KeyboardInterrupt``.
"""

from __future__ import annotations

import _thread
import atexit
import os
import signal
import sys
import threading
from types import TracebackType
from typing import Any

#: the signals held during a compiled call
HELD = (signal.SIGINT, signal.SIGTERM)


class _Deferred:
    """The re-entrant context manager behind :func:`signals_deferred` (one per process)."""

    def __init__(self) -> None:
        self.depth = 0
        self.saved: dict[int, Any] = {}
        self.pending: list[int] = []

    def note(self, signum: int, frame: Any) -> None:
        """The handler while a block is open: take note of the signal."""
        self.pending.append(signum)

    def __enter__(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # handlers run on the main thread only: another thread's call is never interrupted
        if self.depth == 0:
            self.saved = {}
            self.pending = []
            for sig in HELD:
                previous = signal.getsignal(sig)
                if previous is signal.SIG_IGN or previous is raise_at_a_safe_point:
                    continue  # ignored, or the CLI's handler, which takes note itself while a block is open
                signal.signal(sig, self.note)
                self.saved[sig] = previous
        self.depth += 1

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        self.depth -= 1
        if self.depth:
            return
        saved, self.saved = self.saved, {}
        for sig, previous in saved.items():
            signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
        if not self.pending:
            return
        signum = self.pending[0]
        self.pending = []
        previous = saved.get(signum, signal.getsignal(signum))
        if callable(previous):
            previous(signum, None)  # default_int_handler or the CLI's: raises KeyboardInterrupt
        elif previous is not signal.SIG_IGN:  # SIG_DFL (or not set from Python): the default action, now
            signal.raise_signal(signum)


_DEFERRED = _Deferred()


def signals_deferred() -> _Deferred:
    """A context manager that holds SIGINT / SIGTERM until it ends (re-entrant; a no-op off the main thread).

    Use it around every call into compiled code that takes a ``numpy.random.Generator`` (or boxes results
    through Python code): the signal then takes effect right after the call, as a ``KeyboardInterrupt``
    where Python would have raised one, never inside numba's argument handling.
    """
    return _DEFERRED


#: top-level packages whose Python code must not see a signal's exception (see the module's docstring)
UNSAFE_PACKAGES = frozenset({"numba", "llvmlite", "ctypes"})
#: seconds between two tries of a signal that arrived inside :data:`UNSAFE_PACKAGES`
RETRY_S = 0.05


def _in_unsafe_code(frame: Any) -> bool:
    while frame is not None:
        name = frame.f_globals.get("__name__") or ""
        if name.partition(".")[0] in UNSAFE_PACKAGES:
            return True
        frame = frame.f_back
    return False


#: delay of the first retry of a signal that met unsafe code (a short window such as numba boxing a kernel's
#: results: the main thread is back in the caller's code by then); later retries every :data:`RETRY_S`
FIRST_RETRY_S = 0.001
_deferred: list[int] = []


def raise_at_a_safe_point(signum: int, frame: Any) -> None:
    """A SIGINT / SIGTERM handler: ``KeyboardInterrupt``, unless the main thread is inside the Python code of
    :data:`UNSAFE_PACKAGES`; then the signal is raised again in the main thread (``_thread.interrupt_main``, from
    a timer thread: raised from the handler itself it would be handled again inside it) :data:`FIRST_RETRY_S`
    later, then every :data:`RETRY_S`, until it lands in other code."""
    if _DEFERRED.depth and threading.current_thread() is threading.main_thread():
        _DEFERRED.note(signum, frame)  # inside a compiled call: raised when it returns
        return
    if not _in_unsafe_code(frame):
        _deferred.clear()
        raise KeyboardInterrupt
    retry = threading.Timer(RETRY_S if _deferred else FIRST_RETRY_S, _thread.interrupt_main, args=(signum,))
    retry.daemon = True
    retry.start()
    _deferred.append(signum)


def install_safe_handlers() -> dict[int, Any]:
    """Make SIGINT and SIGTERM call :func:`raise_at_a_safe_point` (main thread only; an ignored signal stays
    ignored). Returns the handlers replaced, for :func:`restore_handlers`."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    previous: dict[int, Any] = {}
    for sig in HELD:
        handler = signal.getsignal(sig)
        if handler is signal.SIG_IGN:
            continue
        previous[sig] = signal.signal(sig, raise_at_a_safe_point)
    return previous


def restore_handlers(previous: dict[int, Any]) -> None:
    """Put back the handlers :func:`install_safe_handlers` replaced."""
    for sig, handler in previous.items():
        signal.signal(sig, handler if handler is not None else signal.SIG_DFL)


_exiting: list[int] = []


def _ignore_while_finalizing() -> None:
    """Registered with ``atexit`` when this module is imported (the CLI imports it first), so it runs after the
    ``atexit`` callbacks of the libraries imported later (torch's among them): from here to the end of the
    interpreter's shutdown, where Python would reset the handlers to the default action (a kill by the
    signal, exit -2), a signal is ignored."""
    if _exiting and threading.current_thread() is threading.main_thread():
        for sig in HELD:
            signal.signal(sig, signal.SIG_IGN)


atexit.register(_ignore_while_finalizing)


def exit_on_signal(status: int) -> None:
    """Once a command has ended: make SIGINT and SIGTERM end the process at once with ``status`` (stdout and
    stderr flushed, ``os._exit``) instead of raising ``KeyboardInterrupt`` into the interpreter's shutdown (a
    second Ctrl-C during ``train`` used to land in torch's ``atexit`` callback); ignored at the very end
    (:func:`_ignore_while_finalizing`). Main thread only; an ignored signal stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        return
    _exiting.append(status)

    def leave(signum: int, frame: Any) -> None:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        os._exit(status)

    for sig in HELD:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, leave)
