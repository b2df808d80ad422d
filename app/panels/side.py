"""The Segment tab's side panel: one dock holding the tool, fit and factor panels in boxes,
and, pinned below them where no scrolling hides it, what a user needs while drawing."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtGui import QAction
from PySide6.QtWidgets import (
    QDockWidget,
    QFrame,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QScrollArea,
    QToolButton,
    QVBoxLayout,
    QWidget,
)


def _action_button(action: QAction, text: str) -> QToolButton:
    """A compact button that triggers ``action`` and follows its enabled state."""
    button = QToolButton()
    button.setText(text)
    button.setToolTip(action.toolTip() or action.text())
    button.clicked.connect(action.trigger)
    action.changed.connect(lambda: button.setEnabled(action.isEnabled()))
    button.setEnabled(action.isEnabled())
    return button


class DrawingBar(QFrame):
    """The point count, Undo/Redo and the fit read-out, always in view (issue 29): the
    panels above scroll, this does not."""

    def __init__(self, count: QLabel, fit_result: QLabel, undo: QAction, redo: QAction,
                 parent: QWidget | None = None):
        super().__init__(parent)
        self.setObjectName("drawing-bar")
        self.setFrameShape(QFrame.Shape.StyledPanel)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(6, 4, 6, 4)
        row = QHBoxLayout()
        count.setWordWrap(False)
        row.addWidget(count, 1)
        self.undo_button = _action_button(undo, "Undo")
        self.redo_button = _action_button(redo, "Redo")
        row.addWidget(self.undo_button)
        row.addWidget(self.redo_button)
        layout.addLayout(row)
        fit_result.setWordWrap(True)
        layout.addWidget(fit_result)


class SidePanel(QDockWidget):
    """A dock of titled boxes, ``sections`` = [(title, widget, stretch), ...] top to bottom,
    scrolling when the window is short; ``footer`` (e.g. a :class:`DrawingBar`) stays below."""

    def __init__(self, sections: list[tuple[str, QWidget, int]], parent: QWidget | None = None,
                 footer: QWidget | None = None):
        super().__init__("Segmentation", parent)
        self.setObjectName("segmentation-dock")
        self.setFeatures(QDockWidget.DockWidgetFeature.DockWidgetMovable)
        panel = QWidget()
        layout = QVBoxLayout(panel)
        layout.setContentsMargins(2, 2, 2, 2)
        self.boxes: dict[str, QGroupBox] = {}
        for title, widget, stretch in sections:
            box = QGroupBox(title)
            box_layout = QVBoxLayout(box)
            box_layout.setContentsMargins(2, 2, 2, 2)
            box_layout.addWidget(widget)
            layout.addWidget(box, stretch)
            self.boxes[title] = box
        # in a scroll area, so that a small window (800x600) is not forced taller by the panel
        scroll = QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        scroll.setWidget(panel)
        self.panel = panel
        self.scroll = scroll
        self.footer = footer
        holder = QWidget()
        outer = QVBoxLayout(holder)
        outer.setContentsMargins(0, 0, 0, 0)
        outer.setSpacing(2)
        outer.addWidget(scroll, 1)
        if footer is not None:
            outer.addWidget(footer)
        self.setWidget(holder)
        self.setMinimumWidth(280)
