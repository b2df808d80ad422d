"""The builder's stage runner: one worker at a time, a plan of stages, progress and Cancel.

:class:`StageRunner` (no widgets) runs jobs in :class:`app.workers.Worker` threads: a single
job (loading meshes, an evaluation) or a *plan* of build stages, asking for each stage's job
only when the stage before it has been stored, since a stage's inputs are the previous stage's
result (``core.build.stages.StagedBuild.job``). Cancel stops the running job at its next progress
report and drops the rest of the plan; completed stages stay with the receiver.

:class:`RunBox` is the "5. Build" group: Build / Cancel, the progress bar, each stage's state
(not run / running / done / out of date) and the status line.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

from PySide6.QtCore import QObject, Qt, Signal
from PySide6.QtWidgets import (
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QProgressBar,
    QPushButton,
    QVBoxLayout,
    QWidget,
)

from app.workers import Worker
from core.build.stages import STAGES

STAGE_TITLES = {"load": "Loading meshes", "correspondence": "Correspondence",
                "alignment": "Alignment", "model": "Model", "evaluation": "Evaluation",
                "labels": "Label maps"}
# One job of a plan: the function to run in the worker (it gets ``progress=``) and the key the
# result is stored under.
Job = tuple[Callable[..., Any], Any]


class StageRunner(QObject):
    """Runs jobs one at a time in worker threads.

    Signals
    -------
    started(str)
        A job of that stage started.
    progress(str, float, str)
        Stage, fraction in [0, 1], message.
    succeeded(str, object, object, float)
        Stage, result, the key it was started with, seconds.
    failed(str, str)
        Stage and a one-line message.
    cancelled(str)
    idle(str)
        The last job ended: "completed", "failed" or "cancelled".
    busy_changed(bool)
    """

    started = Signal(str)
    progress = Signal(str, float, str)
    succeeded = Signal(str, object, object, float)
    failed = Signal(str, str)
    cancelled = Signal(str)
    idle = Signal(str)
    busy_changed = Signal(bool)

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self.worker: Worker | None = None
        self.stage: str | None = None
        self.plan: list[str] = []
        self._next_job: Callable[[str], Job] | None = None
        self._started = 0.0
        self._cancel_requested = 0.0
        self.last_cancel_latency: float | None = None
        self.closed = False
        self._announced = False  # busy_changed(True) was emitted

    @property
    def busy(self) -> bool:
        return self.worker is not None

    def run(self, stage: str, fn: Callable[..., Any], *args: Any, key: Any = None,
            **kwargs: Any) -> None:
        """Run one job ``fn(*args, progress=..., **kwargs)``."""
        self.plan = []
        self._start(stage, Worker(fn, *args, **kwargs), key)

    def run_plan(self, stages: list[str], next_job: Callable[[str], Job]) -> None:
        """Run ``stages`` in order; ``next_job(stage)`` gives each one's job when it is due
        (after the previous stage's ``succeeded`` was handled)."""
        self.plan = list(stages)
        self._next_job = next_job
        self._run_next()

    def _run_next(self) -> None:
        if not self.plan or self.closed:
            return
        stage = self.plan.pop(0)
        try:
            fn, key = self._next_job(stage)
        except ValueError as exc:  # the settings changed into something unreadable
            self.plan = []
            self.failed.emit(stage, str(exc))
            self._end("failed")
            return
        self._start(stage, Worker(fn), key)

    def _start(self, stage: str, worker: Worker, key: Any) -> None:
        worker.stage, worker.key = stage, key
        self.worker, self.stage = worker, stage
        self._started = time.monotonic()
        # bound methods of this GUI-thread object: the calls are queued to the GUI thread
        worker.progress.connect(self._on_progress)
        worker.succeeded.connect(self._on_succeeded)
        worker.failed.connect(self._on_failed)
        worker.cancelled.connect(self._on_cancelled)
        worker.done.connect(self._on_done)
        self.started.emit(stage)
        if not self._announced:
            self._announced = True
            self.busy_changed.emit(True)
        worker.start()

    def cancel(self) -> None:
        """Stop the running job at its next progress report; drop the rest of the plan."""
        if self.worker is not None:
            self.plan = []
            self._cancel_requested = time.monotonic()
            self.worker.cancel()

    def close(self, wait_ms: int = 5000) -> None:
        """Cancel, wait for the worker and ignore its late signals (idempotent)."""
        self.closed = True
        self.plan = []
        worker = self.worker
        if worker is not None:
            worker.cancel()
            worker.wait(wait_ms)
        self.worker = None

    # -- worker signals ------------------------------------------------------------------

    def _on_progress(self, fraction: float, message: str) -> None:
        if self.sender() is self.worker:
            self.progress.emit(self.stage, fraction, message)

    def _on_succeeded(self, result: Any) -> None:
        worker = self.sender()
        if self.closed or worker is not self.worker:
            return
        self.succeeded.emit(worker.stage, result, worker.key, time.monotonic() - self._started)

    def _on_failed(self, message: str) -> None:
        if self.sender() is self.worker:
            self.plan = []
            self.failed.emit(self.worker.stage, message)

    def _on_cancelled(self) -> None:
        if self.sender() is self.worker:
            self.plan = []
            self.last_cancel_latency = time.monotonic() - self._cancel_requested
            self.cancelled.emit(self.worker.stage)

    def _on_done(self) -> None:
        worker = self.worker
        if worker is None or self.sender() is not worker:
            return
        worker.wait()
        self.worker, self.stage = None, None
        if self.plan and not self.closed:
            self._run_next()
            return
        self._end("cancelled" if worker.was_cancelled else
                  "failed" if worker.error is not None else "completed")

    def _end(self, outcome: str) -> None:
        self.idle.emit(outcome)
        if self._announced:
            self._announced = False
            self.busy_changed.emit(False)


class RunBox(QGroupBox):
    """"5. Build": Build and Cancel, progress, each stage's state and the status line."""

    def __init__(self, parent: QWidget | None = None):
        super().__init__("5. Build", parent)
        self.build_button = QPushButton("Build model")
        self.build_button.setObjectName("build")
        self.build_button.setToolTip("Run the stages whose inputs changed (completed stages "
                                     "are reused).")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setObjectName("cancel")
        self.cancel_button.setToolTip("Stop the running step (within about a second). "
                                      "Completed stages are kept.")
        self.progress_bar = QProgressBar()
        self.progress_bar.setRange(0, 1000)
        self.progress_bar.setTextVisible(True)
        self.progress_bar.setFormat("")
        self.status_label = QLabel("")
        self.status_label.setObjectName("status")
        self.status_label.setWordWrap(True)
        self.status_label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.stage_labels = {s: QLabel("—") for s in STAGES}
        self.safeguard_label = QLabel("")
        self.safeguard_label.setObjectName("safeguard")
        self.safeguard_label.setWordWrap(True)
        self.safeguard_label.setTextInteractionFlags(Qt.TextSelectableByMouse)
        self.safeguard_label.setToolTip("The correspondence safeguard keeps the remesh and each "
                                        "refinement pass only where the model's leave-one-out "
                                        "error against the raw inputs says it helps")
        self.safeguard_label.hide()
        layout = QVBoxLayout(self)
        row = QHBoxLayout()
        row.addWidget(self.build_button, 1)
        row.addWidget(self.cancel_button)
        layout.addLayout(row)
        layout.addWidget(self.progress_bar)
        stage_form = QFormLayout()
        for s in STAGES:
            stage_form.addRow(STAGE_TITLES[s], self.stage_labels[s])
        layout.addLayout(stage_form)
        layout.addWidget(self.safeguard_label)
        layout.addWidget(self.status_label)

    def job_started(self, stage: str) -> None:
        self.progress_bar.setValue(0)
        self.progress_bar.setFormat(f"{STAGE_TITLES[stage]}: %p%")
        self.set_status(f"{STAGE_TITLES[stage]}…")

    def job_progress(self, stage: str, fraction: float, message: str) -> None:
        self.progress_bar.setValue(int(round(1000 * fraction)))
        if message:
            self.status_label.setStyleSheet("")
            self.status_label.setText(f"{STAGE_TITLES[stage]}: {message}")

    def job_ended(self, outcome: str) -> None:
        """``outcome`` of :attr:`StageRunner.idle`."""
        self.progress_bar.setFormat("cancelled" if outcome == "cancelled" else "%p%")
        if outcome == "completed":
            self.progress_bar.setValue(1000)

    def show_stages(self, status: Mapping[str, str], seconds: Mapping[str, float],
                    running: str | None) -> None:
        """``status`` per stage from ``core.build.stages.StageCache.status``."""
        for stage in STAGES:
            label = self.stage_labels[stage]
            if running == stage:
                label.setText("running…")
            elif status[stage] == "done":
                label.setText(f"done ({seconds[stage]:.1f} s)")
            elif status[stage] == "out of date":
                label.setText(f"out of date (done in {seconds[stage]:.1f} s)")
            else:
                label.setText("not run")

    def show_safeguard(self, lines: list[str]) -> None:
        """The safeguard's decisions of the last correspondence (hidden when there are none)."""
        self.safeguard_label.setText("\n".join(f"Safeguard: {line}" for line in lines))
        self.safeguard_label.setVisible(bool(lines))

    def set_status(self, text: str, error: bool = False) -> None:
        self.status_label.setStyleSheet("color: #b00020;" if error else "")
        self.status_label.setText(text)
