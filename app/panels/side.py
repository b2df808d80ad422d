"""The Segment tab's side panel: one dock holding the tool, fit and factor panels in boxes."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtWidgets import QDockWidget, QGroupBox, QScrollArea, QVBoxLayout, QWidget


class SidePanel(QDockWidget):
    """A dock of titled boxes, ``sections`` = [(title, widget, stretch), ...] top to bottom."""

    def __init__(self, sections: list[tuple[str, QWidget, int]], parent: QWidget | None = None):
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
        self.setWidget(scroll)
        self.setMinimumWidth(280)
