"""The 2x2 view grid of the segmentation workspace: axial, sagittal, coronal and 3D."""

from __future__ import annotations

from PySide6.QtCore import Qt, Signal
from PySide6.QtWidgets import QApplication, QGridLayout, QLabel, QWidget

from app.model.state import FRAME_NAMES, WorkspaceState
from app.views.slice_view import SliceView


class SegmentWorkspace(QWidget):
    """The 2x2 view grid of the segmentation workspace.

    The 3D view can be created after the first paint (``defer_3d``): importing pyvista's
    plotting stack and creating the OpenGL context take about two seconds, and the slice
    views are usable meanwhile.
    """

    volume_view_created = Signal()

    def __init__(self, state: WorkspaceState, parent: QWidget | None = None,
                 with_3d: bool = True, defer_3d: bool = False):
        super().__init__(parent)
        self.state = state
        self.views = {name: SliceView(state, name) for name in FRAME_NAMES}
        self.volume_view = None
        self._layout = QGridLayout(self)
        self._layout.setContentsMargins(2, 2, 2, 2)
        self._layout.setSpacing(3)
        self._layout.addWidget(self.views["axial"], 0, 0)
        self._layout.addWidget(self.views["sagittal"], 0, 1)
        self._layout.addWidget(self.views["coronal"], 1, 0)
        self._placeholder = QLabel("Loading the 3D view…" if with_3d else "3D view disabled")
        self._placeholder.setAlignment(Qt.AlignmentFlag.AlignCenter)
        self._placeholder.setStyleSheet("background: #15151c; color: #aaa;")
        self._layout.addWidget(self._placeholder, 1, 1)
        for i in range(2):
            self._layout.setRowStretch(i, 1)
            self._layout.setColumnStretch(i, 1)
        if with_3d and not defer_3d:
            self.create_volume_view()

    def create_volume_view(self):
        """Create the 3D view in the bottom-right cell (once); returns it."""
        if self.volume_view is None:
            from app.views.volume_view import VolumeView

            self.volume_view = VolumeView(self.state)
            self._layout.replaceWidget(self._placeholder, self.volume_view)
            self._placeholder.hide()
            self._placeholder.setParent(None)
            self._placeholder.deleteLater()
            self.volume_view_created.emit()
        return self.volume_view

    def reset_views(self) -> None:
        for view in self.views.values():
            view.reset_view()
        if self.volume_view is not None:
            self.volume_view.reset_camera()
            self.volume_view.plotter.render()

    def render_now(self) -> None:
        """Flush pending view updates (before a screenshot)."""
        app = QApplication.instance()
        app.processEvents()
        if self.volume_view is not None:
            self.volume_view.flush()
        for view in self.views.values():
            view.repaint()
        app.processEvents()
