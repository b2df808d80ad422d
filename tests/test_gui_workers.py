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


_EXIT_SCRIPT = """
import sys, time
from PySide6.QtWidgets import QApplication
from app.workers import Worker, settle_at_exit

app = QApplication([])
stoppable = Worker(lambda progress: [progress(0.0) or time.sleep(0.05) for _ in range(400)])
deaf = Worker(lambda: time.sleep(float(sys.argv[1])))  # reports nothing: Cancel cannot reach it
stoppable.start()
if float(sys.argv[1]) > 0:
    deaf.start()
time.sleep(0.2)
code = settle_at_exit(7, wait_ms=int(sys.argv[2]))
print("stoppable finished:", stoppable.isFinished(), flush=True)
sys.exit(code)
"""


@pytest.mark.parametrize("deaf_seconds, wait_ms, expected", [(0, 20000, "True"), (30, 300, None)])
def test_the_gui_ends_without_an_abort_while_a_worker_runs(deaf_seconds, wait_ms, expected):
    """At the end of the event loop ``settle_at_exit`` cancels the running workers and waits
    for them; one that reports nothing, and so cannot be cancelled, no longer aborts the
    process as the interpreter destroys its running thread ("QThread: Destroyed while thread
    is still running"): the process exits at once with the GUI's code."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", _EXIT_SCRIPT, str(deaf_seconds), str(wait_ms)],
                          capture_output=True, text=True, timeout=60,  # a hang guard
                          env=dict(os.environ, PYTHONPATH=str(root), QT_QPA_PLATFORM="offscreen"))
    assert proc.returncode == 7, proc.stderr[-2000:]
    assert "Destroyed while thread" not in proc.stderr
    if expected is not None:  # every worker stopped: the normal return
        assert f"stoppable finished: {expected}" in proc.stdout
    else:                     # the deaf one still ran: exited at once, before the print
        assert "stoppable finished" not in proc.stdout
