"""Worker threads: result, error, cancellation, and the latest-edit-wins runner."""

from __future__ import annotations

import threading

import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from app.workers import LatestWinsRunner, Worker  # noqa: E402


def _square(x, progress=None):
    for i in range(3):
        if progress:
            progress(i / 3, f"step {i}")
    return x * x


def test_worker_delivers_result_and_progress(qtbot):
    worker = Worker(_square, 7)
    seen, results = [], []
    worker.progress.connect(lambda f, m: seen.append((f, m)))
    worker.succeeded.connect(results.append)
    with qtbot.waitSignal(worker.done, timeout=5000):
        worker.start()
    qtbot.waitUntil(lambda: results == [49], timeout=5000)
    worker.wait()
    assert worker.result == 49 and worker.error is None
    assert [f for f, _ in seen] == pytest.approx([0, 1 / 3, 2 / 3])


def test_many_emits_do_not_exhaust_true(qtbot):
    """Regression: PySide6 6.12.0 emit() leaks a reference to True per call (app/qtfix.py)."""
    import sys

    from PySide6.QtCore import QObject, Signal

    import app  # noqa: F401 - installs the guard

    class Emitter(QObject):
        ping = Signal()

    emitter = Emitter()
    emitter.ping.connect(lambda: None)
    for _ in range(20000):          # more than True's natural reference count
        emitter.ping.emit()
    assert sys.getrefcount(True) > 1000


def test_worker_reports_value_error_as_one_line(qtbot):
    def bad():
        raise ValueError("points must be (P, 3),\n got (4, 2)")

    worker = Worker(bad)
    with qtbot.waitSignal(worker.failed, timeout=5000) as blocker:
        worker.start()
    assert blocker.args == ["points must be (P, 3), got (4, 2)"]
    worker.wait()


def test_worker_cancel_stops_at_next_progress(qtbot):
    release = threading.Event()
    calls = []

    def slow(progress):
        for i in range(1000):
            progress(i / 1000, "")
            calls.append(i)
            release.wait(0.01)
        return "finished"

    worker = Worker(slow)
    worker.start()
    qtbot.waitUntil(lambda: len(calls) > 2, timeout=5000)
    with qtbot.waitSignal(worker.cancelled, timeout=5000):
        worker.cancel()
    worker.wait()
    assert worker.was_cancelled and worker.result is None and len(calls) < 1000


def test_latest_wins_delivers_only_newest(qtbot):
    runner = LatestWinsRunner()
    gate = threading.Event()
    results = []
    runner.result.connect(lambda value, gen: results.append((value, gen)))

    def job(value, block):
        def fn(progress):
            if block:
                gate.wait(5)
            progress(1.0, "")
            return value
        return fn

    runner.submit(job("first", True))      # runs, will be cancelled at its progress call
    runner.submit(job("second", False))    # waits, then replaced
    gen = runner.submit(job("third", False))
    gate.set()
    qtbot.waitUntil(lambda: not runner.is_busy, timeout=5000)
    assert results == [("third", gen)]
    assert runner.n_started == 2  # "second" never started
    runner.wait()


def test_latest_wins_error_keeps_running(qtbot):
    runner = LatestWinsRunner()
    errors, results = [], []
    runner.failed.connect(lambda msg, gen: errors.append(msg))
    runner.result.connect(lambda value, gen: results.append(value))

    def bad(progress):
        raise ValueError("need at least 3 points")

    runner.submit(bad)
    qtbot.waitUntil(lambda: not runner.is_busy, timeout=5000)
    runner.submit(lambda progress: 5)
    qtbot.waitUntil(lambda: not runner.is_busy, timeout=5000)
    assert errors == ["need at least 3 points"] and results == [5]


@pytest.mark.parametrize("outcome", ["succeeded", "failed", "cancelled"])
def test_dialog_task_delivers_its_outcome_in_the_gui_thread(qtbot, outcome):
    """DialogTask's outcome signals are emitted from its own (GUI-thread) slots, whichever
    thread the worker finished in, so receivers may touch widgets."""
    from app.workers import DialogTask
    from core.runtime.progress import Cancelled

    gui_thread = threading.current_thread()

    def job(progress=None):
        assert threading.current_thread() is not gui_thread  # the job runs in the worker
        if outcome == "failed":
            raise ValueError("bad input")
        if outcome == "cancelled":
            raise Cancelled()
        return 5

    task = DialogTask("Title", "Working")
    delivered = []
    getattr(task, outcome).connect(lambda *args: delivered.append(
        (threading.current_thread() is gui_thread, args)))
    with qtbot.waitSignal(getattr(task, outcome), timeout=5000):
        assert task.start(job, show_dialog=False)
    assert delivered and delivered[0][0] is True
    assert not task.is_running
    if outcome == "succeeded":
        assert delivered[0][1] == (5,)
    elif outcome == "failed":
        assert "bad input" in delivered[0][1][0]
