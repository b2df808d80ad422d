"""Termination signals for long commands (issue 18 item 14): SIGTERM as an exception, as
Python already turns SIGINT into ``KeyboardInterrupt``.

:func:`termination_signals` (installed by the command line for every command) turns SIGTERM
into :class:`Terminated` and SIGINT into ``KeyboardInterrupt``, also for a process started
with SIGINT ignored. The executors' waits are short timeouts and call
:func:`raise_if_signalled`, so either exception surfaces within a fraction of a second. A
signal landing in a destructor or finalizer is not raised there (Python would swallow it with a
printed traceback, and the cleanup would stop half-done) but by that next wait.
:func:`signals_deferred` holds both back over a step that must not be cut in half. The command
exits 128 + the signal number (130 SIGINT, 143 SIGTERM), POSIX shells' convention.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import sys
import threading
from collections.abc import Iterator
from typing import NoReturn


class Terminated(BaseException):
    """Raised in the main thread when the process receives SIGTERM (exit code 128 + 15)."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(f"terminated by signal {signum}")
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


_DEFERRED: list[int] | None = None  # signals held back by signals_deferred, or None
# The signal received under termination_signals. It stays set: a raise that got swallowed
# (Python ignores exceptions raised in a destructor, where a signal can land) is raised again
# by the executor's next wait.
_SIGNALLED: int | None = None


def _raise_for(signum: int) -> None:
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Terminated(signum)


def _finalizer_codes() -> frozenset:
    import weakref
    from multiprocessing import util

    return frozenset({util.Finalize.__call__.__code__, weakref.finalize.__call__.__code__})


def _in_finalizer(frame) -> bool:
    """Whether the interrupted code runs inside a destructor or a finalizer callback (the
    garbage collector runs them wherever an allocation triggers it)."""
    codes = _finalizer_codes()
    while frame is not None:
        if frame.f_code.co_name == "__del__" or frame.f_code in codes:
            return True
        frame = frame.f_back
    return False


def _on_signal(signum, frame) -> None:
    global _SIGNALLED
    _SIGNALLED = signum
    if _DEFERRED is not None:  # inside a critical section: raise when it ends
        _DEFERRED.append(signum)
        return
    # Raised in a finalizer, the exception would be swallowed with a printed traceback and
    # the cleanup cut in half: a pool's semaphore unlinked but still registered, so the
    # resource tracker warned of a leaked semaphore at exit. The executor's next wait raises it.
    if _in_finalizer(frame):
        return
    _raise_for(signum)


@contextlib.contextmanager
def termination_signals() -> Iterator[None]:
    """While active, SIGTERM raises :class:`Terminated` in the main thread and SIGINT
    ``KeyboardInterrupt`` (also when the process started with SIGINT ignored, as a shell's
    background job does). A no-op outside the main thread; a SIGINT handler someone else
    installed (e.g. a GUI's) is left alone."""
    global _SIGNALLED
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous_signalled = _SIGNALLED
    previous_term = signal.signal(signal.SIGTERM, _on_signal)
    previous_int = signal.getsignal(signal.SIGINT)
    ours_int = previous_int in (signal.SIG_IGN, signal.SIG_DFL, None, signal.default_int_handler)
    if ours_int:
        signal.signal(signal.SIGINT, _on_signal)
    try:
        yield
    finally:
        _SIGNALLED = previous_signalled
        signal.signal(signal.SIGTERM, previous_term)
        if ours_int:
            signal.signal(signal.SIGINT, previous_int if previous_int is not None else signal.SIG_DFL)


def raise_if_signalled() -> None:
    """Raise ``KeyboardInterrupt``/:class:`Terminated` again if a signal arrived under
    :func:`termination_signals` (its first raise may have been swallowed)."""
    if _SIGNALLED is not None:
        _raise_for(_SIGNALLED)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM (as installed by :func:`termination_signals`) back until the block
    ends, for steps that must not be cut in half: starting a worker process (one started but
    not yet registered could not be stopped, and would print a traceback on its own), or
    writing an output and recording that it was written."""
    global _DEFERRED
    if _DEFERRED is not None or threading.current_thread() is not threading.main_thread():
        yield
        return
    _DEFERRED = []
    try:
        yield
    finally:
        pending, _DEFERRED = _DEFERRED, None
        if pending:
            _raise_for(pending[0])


def exit_now(code: int) -> NoReturn:
    """End the process at once with ``code``, without the interpreter's shutdown (which can
    wait on a pool's management thread, or destroy a GUI worker thread still running, which
    aborts), after the cleanup that must not be skipped:

    - multiprocessing's own first exit step: finalizers of priority >= 0 unlink a stopped
      pool's semaphores and close its queues (the joins that can block have priority < 0);
      skipped, the resource tracker warned of "leaked semaphore objects";
    - and its last one: the process's temporary folder (/tmp/pymp-*, the fork server's socket
      in it), removed at priority -100; skipped, every interrupted command left one behind.
      The fork server follows its parent and needs the socket no more;
    - the standard streams, flushed.
    """
    import multiprocessing.process
    from multiprocessing import util

    with contextlib.suppress(Exception):  # each step apart: one failing skips no other
        util._run_finalizers(0)  # type: ignore[attr-defined]  # private: not in typeshed
    with contextlib.suppress(Exception):
        process = multiprocessing.process.current_process()
        tempdir = process._config.get("tempdir")  # type: ignore[attr-defined]  # private
        if tempdir:
            shutil.rmtree(tempdir, ignore_errors=True)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)
