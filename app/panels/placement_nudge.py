"""*Adjust automatic placement*: nudge the registration by hand, every structure together.

A small non-modal dialog (Edit > Adjust automatic placement…, offered after *Place models
automatically*): shift buttons along R/L, A/P, S/I and turn buttons about those axes, a step
for each, Undo, and the read-out of :meth:`app.placement.AutoPlacement.readout` (how far the
nudges moved the structures, the contour points' distance to the surfaces). The maths is
``core.registration.placement.nudged``; this is widgets and wiring only.
"""

from __future__ import annotations

from PySide6.QtWidgets import (
    QDialog,
    QDoubleSpinBox,
    QGridLayout,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QToolButton,
    QVBoxLayout,
)

AXES = (("R/L", 0), ("A/P", 1), ("S/I", 2))


class PlacementNudgeDialog(QDialog):
    """See the module docstring; ``window`` is the main window."""

    def __init__(self, window):
        super().__init__(window)
        self.setWindowTitle("Adjust automatic placement")
        self.window = window
        self.placement = window.auto_place
        layout = QVBoxLayout(self)
        steps = QHBoxLayout()
        self.shift_step = self._spin(" mm", 1.0, 0.1, 20.0)
        self.turn_step = self._spin("°", 1.0, 0.1, 20.0)
        steps.addWidget(QLabel("Step"))
        steps.addWidget(self.shift_step)
        steps.addWidget(self.turn_step)
        layout.addLayout(steps)
        grid = QGridLayout()
        grid.addWidget(QLabel("Shift"), 0, 1, 1, 2)
        grid.addWidget(QLabel("Turn"), 0, 3, 1, 2)
        self.buttons: dict[tuple[str, int, int], QToolButton] = {}
        for row, (name, axis) in enumerate(AXES, start=1):
            grid.addWidget(QLabel(name), row, 0)
            for col, (kind, sign) in enumerate((("shift", -1), ("shift", 1), ("turn", -1),
                                                ("turn", 1)), start=1):
                button = QToolButton()
                button.setText("−" if sign < 0 else "+")
                button.setToolTip(f"{'Shift along' if kind == 'shift' else 'Turn about'} "
                                  f"{name} by {'minus' if sign < 0 else 'plus'} one step")
                button.clicked.connect(lambda _=False, k=kind, a=axis, s=sign: self.step(k, a, s))
                grid.addWidget(button, row, col)
                self.buttons[(kind, axis, sign)] = button
        layout.addLayout(grid)
        self.undo_button = QPushButton("Undo nudge")
        self.undo_button.clicked.connect(self.placement.undo_nudge)
        layout.addWidget(self.undo_button)
        self.readout = QLabel()
        self.readout.setObjectName("nudge-readout")
        self.readout.setWordWrap(True)
        self.readout.setMinimumWidth(280)
        layout.addWidget(self.readout)
        self.placement.nudged.connect(self.refresh)
        self.placement.finished.connect(lambda _message: self.refresh())
        window.state.events.surface.connect(self.refresh)
        self.refresh()

    @staticmethod
    def _spin(suffix: str, value: float, lo: float, hi: float) -> QDoubleSpinBox:
        spin = QDoubleSpinBox()
        spin.setRange(lo, hi)
        spin.setDecimals(1)
        spin.setSingleStep(0.5)
        spin.setValue(value)
        spin.setSuffix(suffix)
        return spin

    def step(self, kind: str, axis: int, sign: int) -> bool:
        """One nudge: shift along or turn about world axis ``axis`` by one step."""
        vector = [0.0, 0.0, 0.0]
        if kind == "shift":
            vector[axis] = sign * self.shift_step.value()
            done = self.placement.nudge(shift_mm=vector)
        else:
            vector[axis] = sign * self.turn_step.value()
            done = self.placement.nudge(rotation_deg=vector)
        if done:
            self.window.show_message(self.placement.readout())
            if len(self.window.state.active.points):
                self.window.schedule_refit()
        return done

    def refresh(self) -> None:
        if not self.isVisible() and self.readout.text():
            return                       # follows the structures only while shown
        placed = bool(self.placement.placed_structures()) and self.placement.transform is not None
        for button in self.buttons.values():
            button.setEnabled(placed)
        self.undo_button.setEnabled(self.placement.can_undo_nudge())
        self.readout.setText(self.placement.readout())


class PlacementNudge:
    """The window's feature ``"placement-nudge"``: *Edit > Adjust automatic placement…*
    (the dialog is made once, when first shown)."""

    def __init__(self, window):
        self.window = window
        self.dialog: PlacementNudgeDialog | None = None
        self.action = window.registry.add(
            "adjust-placement", "Adjust automatic placement…", self.show,
            tip="Shift or turn the automatic placement by hand, every structure together")
        window.registry.place("edit", "adjust-placement")

    def show(self) -> PlacementNudgeDialog:
        if self.dialog is None:
            self.dialog = PlacementNudgeDialog(self.window)
        self.dialog.show()
        self.dialog.refresh()
        self.dialog.raise_()
        return self.dialog
