"""Tool choice, window/level presets, point and placement actions of the Segment side panel."""

from __future__ import annotations

from PySide6.QtWidgets import QComboBox, QGridLayout, QHBoxLayout, QLabel, QPushButton, QVBoxLayout, QWidget

from app.views.slice_view import TOOLS

WINDOW_PRESETS = {
    "Auto (1-99.5 %)": None,
    "Full range": "full",
    "Grey/white contrast": "contrast",
    "Bright": "bright",
}


class ToolsPanel(QWidget):
    """Tool choice, window/level presets and point/placement actions."""

    def __init__(self, window):
        super().__init__(window)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        row = QHBoxLayout()
        self.tool_buttons = {}
        for tool in TOOLS:
            action = window.tools.actions[tool]
            button = QPushButton(action.text().replace("&", ""))
            button.setCheckable(True)
            button.setChecked(action.isChecked())
            button.clicked.connect(action.trigger)
            action.toggled.connect(button.setChecked)
            row.addWidget(button)
            self.tool_buttons[tool] = button
        layout.addLayout(row)
        wl = QHBoxLayout()
        wl.addWidget(QLabel("Window/level"))
        self.presets = QComboBox()
        self.presets.addItems(list(WINDOW_PRESETS))
        self.presets.activated.connect(lambda i: window.apply_window_preset(self.presets.itemText(i)))
        wl.addWidget(self.presets, 1)
        layout.addLayout(wl)
        grid = QGridLayout()
        buttons = [("Place here", "place-here"), ("Place automatically", "auto-place"),
                   ("Reset pose", "reset-pose"), ("Reset views", "reset-views"),
                   ("Clear slice", "clear-slice"), ("Clear all", "clear-points")]
        for i, (text, action_id) in enumerate(buttons):
            action = window.registry[action_id]
            button = QPushButton(text)
            button.setToolTip(action.toolTip() or action.text())
            button.clicked.connect(action.trigger)
            action.changed.connect(lambda b=button, a=action: b.setEnabled(a.isEnabled()))
            button.setEnabled(action.isEnabled())
            grid.addWidget(button, i // 2, i % 2)
        layout.addLayout(grid)
        self.count = QLabel()           # shown in the side panel's drawing bar (app.panels.side)
        self.state = window.state
        self.state.events.points.connect(self._count)
        self._count()

    def _count(self) -> None:
        pts = self.state.active.points
        self.count.setText(f"{len(pts)} contour point(s) on {pts.n_slices()} slice(s)")
