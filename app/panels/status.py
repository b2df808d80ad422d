"""The status bar's read-outs: the point under the cursor (or the crosshair) and the last fit."""

from __future__ import annotations

import numpy as np
from PySide6.QtWidgets import QLabel

from app.model.state import WorkspaceState


class CursorReadout(QLabel):
    """World position (RAS mm), voxel index and intensity under the cursor, else the crosshair."""

    def __init__(self, state: WorkspaceState):
        super().__init__()
        self.setObjectName("cursor-info")
        self.state = state
        self.hover: np.ndarray | None = None       # world point under the cursor, or None
        self.extra = lambda world: ""              # e.g. AC-PC coordinates, set by the window
        state.events.crosshair.connect(self.refresh)

    def on_hover(self, world) -> None:
        self.hover = None if world is None else np.asarray(world)
        self.refresh()

    def refresh(self) -> None:
        point = self.hover if self.hover is not None else self.state.crosshair
        text = self.state.describe(point)
        where = "cursor" if self.hover is not None else "crosshair"
        extra = self.extra(point) if text else ""
        self.setText((f"{where}  {text}" + (f"   {extra}" if extra else "")) if text else "")


class FitReadout(QLabel):
    """The last refit in one line: residual, iterations and edit-to-display time; or its error."""

    def __init__(self, state: WorkspaceState, refit):
        super().__init__()
        self.state = state
        refit.applied.connect(self._on_applied)
        refit.failed.connect(lambda message: self.setText("fit: " + message[:60]))
        refit.busy.connect(lambda busy: busy and self.setText("fitting…"))

    def _on_applied(self, result) -> None:
        self.setText(f"residual {result.residual_mm:.2f} mm, {result.n_iter} it, "
                     f"{1000 * self.state.active.fit_info.seconds:.0f} ms")


def status_readouts(window) -> tuple[CursorReadout, FitReadout]:
    """The status bar's permanent read-outs, wired: the cursor (world, voxel, value, AC-PC
    from the plan) and the last fit."""
    cursor = CursorReadout(window.state)
    fit = FitReadout(window.state, window.refit)
    cursor.extra = window.plan.acpc_text
    window.plan.planning.events.landmarks.connect(cursor.refresh)
    window.statusBar().addPermanentWidget(cursor, 1)
    window.statusBar().addPermanentWidget(fit)
    for view in window.workspace.views.values():
        view.hovered.connect(cursor.on_hover)
    return cursor, fit
