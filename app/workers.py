"""Background work for the GUI: a cancellable worker thread and a "latest edit wins" scheduler.

The GUI thread never runs anything that can take more than ~100 ms. Long computations from
``core`` (model builds, evaluations, refits) run in a :class:`Worker`, a ``QThread`` that calls
one function and reports back through Qt signals. Signals emitted from the worker thread reach
slots of objects living in the GUI thread as queued calls, so receivers must be methods of
QObjects (widgets, the window) created in the GUI thread.

Cancellation follows ``core.runtime.progress``: the function is given a ``progress(fraction, message)``
callback; after :meth:`Worker.cancel` the next call of that callback raises
:class:`core.runtime.progress.Cancelled`, which unwinds the computation and ends in ``cancelled``.

:class:`LatestWinsRunner` serialises a stream of requests (one per edit) onto one worker at a
time: a new request replaces any request still waiting, marks the running one stale (its
progress callback raises ``Cancelled`` at its next call) and the result of a stale run is
dropped, so only the outcome of the newest request is ever delivered.

Usage::

    worker = Worker(build_model, meshes, method="pca")       # build_model(..., progress=...)
    worker.progress.connect(panel.on_progress)
    worker.succeeded.connect(panel.on_model_built)
    worker.failed.connect(panel.on_error)                     # one-line message, no traceback
    worker.start()
    ...
    worker.cancel()
"""

from __future__ import annotations

import inspect
import sys
import threading
import traceback
from collections.abc import Callable
from typing import Any

from PySide6.QtCore import QObject, Qt, QThread, Signal, Slot

from core.runtime.progress import Cancelled

__all__ = ["Worker", "DialogTask", "LatestWinsRunner", "error_message", "running_workers",
           "settle_at_exit"]

# Workers still running are kept alive here: a QThread garbage-collected while running aborts
# the process ("QThread: Destroyed while thread is still running").
_RUNNING: set[Worker] = set()


def running_workers() -> list[Worker]:
    """Workers started and not yet finished (for tests and for waiting at exit)."""
    return list(_RUNNING)


def settle_at_exit(code: int, wait_ms: int = 30000) -> int:
    """The end of the GUI (after the event loop): cancel the workers still running and wait
    for them; each stops at its next progress report. A worker that does not stop within
    ``wait_ms`` (inside a long call that reports nothing) would be destroyed running by the
    interpreter's shutdown, which aborts the process: then exit at once with ``code``
    (:func:`core.runtime.signals.exit_now`). Returns ``code`` otherwise."""
    import time

    deadline = time.monotonic() + wait_ms / 1000.0
    workers = running_workers()  # (finished ones leave the set in the event loop, now over)
    for worker in workers:
        worker.cancel()
    for worker in workers:
        worker.wait(max(0, int(1000 * (deadline - time.monotonic()))))
    if not all(worker.isFinished() for worker in workers):
        from core.runtime.signals import exit_now

        exit_now(code)
    return code


def error_message(exc: BaseException) -> str:
    """A one-line message for the user: the text of data/argument errors, type + text otherwise."""
    if isinstance(exc, (ValueError, OSError)):
        text = str(exc) or type(exc).__name__
    else:
        text = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
    return " ".join(text.split())


def _accepts_progress(fn: Callable[..., Any], name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


class Worker(QThread):
    """Run ``fn(*args, **kwargs)`` in a thread; report progress, result, error or cancellation.

    Parameters
    ----------
    fn : callable
        The computation. If it accepts a keyword named ``progress_arg`` (default ``"progress"``)
        it receives a ``progress(fraction, message)`` callback.
    *args, **kwargs
        Passed to ``fn``.
    progress_arg : str or None
        Name of the progress keyword of ``fn``; None never passes one.

    Signals
    -------
    progress(float, str)
        Fraction in [0, 1] and a message, as reported by ``fn``.
    succeeded(object)
        The return value of ``fn``.
    failed(str)
        A one-line message (the traceback goes to stderr for unexpected exception types).
    cancelled()
        ``fn`` stopped because :meth:`cancel` was called.
    done()
        Emitted last, after exactly one of succeeded/failed/cancelled.
    """

    progress = Signal(float, str)
    succeeded = Signal(object)
    failed = Signal(str)
    cancelled = Signal()
    done = Signal()

    def __init__(self, fn: Callable[..., Any], *args: Any, progress_arg: str | None = "progress",
                 parent: QObject | None = None, **kwargs: Any):
        super().__init__(parent)
        self.fn = fn
        self.args = args
        self.kwargs = kwargs
        self.progress_arg = progress_arg
        self.result: Any = None
        self.error: str | None = None
        self.was_cancelled = False
        self._cancel = threading.Event()
        self.finished.connect(self._forget)

    def start(self, *args: Any) -> None:  # noqa: D102 - QThread.start
        _RUNNING.add(self)
        super().start(*args)

    def cancel(self) -> None:
        """Ask the computation to stop at its next progress report."""
        self._cancel.set()

    @property
    def cancel_requested(self) -> bool:
        return self._cancel.is_set()

    def _report(self, fraction: float, message: str = "") -> None:
        if self._cancel.is_set():
            raise Cancelled()
        self.progress.emit(float(fraction), str(message))

    def run(self) -> None:  # runs in the worker thread
        kwargs = dict(self.kwargs)
        if self.progress_arg and _accepts_progress(self.fn, self.progress_arg):
            kwargs[self.progress_arg] = self._report
        try:
            if self._cancel.is_set():
                raise Cancelled()
            self.result = self.fn(*self.args, **kwargs)
        except Cancelled:
            self.was_cancelled = True
            self.cancelled.emit()
        except Exception as exc:  # noqa: BLE001 - every error is shown, none crashes the GUI
            if not isinstance(exc, (ValueError, OSError)):
                traceback.print_exc(file=sys.stderr)
            self.error = error_message(exc)
            self.failed.emit(self.error)
        else:
            self.succeeded.emit(self.result)
        self.done.emit()

    def _forget(self) -> None:
        _RUNNING.discard(self)


class DialogTask(QObject):
    """One long job at a time in a :class:`Worker`, behind a modal progress dialog with Cancel.

    ``start(fn, *args, **kwargs)`` runs ``fn`` (given ``progress=``) unless a job is running;
    the outcome arrives as ``succeeded(result)``, ``failed(message)`` or ``cancelled()``, after
    the dialog is closed. Without a dialog (``show_dialog=False``: tests, scripts) the job runs
    the same way. Used by *Place models automatically* and *Open second image*.
    """

    succeeded = Signal(object)
    failed = Signal(str)
    cancelled = Signal()

    def __init__(self, title: str, label: str, parent=None):
        super().__init__(parent)
        self.title, self.label = title, label
        self.worker: Worker | None = None
        self.dialog = None
        self._parent = parent

    @property
    def is_running(self) -> bool:
        return self.worker is not None

    def start(self, fn: Callable[..., Any], *args: Any, show_dialog: bool = True,
              **kwargs: Any) -> bool:
        if self.worker is not None:
            return False
        self.worker = Worker(fn, *args, **kwargs)
        # The worker emits from its own thread: queued connections to this object's slots
        # deliver the outcome in the GUI thread (a lambda has no thread affinity of its own)
        queued = Qt.ConnectionType.QueuedConnection
        self.worker.succeeded.connect(self._on_succeeded, queued)
        self.worker.failed.connect(self._on_failed, queued)
        self.worker.cancelled.connect(self._on_cancelled, queued)
        if show_dialog:
            from PySide6.QtWidgets import QProgressDialog

            self.dialog = QProgressDialog(self.label, "Cancel", 0, 100, self._parent)
            self.dialog.setWindowTitle(self.title)
            self.dialog.setWindowModality(Qt.WindowModality.WindowModal)
            self.dialog.setMinimumDuration(0)
            self.dialog.canceled.connect(self.cancel)
            self.worker.progress.connect(self._on_progress)
        self.worker.start()
        return True

    def cancel(self) -> None:
        if self.worker is not None:
            self.worker.cancel()

    def wait(self, msecs: int = 60000) -> bool:
        return self.worker.wait(msecs) if self.worker is not None else True

    def _on_progress(self, fraction: float, message: str) -> None:
        dialog = self.dialog
        if dialog is None:
            return
        if message:
            dialog.setLabelText(f"{self.label}\n{message}")
        # last: a modal dialog's setValue processes events, which may deliver the end of the
        # job and close the dialog (self.dialog is None afterwards)
        dialog.setValue(int(100 * fraction))

    @Slot(object)
    def _on_succeeded(self, result: Any) -> None:
        self._finish(self.succeeded, result)

    @Slot(str)
    def _on_failed(self, message: str) -> None:
        self._finish(self.failed, message)

    @Slot()
    def _on_cancelled(self) -> None:
        self._finish(self.cancelled)

    def _finish(self, signal, *args) -> None:
        self.worker = None
        if self.dialog is not None:
            self.dialog.canceled.disconnect(self.cancel)
            self.dialog.close()
            self.dialog = None
        signal.emit(*args)


class LatestWinsRunner(QObject):
    """Run the newest of a stream of requests; drop stale ones and their results.

    ``submit(fn)`` with ``fn(progress) -> result``. At most one request runs at a time and at
    most one waits; a newer submission replaces the waiting one and cancels the running one at
    its next progress report. ``result`` is emitted only for the newest submission (the
    generation number it was submitted with is passed along); errors likewise.

    Signals
    -------
    result(object, int)
        Result of the newest request and its generation number.
    failed(str, int)
        One-line error message of the newest request and its generation number.
    busy(bool)
        True when work starts while idle, False when the runner becomes idle.
    """

    result = Signal(object, int)
    failed = Signal(str, int)
    busy = Signal(bool)

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self.generation = 0
        self._running: Worker | None = None
        self._running_generation = -1
        self._pending: tuple[Callable[..., Any], int] | None = None
        self.n_started = 0
        self.n_dropped = 0

    @property
    def is_busy(self) -> bool:
        return self._running is not None or self._pending is not None

    def submit(self, fn: Callable[[Callable[[float, str], None]], Any]) -> int:
        """Queue ``fn`` as the newest request; return its generation number."""
        self.generation += 1
        if self._pending is not None:
            self.n_dropped += 1
        self._pending = (fn, self.generation)
        if self._running is None:
            self.busy.emit(True)
            self._start_pending()
        else:
            self._running.cancel()
        return self.generation

    def cancel(self) -> None:
        """Drop the waiting request and stop the running one (no result is delivered)."""
        self.generation += 1
        self._pending = None
        if self._running is not None:
            self._running.cancel()

    def wait(self, msecs: int = 30000) -> bool:
        """Block until the running worker ends (for shutdown and tests)."""
        if self._running is not None:
            return self._running.wait(msecs)
        return True

    def _start_pending(self) -> None:
        fn, generation = self._pending  # type: ignore[misc]
        self._pending = None
        worker = Worker(_call_with_progress, fn, progress_arg="progress", parent=None)
        self._running, self._running_generation = worker, generation
        worker.succeeded.connect(self._on_succeeded)
        worker.failed.connect(self._on_failed)
        worker.done.connect(self._on_done)
        self.n_started += 1
        worker.start()

    def _on_succeeded(self, value: object) -> None:
        if self._running_generation == self.generation:
            self.result.emit(value, self._running_generation)
        else:
            self.n_dropped += 1

    def _on_failed(self, message: str) -> None:
        if self._running_generation == self.generation:
            self.failed.emit(message, self._running_generation)

    def _on_done(self) -> None:
        worker = self._running
        self._running = None
        if worker is not None:
            worker.wait()
        if self._pending is not None:
            self._start_pending()
        else:
            self.busy.emit(False)


def _call_with_progress(fn: Callable[[Callable[[float, str], None]], Any], progress) -> Any:
    return fn(progress)
