"""The main window's tabs: the Segment workspace and the model builder, created on first use.

Importing the builder and building its views takes a moment, so its tab holds a placeholder
until it is first shown.
"""

from __future__ import annotations

import importlib.util

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QLabel, QTabWidget, QWidget


def builder_available() -> bool:
    return importlib.util.find_spec("app.panels.builder") is not None


class WorkspaceTabs(QTabWidget):
    """Segment | Build model. ``segment_shown(bool)`` when the Segment tab (un)shows;
    ``use_model(path)`` when the builder hands over a model for segmentation."""

    segment_shown = Signal(bool)
    use_model = Signal(str)

    def __init__(self, segment: QWidget, parent: QWidget | None = None):
        super().__init__(parent)
        self.setDocumentMode(True)
        self.segment = segment
        self.builder = None
        self.addTab(segment, "Segment")
        self._placeholder = QLabel("Loading the model builder…")
        self._placeholder.setAlignment(Qt.AlignmentFlag.AlignCenter)
        if builder_available():
            self.addTab(self._placeholder, "Build model")
        self.currentChanged.connect(self._on_tab)

    def _on_tab(self, index: int) -> None:
        if self.widget(index) is self._placeholder:
            self.ensure_builder()
        self.segment_shown.emit(self.currentWidget() is self.segment)

    def prepare_builder(self) -> None:
        """Build the builder panel in the background of an idle GUI (after the first paint),
        without switching to it, so that the first switch to its tab is only a repaint."""
        if self.builder is None and self.indexOf(self._placeholder) >= 0:
            current = self.currentIndex()
            size = self.currentWidget().size()
            if self.ensure_builder() is None:
                return
            self.builder.resize(size)
            self.builder.grab()      # polish and lay out now (the first show costs ~0.3 s)
            self.blockSignals(True)
            self.setCurrentIndex(current)
            self.blockSignals(False)
            self.segment_shown.emit(self.currentWidget() is self.segment)

    def ensure_builder(self):
        """The builder panel, created (and its tab made current) on the first call."""
        if self.builder is not None:
            return self.builder
        try:
            from app.panels.builder import BuilderPanel
        except ImportError as exc:
            self._placeholder.setText(f"Model builder unavailable: {exc}")
            return None
        index = self.indexOf(self._placeholder)
        self.builder = BuilderPanel()
        self.builder.use_for_segmentation.connect(self.use_model)
        self.blockSignals(True)
        self.removeTab(index)
        self.insertTab(index, self.builder, "Build model")
        self.setCurrentIndex(index)
        self.blockSignals(False)
        self.segment_shown.emit(self.currentWidget() is self.segment)
        return self.builder

    def show_segment(self) -> None:
        self.setCurrentWidget(self.segment)
