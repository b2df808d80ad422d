"""One repaint of the window per edit while its refit runs.

Each repaint of a window that holds an OpenGL widget (the 3D view) is a composition of the
whole window; on a software OpenGL stack (llvmpipe under Xvfb, remote desktops) one costs
~20-30 ms. A click used to repaint the window several times before its refit's result was
shown (the point count, the cursor read-out, the fit panel...), each composition delaying the
result and taking CPU from the refit. :class:`PaintGate` holds the window's update requests
from the edit until its refit's result is applied (at most ``HOLD_S``), then lets one
repaint show everything. Qt keeps the dirty regions meanwhile; nothing is lost.
"""

from __future__ import annotations

import time

from PySide6.QtCore import QCoreApplication, QEvent, QObject, QTimer
from PySide6.QtWidgets import QWidget

HOLD_S = 0.05       # longest hold: a slow fit still shows the edit itself this soon


class PaintGate(QObject):
    """Holds ``window``'s update requests while ``refit`` (an :class:`app.refit.RefitController`)
    has a result pending for the newest edit."""

    def __init__(self, window: QWidget, refit):
        super().__init__(window)
        self.window = window
        self.pending = False               # a refit was submitted, its result not applied yet
        self._held_since: float | None = None
        self._let_through = False           # the request release() posted: not held again
        self._timer = QTimer(self)
        self._timer.setSingleShot(True)
        self._timer.timeout.connect(self.release)
        refit.submitted.connect(self._on_submitted)
        refit.applied.connect(self._on_done)
        refit.failed.connect(self._on_done)
        refit.busy.connect(lambda busy: None if busy else self._on_done())
        window.installEventFilter(self)

    def _on_submitted(self) -> None:
        self.pending = True

    def _on_done(self, *_args) -> None:
        self.pending = False
        self.release()

    def release(self) -> None:
        """Let a held repaint happen now (Qt posts no new request while one is outstanding)."""
        self._timer.stop()
        if self._held_since is not None:
            self._held_since = None
            self._let_through = True
            QCoreApplication.postEvent(self.window, QEvent(QEvent.Type.UpdateRequest))

    def eventFilter(self, obj, event) -> bool:  # noqa: N802 - Qt API
        if obj is not self.window or event.type() != QEvent.Type.UpdateRequest:
            return False
        if self._let_through:
            self._let_through = False
            return False
        if self.pending:
            now = time.perf_counter()
            if self._held_since is None:
                self._held_since = now
                self._timer.start(int(1000 * HOLD_S))
                return True
            if now - self._held_since < HOLD_S:
                return True
        return False
