"""The main window: the segmentation workspace (and the model-builder tab).

Layout (ITK-SNAP-like): a 2x2 grid of the axial, sagittal and coronal slice views and the 3D
view, linked by one crosshair in world (RAS, mm) coordinates; a side panel with the tools,
the fit settings and read-out, and one slider per deformation factor; a status bar with the
world position, voxel index and intensity under the cursor.

Wiring (3D Slicer's Widget/Logic split): every number comes from ``core`` (slicing,
reconstruction, segmentation, I/O, sessions); the views and panels listen to one
:class:`app.state.SegmentationState`. Each point edit submits a refit to a
:class:`app.workers.LatestWinsRunner` (a worker thread; newest edit wins, stale results are
dropped), warm-started from the current fit. Every edit is also written to a recovery file,
offered at the next start if the program did not close normally.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QAction, QActionGroup, QKeySequence
from PySide6.QtWidgets import (QApplication, QComboBox, QDockWidget, QFileDialog, QGridLayout,
                               QGroupBox, QHBoxLayout, QLabel, QMainWindow, QMessageBox,
                               QPushButton, QTabWidget, QToolBar, QVBoxLayout,
                               QWidget)

from app import demo
from app.panels.factors import FactorsPanel
from app.panels.fit import FitPanel
from app.state import FRAME_NAMES, FitInfo, Points, SegmentationState
from app.views.slice_view import TOOLS, SliceView
from app.workers import LatestWinsRunner, error_message
from core.io import DataFileError, load_model, load_volume, save_mesh, save_points, save_volume

WINDOW_PRESETS = {
    "Auto (1-99.5 %)": None,
    "Full range": "full",
    "Grey/white contrast": "contrast",
    "Bright": "bright",
}

SHORTCUTS = [
    ("Ctrl+O", "Open image"), ("Ctrl+M", "Load model"), ("Ctrl+Shift+O", "Open session"),
    ("Ctrl+S", "Save session"), ("Ctrl+E", "Export label map, mesh and points"),
    ("Ctrl+Z", "Undo"), ("Ctrl+Shift+Z", "Redo"),
    ("Delete", "Remove the point under the cursor (else the last point)"),
    ("Page Up / Page Down, wheel", "Next / previous slice in the active view"),
    ("N / D / W", "Tool: navigate / draw contour / window-level"),
    ("P", "Place the model at the crosshair"), ("R", "Reset the views"),
    ("Left click (navigate)", "Move the crosshair"),
    ("Left click or drag (draw)", "Add contour points on the slice"),
    ("Ctrl+left click (draw)", "Delete the point under the cursor"),
    ("Shift+left drag", "Window/level"), ("Right drag / Ctrl+wheel", "Zoom"),
    ("Middle drag", "Pan"),
]


class SegmentWorkspace(QWidget):
    """The 2x2 view grid of the segmentation workspace.

    The 3D view can be created after the first paint (``defer_3d``): importing pyvista's
    plotting stack and creating the OpenGL context take about two seconds, and the slice
    views are usable meanwhile.
    """

    volume_view_created = Signal()

    def __init__(self, state: SegmentationState, parent: QWidget | None = None,
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


class ToolsPanel(QWidget):
    """Tool choice, window/level presets and point/placement actions."""

    def __init__(self, window: MainWindow):
        super().__init__(window)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        row = QHBoxLayout()
        self.tool_buttons = {}
        for tool in TOOLS:
            action = window.tool_actions[tool]
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
        buttons = [("Place here", window.act_place), ("Reset pose", window.act_reset_pose),
                   ("Clear slice", window.act_clear_slice), ("Clear all", window.act_clear_points),
                   ("Undo", window.act_undo), ("Redo", window.act_redo)]
        for i, (text, action) in enumerate(buttons):
            button = QPushButton(text)
            button.setToolTip(action.toolTip() or action.text())
            button.clicked.connect(action.trigger)
            action.changed.connect(lambda b=button, a=action: b.setEnabled(a.isEnabled()))
            button.setEnabled(action.isEnabled())
            grid.addWidget(button, i // 2, i % 2)
        layout.addLayout(grid)
        self.count = QLabel()
        layout.addWidget(self.count)
        window.state.points_changed.connect(self._count)
        self.state = window.state
        self._count()

    def _count(self) -> None:
        pts = self.state.points
        slices = len({(int(f), round(float(d), 3)) for f, d in zip(pts.frame, pts.depth)})
        self.count.setText(f"{len(pts)} contour point(s) on {slices} slice(s)")


class MainWindow(QMainWindow):
    """SSM Studio's main window (see the module docstring)."""

    refit_applied = Signal(object)         # FitResult applied to the state
    closed = Signal()

    def __init__(self, with_3d: bool = True, recovery: bool = True, defer_3d: bool = False):
        super().__init__()
        self.setWindowTitle("SSM Studio")
        self.setAcceptDrops(True)
        self.state = SegmentationState(self)
        self.session_path: Path | None = None
        self.active_view = "axial"
        self.last_fit = None
        self._edit_time: float | None = None
        self._hover: np.ndarray | None = None
        self._closing = False
        self.recovery_enabled = recovery
        self.unsaved = False
        self.refit_times: list[float] = []

        self.runner = LatestWinsRunner(self)
        self.runner.result.connect(self._on_refit_result)
        self.runner.failed.connect(self._on_refit_failed)
        self.runner.busy.connect(self._on_refit_busy)

        self._create_actions()
        self.workspace = SegmentWorkspace(self.state, with_3d=with_3d, defer_3d=defer_3d)
        self.fit_panel = FitPanel(self.state)
        self.factors_panel = FactorsPanel(self.state)
        self.tools_panel = ToolsPanel(self)
        self._create_menus()
        self._create_toolbar()
        self._create_side_panel()

        self.workspace.volume_view_created.connect(self._wire_volume_view)
        if self.workspace.volume_view is not None:
            self._wire_volume_view()
        self.factors_panel.factor_touched.connect(self._show_factor_region)
        self._factor_timer = QTimer(self)
        self._factor_timer.setSingleShot(True)
        self._factor_timer.setInterval(2500)
        self._factor_timer.timeout.connect(lambda: self._show_factor_region(-1))
        self.tabs = QTabWidget()
        self.tabs.setDocumentMode(True)
        self.tabs.addTab(self.workspace, "Segment")
        self.builder = None
        self._builder_placeholder = QLabel("Loading the model builder…")
        self._builder_placeholder.setAlignment(Qt.AlignmentFlag.AlignCenter)
        if _builder_available():
            self.tabs.addTab(self._builder_placeholder, "Build model")
        self.tabs.currentChanged.connect(self._on_tab)
        self.setCentralWidget(self.tabs)

        self.cursor_label = QLabel()
        self.cursor_label.setObjectName("cursor-info")
        self.fit_label = QLabel()
        self.statusBar().addPermanentWidget(self.cursor_label, 1)
        self.statusBar().addPermanentWidget(self.fit_label)

        for view in self.workspace.views.values():
            view.hovered.connect(self._on_hover)
            view.activated.connect(self._on_view_activated)
            view.message.connect(self.show_message)
        self.state.points_changed.connect(self._on_points_changed)
        self.state.crosshair_changed.connect(self._update_cursor_label)
        self.state.history_changed.connect(self._update_actions)
        self.state.model_changed.connect(self._update_actions)
        self.state.image_changed.connect(self._update_title)
        self.state.model_changed.connect(self._update_title)
        self.state.edited.connect(self._on_edited)
        self.fit_panel.settings_changed.connect(self._on_fit_settings)
        self.fit_panel.refit_requested.connect(lambda: self.schedule_refit(force=True))

        self._autosave_timer = QTimer(self)
        self._autosave_timer.setSingleShot(True)
        self._autosave_timer.setInterval(250)
        self._autosave_timer.timeout.connect(self.write_recovery)
        self._update_actions()

    # -- construction ---------------------------------------------------------------------------
    def _action(self, text: str, slot, shortcut=None, tip: str = "") -> QAction:
        action = QAction(text, self)
        if shortcut is not None:
            action.setShortcut(QKeySequence(shortcut))
        if tip:
            action.setToolTip(tip)
            action.setStatusTip(tip)
        action.triggered.connect(slot)
        self.addAction(action)
        return action

    def _create_actions(self) -> None:
        a = self._action
        self.act_open_image = a("&Open image…", self.open_image_dialog, QKeySequence.StandardKey.Open,
                                "Open a NIfTI image (.nii, .nii.gz)")
        self.act_load_model = a("Load &model…", self.load_model_dialog, "Ctrl+M",
                                "Load a shape model (.npz)")
        self.act_open_session = a("Open &session…", self.open_session_dialog, "Ctrl+Shift+O")
        self.act_save_session = a("&Save session", self.save_session, QKeySequence.StandardKey.Save)
        self.act_save_session_as = a("Save session &as…", lambda: self.save_session(ask=True))
        self.act_export = a("&Export all…", self.export_all_dialog, "Ctrl+E",
                            "Export the label map (NIfTI), the surface mesh and the points")
        self.act_export_labels = a("Export label map…", lambda: self.export_dialog("labels"))
        self.act_export_mesh = a("Export surface mesh…", lambda: self.export_dialog("mesh"))
        self.act_export_points = a("Export points…", lambda: self.export_dialog("points"))
        self.act_import_points = a("Import points…", self.import_points_dialog)
        self.act_quit = a("&Quit", self.close, QKeySequence.StandardKey.Quit)
        self.act_undo = a("&Undo", self.undo, "Ctrl+Z")
        self.act_redo = a("&Redo", self.redo, "Ctrl+Shift+Z")
        self.act_delete = a("&Delete point", self.delete_point, QKeySequence.StandardKey.Delete,
                            "Remove the point under the cursor, else the last point")
        self.act_clear_slice = a("Clear &slice", self.clear_active_slice, None,
                                 "Remove the points of the active view's slice")
        self.act_clear_points = a("Clear &all points", self.state.clear_points)
        self.act_place = a("&Place model here", self.place_here, "P",
                           "Move the model so that its centre is at the crosshair")
        self.act_reset_pose = a("Reset model pose", self.state.reset_placement, None,
                                "Back to the model's stored position and mean shape")
        self.act_next_slice = a("Next slice", lambda: self.state.step_slice(self.active_view, 1),
                                QKeySequence(Qt.Key.Key_PageUp))
        self.act_prev_slice = a("Previous slice", lambda: self.state.step_slice(self.active_view, -1),
                                QKeySequence(Qt.Key.Key_PageDown))
        self.act_reset_views = a("&Reset views", self.reset_views, "R")
        self.act_shortcuts = a("&Keyboard shortcuts", self.show_shortcuts, QKeySequence.StandardKey.HelpContents)
        self.act_about = a("&About SSM Studio", self.show_about)
        self.tool_group = QActionGroup(self)
        self.tool_actions = {}
        for tool, text, key in (("navigate", "Navigate", "N"), ("draw", "Draw contour", "D"),
                                ("window", "Window/level", "W")):
            action = a(text, lambda checked=False, t=tool: self.set_tool(t), key)
            action.setCheckable(True)
            self.tool_group.addAction(action)
            self.tool_actions[tool] = action
        self.tool_actions["navigate"].setChecked(True)

    def _create_menus(self) -> None:
        bar = self.menuBar()
        file_menu = bar.addMenu("&File")
        for act in (self.act_open_image, self.act_load_model, None, self.act_open_session,
                    self.act_save_session, self.act_save_session_as, None, self.act_import_points,
                    self.act_export, self.act_export_labels, self.act_export_mesh,
                    self.act_export_points, None, self.act_quit):
            file_menu.addSeparator() if act is None else file_menu.addAction(act)
        edit = bar.addMenu("&Edit")
        for act in (self.act_undo, self.act_redo, None, self.act_delete, self.act_clear_slice,
                    self.act_clear_points, None, self.act_place, self.act_reset_pose):
            edit.addSeparator() if act is None else edit.addAction(act)
        view = bar.addMenu("&View")
        for act in self.tool_actions.values():
            view.addAction(act)
        view.addSeparator()
        for act in (self.act_next_slice, self.act_prev_slice, self.act_reset_views):
            view.addAction(act)
        presets = view.addMenu("Window/level preset")
        for name in WINDOW_PRESETS:
            presets.addAction(name, lambda n=name: self.apply_window_preset(n))
        help_menu = bar.addMenu("&Help")
        help_menu.addAction(self.act_shortcuts)
        help_menu.addAction(self.act_about)

    def _create_toolbar(self) -> None:
        bar = QToolBar("Main")
        bar.setObjectName("main-toolbar")
        bar.setMovable(False)
        for act in (self.act_open_image, self.act_load_model, self.act_save_session, self.act_export):
            bar.addAction(act)
        bar.addSeparator()
        for act in self.tool_actions.values():
            bar.addAction(act)
        bar.addSeparator()
        for act in (self.act_undo, self.act_redo, self.act_place, self.act_reset_views):
            bar.addAction(act)
        self.addToolBar(Qt.ToolBarArea.TopToolBarArea, bar)
        self.toolbar = bar

    def _create_side_panel(self) -> None:
        dock = QDockWidget("Segmentation", self)
        dock.setObjectName("segmentation-dock")
        dock.setFeatures(QDockWidget.DockWidgetFeature.DockWidgetMovable)
        panel = QWidget()
        layout = QVBoxLayout(panel)
        layout.setContentsMargins(2, 2, 2, 2)
        for title, widget, stretch in (("Tools", self.tools_panel, 0), ("Fit", self.fit_panel, 0),
                                       ("Deformation factors", self.factors_panel, 1)):
            box = QGroupBox(title)
            box_layout = QVBoxLayout(box)
            box_layout.setContentsMargins(2, 2, 2, 2)
            box_layout.addWidget(widget)
            layout.addWidget(box, stretch)
        dock.setWidget(panel)
        dock.setMinimumWidth(330)
        self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, dock)
        self.side_dock = dock

    # -- loading ------------------------------------------------------------------------------
    def load_image(self, path: str | os.PathLike) -> None:
        """Load a NIfTI image (raises DataFileError)."""
        volume = load_volume(path)
        self.state.set_image(volume, path)
        if self.state.model is not None:
            self._center_on_model()
        self.show_message(f"Opened {Path(path).name}: {volume.shape[0]}x{volume.shape[1]}x"
                          f"{volume.shape[2]} voxels, {' '.join(f'{s:.2g}' for s in volume.spacing)} mm")

    def load_model(self, path: str | os.PathLike, coef=None, pose=None) -> None:
        """Load a shape model at its stored world position (raises DataFileError)."""
        model = load_model(path)
        self.runner.cancel()
        self.last_fit = None
        self.state.set_model(model, path, coef=coef, pose=pose)
        self.state.clear_history()
        self._center_on_model()
        centre = self.state.surface_vertices().mean(axis=0)
        if self.state.volume is not None:
            lo, hi = self.state.volume.world_bounds()
            if np.any(centre < lo) or np.any(centre > hi):
                self.show_message(f"Model {Path(path).name} lies outside the image: "
                                  "use 'Place here' to move it to the crosshair")
                return
        self.show_message(f"Loaded model {Path(path).name}: {model.method}, "
                          f"{model.n_factors} factors, {model.n_vertices} vertices")
        if len(self.state.points):
            self.schedule_refit()

    def _center_on_model(self) -> None:
        vertices = self.state.surface_vertices()
        if vertices is not None and self.state.volume is not None:
            self.state.set_crosshair(vertices.mean(axis=0))

    def load_demo(self) -> None:
        image = demo.demo_image()
        if image is None:
            raise DataFileError(demo.resources_dir(), "no demo image found (resources/ is "
                                "incomplete and nilearn is not installed)")
        self.load_image(image)
        model = demo.demo_model()
        if model is not None:
            self.load_model(model)
        self.state.clear_history()

    def open_path(self, path: str | os.PathLike) -> None:
        """Open any supported file by its type (drag and drop, recent files)."""
        name = str(path).lower()
        try:
            if name.endswith((".nii", ".nii.gz")):
                self.load_image(path)
            elif name.endswith(".npz"):
                self.load_model(path)
            elif name.endswith((".mrk.json", ".csv")):
                self.import_points(path)
            elif name.endswith(".json"):
                self.open_session(path)
            else:
                raise ValueError(f"{path}: unsupported file type (expected .nii/.nii.gz image, "
                                 ".npz model, .json session, or .csv/.mrk.json points)")
        except (ValueError, OSError) as exc:
            self.show_error(exc)

    # -- dialogs ------------------------------------------------------------------------------
    def _start_dir(self) -> str:
        for p in (self.session_path, self.state.image_path):
            if p is not None:
                return str(Path(p).parent)
        return str(Path.cwd())

    def open_image_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open image", self._start_dir(),
                                              "NIfTI images (*.nii *.nii.gz);;All files (*)")
        if path:
            self.open_path(path)

    def load_model_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Load shape model", self._start_dir(),
                                              "Shape models (*.npz);;All files (*)")
        if path:
            self.open_path(path)

    def open_session_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open session", self._start_dir(),
                                              "Sessions (*.json);;All files (*)")
        if path:
            self.open_path(path)

    def import_points_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Import points", self._start_dir(),
                                              "Points (*.csv *.mrk.json);;All files (*)")
        if path:
            self.open_path(path)

    def export_dialog(self, what: str) -> None:
        filters = {"labels": ("label map", "NIfTI (*.nii.gz *.nii)", "segmentation.nii.gz"),
                   "mesh": ("surface mesh", "Meshes (*.vtk *.vtp *.stl *.ply *.obj)", "surface.vtk"),
                   "points": ("points", "CSV (*.csv);;Slicer markups (*.mrk.json)", "points.csv")}
        title, filt, default = filters[what]
        path, _ = QFileDialog.getSaveFileName(self, f"Export {title}",
                                              str(Path(self._start_dir()) / default), filt)
        if path:
            self._guarded(lambda: getattr(self, f"export_{what}")(path))

    def export_all_dialog(self) -> None:
        folder = QFileDialog.getExistingDirectory(self, "Export into folder", self._start_dir())
        if folder:
            self._guarded(lambda: self.export_all(folder))

    def _guarded(self, fn) -> bool:
        try:
            fn()
            return True
        except (ValueError, OSError) as exc:
            self.show_error(exc)
            return False

    # -- drag and drop ------------------------------------------------------------------------
    def dragEnterEvent(self, event) -> None:  # noqa: N802
        if event.mimeData().hasUrls():
            event.acceptProposedAction()

    def dropEvent(self, event) -> None:  # noqa: N802
        for url in event.mimeData().urls():
            if url.isLocalFile():
                self.open_path(url.toLocalFile())
        event.acceptProposedAction()

    # -- tools and editing --------------------------------------------------------------------
    def set_tool(self, tool: str) -> None:
        for view in self.workspace.views.values():
            view.set_tool(tool)
        self.tool_actions[tool].setChecked(True)
        hints = {"navigate": "Navigate: click to move the crosshair",
                 "draw": "Draw: click or drag on the structure's outline to add contour points; "
                         "Ctrl+click deletes a point",
                 "window": "Window/level: drag left-right for width, up-down for level"}
        self.show_message(hints[tool])

    def _on_view_activated(self, name: str) -> None:
        self.active_view = name

    def undo(self) -> None:
        if self.state.undo():
            self.show_message("Undone")

    def redo(self) -> None:
        if self.state.redo():
            self.show_message("Redone")

    def delete_point(self) -> None:
        view = self.workspace.views[self.active_view]
        if self._hover is not None:
            x, y = view.world_to_screen(self._hover)
            if view.delete_point_near(x, y):
                return
        if len(self.state.points):
            self.state.remove_point(len(self.state.points) - 1)

    def clear_active_slice(self) -> None:
        view = self.workspace.views[self.active_view]
        removed = self.state.clear_slice(self.active_view, view.depth)
        self.show_message(f"Removed {removed} point(s) from the {self.active_view} slice")

    def place_here(self) -> None:
        if self.state.model is None:
            self.show_message("Load a model first (File > Load model)")
            return
        self.runner.cancel()
        self.last_fit = None
        self.state.place_at(self.state.crosshair)
        if len(self.state.points):
            self.schedule_refit()

    def reset_views(self) -> None:
        for view in self.workspace.views.values():
            view.reset_view()
        if self.workspace.volume_view is not None:
            self.workspace.volume_view.reset_camera()
            self.workspace.volume_view.plotter.render()

    def apply_window_preset(self, name: str) -> None:
        volume = self.state.volume
        if volume is None:
            return
        from core.planes import auto_window

        kind = WINDOW_PRESETS.get(name)
        lo, hi = self.state.data_range
        if kind is None:
            window, level = auto_window(volume.data)
        elif kind == "full":
            window, level = hi - lo, (hi + lo) / 2
        elif kind == "contrast":
            window, level = auto_window(volume.data, 30.0, 95.0)
            window *= 0.8
        else:
            window, level = auto_window(volume.data, 1.0, 90.0)
        self.state.set_window(window, level)

    def _wire_volume_view(self) -> None:
        self.workspace.volume_view.defer = lambda: self.runner.is_busy

    def _show_factor_region(self, index: int) -> None:
        """Colour the 3D surface by the touched factor's displacement for a few seconds."""
        if index >= 0 and self.state.model is not None:
            self._factor_timer.start()
            sd = np.sqrt(self.state.model.coef_var[index])
            move = sd * np.linalg.norm(self.state.model.factors[index], axis=1)
            share = float(np.mean(move > 0.1 * move.max())) if move.max() > 0 else 0.0
            self.show_message(f"Factor {index + 1}: moves {100 * share:.0f}% of the surface "
                              f"(up to {move.max():.1f} mm per SD)", 4000)
        if self.workspace.volume_view is not None:
            self.workspace.volume_view.show_factor(index)

    # -- refit --------------------------------------------------------------------------------
    def _on_points_changed(self) -> None:
        self._update_actions()
        if self.fit_panel.auto.isChecked():
            self.schedule_refit()

    def _on_fit_settings(self) -> None:
        self.last_fit = None       # a different method: no warm start from the other one
        if self.fit_panel.auto.isChecked() and len(self.state.points):
            self.schedule_refit()

    def _warm_start(self):
        """The FitResult to start from: the last fit if the surface still is that fit."""
        from core.reconstruction import FitResult

        state = self.state
        last = self.last_fit
        if last is not None and np.array_equal(last.coef, state.coef) and np.array_equal(last.pose, state.pose):
            return last
        return FitResult(coef=state.coef.copy(), pose=state.pose.copy(),
                         vertices=state.surface_vertices().copy())

    def point_normals(self) -> np.ndarray:
        """(P, 3) normals of the contour points, oriented by the current surface; 0 = unknown."""
        from core.mesh import vertex_normals

        surface = None
        vertices = self.state.surface_vertices()
        if vertices is not None:
            surface = (vertices, vertex_normals(vertices, self.state.model.faces))
        return np.nan_to_num(self.state.points.normals(surface), nan=0.0)

    def schedule_refit(self, force: bool = False) -> int | None:
        """Submit a refit of the current points (newest wins); returns its generation."""
        state = self.state
        if state.model is None:
            return None
        if len(state.points) == 0:
            self.runner.cancel()
            state.set_fit_info(FitInfo(message=""))
            return None
        from core.reconstruction import fit_points

        model = state.model
        points = state.points.xyz.copy()
        normals = self.point_normals()
        settings = self.fit_panel.settings
        init = self._warm_start()
        placement = None if state.placement is None else state.placement.copy()
        edit_time = time.perf_counter()

        def job(progress):
            def callback(iteration: int, objective: float) -> None:
                progress(min(iteration / 100.0, 1.0), "")

            result = fit_points(model, points, normals, method=settings["method"],
                                pose=settings["pose"], prior_weight=settings["prior_weight"],
                                placement=placement, pose_spread=settings["pose_spread"],
                                init=init, callback=callback)
            return result, edit_time

        return self.runner.submit(job)

    def _on_refit_result(self, value, generation: int) -> None:
        result, edit_time = value
        if self.state.model is None or np.shape(result.coef) != (self.state.model.n_factors,):
            return
        if not (np.all(np.isfinite(result.vertices)) and np.all(np.isfinite(result.pose))):
            self._on_refit_failed("the fit diverged (non-finite result); previous fit kept", generation)
            return
        self.last_fit = result
        self.state.set_surface(result.coef, result.pose, result.vertices)
        elapsed = time.perf_counter() - edit_time
        self.refit_times.append(elapsed)
        self.state.set_fit_info(FitInfo(residual_mm=float(result.residual_mm), n_iter=int(result.n_iter),
                                        converged=bool(result.converged), stop_reason=result.stop_reason,
                                        seconds=elapsed, fit_seconds=float(result.elapsed_s)))
        self.fit_label.setText(f"residual {result.residual_mm:.2f} mm, {result.n_iter} it, "
                               f"{1000 * elapsed:.0f} ms")
        self.refit_applied.emit(result)
        self._schedule_autosave("fit")

    def _on_refit_failed(self, message: str, generation: int) -> None:
        info = FitInfo(message=message)
        self.state.set_fit_info(info)
        self.fit_label.setText("fit: " + message[:60])
        self.statusBar().showMessage(f"Fit not updated: {message}", 8000)

    def _on_refit_busy(self, busy: bool) -> None:
        if busy:
            self.fit_label.setText("fitting…")

    def wait_for_refit(self, timeout_ms: int = 10000) -> bool:
        """Process events until no refit is pending (tests, scripts)."""
        deadline = time.perf_counter() + timeout_ms / 1000
        app = QApplication.instance()
        while self.runner.is_busy and time.perf_counter() < deadline:
            app.processEvents()
            time.sleep(0.002)
        app.processEvents()
        return not self.runner.is_busy

    # -- status -------------------------------------------------------------------------------
    def show_message(self, text: str, msecs: int = 6000) -> None:
        self.statusBar().showMessage(text, msecs)

    def show_error(self, exc: BaseException | str) -> None:
        """One-line error in the status bar and a message box (no traceback)."""
        text = exc if isinstance(exc, str) else error_message(exc)
        self.statusBar().showMessage(f"Error: {text}", 15000)
        if not self._quiet_errors():
            QMessageBox.warning(self, "SSM Studio", text)

    def _quiet_errors(self) -> bool:
        return bool(os.environ.get("SSM_STUDIO_NO_DIALOGS")) or not self.isVisible()

    def _on_hover(self, world) -> None:
        self._hover = None if world is None else np.asarray(world)
        self._update_cursor_label()

    def _update_cursor_label(self) -> None:
        volume = self.state.volume
        point = self._hover if self._hover is not None else self.state.crosshair
        if volume is None:
            self.cursor_label.setText("")
            return
        ijk = volume.world_to_voxel(point)
        inside = bool(volume.contains_voxel(ijk))
        value = volume.value_at(point) if inside else None
        where = "cursor" if self._hover is not None else "crosshair"
        idx = np.rint(ijk).astype(int)
        text = (f"{where}  R {point[0]:+.1f}  A {point[1]:+.1f}  S {point[2]:+.1f} mm   "
                f"voxel ({idx[0]}, {idx[1]}, {idx[2]})   ")
        text += f"value {value:.4g}" if value is not None else "outside the image"
        self.cursor_label.setText(text)

    def _update_actions(self) -> None:
        has_model = self.state.model is not None
        self.act_undo.setEnabled(self.state.can_undo())
        self.act_redo.setEnabled(self.state.can_redo())
        for act in (self.act_place, self.act_reset_pose, self.act_export_labels, self.act_export_mesh):
            act.setEnabled(has_model)
        has_points = len(self.state.points) > 0
        for act in (self.act_delete, self.act_clear_slice, self.act_clear_points, self.act_export_points):
            act.setEnabled(has_points)

    def _update_title(self) -> None:
        parts = [p.name for p in (self.state.image_path, self.state.model_path) if p is not None]
        if self.session_path is not None:
            parts.insert(0, self.session_path.name)
        title = "SSM Studio" + (" — " + " + ".join(parts) if parts else "")
        self.setWindowTitle(title + (" *" if self.unsaved else ""))

    def _on_edited(self, what: str = "") -> None:
        if not self.unsaved:
            self.unsaved = True
            self._update_title()
        self._schedule_autosave(what)

    def _mark_saved(self) -> None:
        self.unsaved = False
        self._update_title()

    def show_shortcuts(self) -> None:
        rows = "".join(f"<tr><td><b>{k}</b></td><td>&nbsp;&nbsp;{v}</td></tr>" for k, v in SHORTCUTS)
        QMessageBox.information(self, "Keyboard and mouse", f"<table>{rows}</table>")

    def show_about(self) -> None:
        from core import __version__

        QMessageBox.about(self, "About SSM Studio",
                          f"<b>SSM Studio {__version__}</b><br>Shape-model-based interactive "
                          "segmentation of deep brain structures.<br>Slice views in world RAS "
                          "coordinates, radiological convention (patient right on screen left).")

    # -- export -------------------------------------------------------------------------------
    def label_map(self) -> np.ndarray:
        """The fitted surface as a uint8 label map on the image grid (1 inside)."""
        from core.segmentation import voxelize

        if self.state.model is None or self.state.volume is None:
            raise ValueError("need an image and a fitted model to export a label map")
        return voxelize(self.state.surface_vertices(), self.state.model.faces,
                        self.state.volume.shape, self.state.volume.affine)

    def export_labels(self, path: str | os.PathLike) -> None:
        labels = self.label_map()
        save_volume(path, labels.astype(np.uint8), self.state.volume.affine)
        self.show_message(f"Exported label map {Path(path).name}: {int(labels.sum())} voxels inside")

    def export_mesh(self, path: str | os.PathLike) -> None:
        from core.io import TriMesh

        if self.state.model is None:
            raise ValueError("no model loaded: nothing to export")
        save_mesh(path, TriMesh(self.state.surface_vertices(), self.state.model.faces))
        self.show_message(f"Exported surface {Path(path).name}")

    def export_points(self, path: str | os.PathLike) -> None:
        pts = self.state.points
        if len(pts) == 0:
            raise ValueError("no contour points to export")
        save_points(path, pts.xyz, self.point_normals())
        self.show_message(f"Exported {len(pts)} points to {Path(path).name}")

    def export_all(self, folder: str | os.PathLike) -> list[Path]:
        folder = Path(folder)
        written = []
        if self.state.model is not None and self.state.volume is not None:
            written.append(folder / "segmentation.nii.gz")
            self.export_labels(written[-1])
            written.append(folder / "surface.vtk")
            self.export_mesh(written[-1])
        if len(self.state.points):
            for name in ("points.csv", "points.mrk.json"):
                written.append(folder / name)
                self.export_points(written[-1])
        self.show_message(f"Exported {len(written)} file(s) to {folder}")
        return written

    def import_points(self, path: str | os.PathLike) -> None:
        """Add points from CSV / Slicer markups; each is assigned to the nearest axial slice."""
        from core.io import load_points

        pset = load_points(path)
        points = self.state.points
        self.state.checkpoint()
        for xyz in pset.points:
            points = points.append(xyz, 0, float(xyz[2]))
        self.state.set_points(points, checkpoint=False)
        self.show_message(f"Imported {len(pset)} point(s) from {Path(path).name}")

    # -- sessions and recovery ----------------------------------------------------------------
    def session_object(self):
        """The current work as a :class:`core.session.Session`."""
        from core.session import Session

        state = self.state
        pts = state.points
        return Session(
            image_path=state.image_path, model_path=state.model_path,
            points=pts.xyz.copy(), normals=self.point_normals() if len(pts) else None,
            point_slices=[(FRAME_NAMES[int(f)], float(d)) for f, d in zip(pts.frame, pts.depth)],
            coef=None if state.coef is None else state.coef.copy(),
            pose=None if state.pose is None else state.pose.copy(),
            fit=self.fit_panel.settings, window=(state.window, state.level),
            crosshair=state.crosshair.copy(), info={"written_by": "ssm-studio"},
        )

    def apply_session(self, session) -> None:
        """Restore image, model, fit, points, window and crosshair from a Session."""
        self.runner.cancel()
        if session.image_path is not None:
            self.load_image(session.image_path)
        if session.model_path is not None:
            self.load_model(session.model_path, coef=session.coef, pose=session.pose)
        fit = dict(session.fit or {})
        self.fit_panel.blockSignals(True)
        try:
            self.fit_panel.set_settings(fit.get("method"), fit.get("pose"), fit.get("prior_weight"),
                                        fit.get("pose_spread"))
        finally:
            self.fit_panel.blockSignals(False)
        xyz = np.asarray(session.points, dtype=np.float64).reshape(-1, 3)
        slices = session.point_slices or [("axial", float(p[2])) for p in xyz]
        points = Points()
        for p, (frame, depth) in zip(xyz, slices):
            name = frame if isinstance(frame, str) else ("sagittal", "coronal", "axial")[int(frame)]
            points = points.append(p, FRAME_NAMES.index(name), float(depth))
        self.state.points = points
        self.last_fit = None
        self.state.points_changed.disconnect(self._on_points_changed)
        try:
            self.state.points_changed.emit()    # redraw, but no refit: the stored fit is shown
        finally:
            self.state.points_changed.connect(self._on_points_changed)
        if session.window is not None:
            self.state.set_window(*session.window)
        if session.crosshair is not None:
            self.state.set_crosshair(session.crosshair)
        self.state.clear_history()
        self._update_actions()

    def open_session(self, path: str | os.PathLike) -> None:
        from core import session as sessions

        session = sessions.load_session(path)
        self.apply_session(session)
        self.session_path = Path(path)
        self._mark_saved()
        self.show_message(f"Opened session {Path(path).name}")

    def save_session(self, ask: bool = False, path: str | os.PathLike | None = None) -> bool:
        from core import session as sessions

        target = Path(path) if path else self.session_path
        if target is None or ask:
            chosen, _ = QFileDialog.getSaveFileName(self, "Save session",
                                                    str(Path(self._start_dir()) / "session.json"),
                                                    "Sessions (*.json)")
            if not chosen:
                return False
            target = Path(chosen)
        if self.state.image_path is None:
            self.show_error("nothing to save: open an image first")
            return False
        ok = self._guarded(lambda: sessions.save_session(target, self.session_object()))
        if ok:
            self.session_path = target
            self._mark_saved()
            self.show_message(f"Saved session {target.name}")
        return ok

    def _schedule_autosave(self, what: str = "") -> None:
        if self.recovery_enabled and not self._closing:
            self._autosave_timer.start()

    def write_recovery(self) -> None:
        if not self.recovery_enabled:
            return
        try:
            from core import session as sessions

            sessions.write_recovery(self.session_object())
        except ImportError:
            return
        except (ValueError, OSError) as exc:
            self.statusBar().showMessage(f"Autosave failed: {error_message(exc)}", 8000)

    def offer_recovery(self, ask=None) -> bool:
        """If a recovery file exists, ask (``ask(text) -> bool``) and restore it; True if restored."""
        try:
            from core import session as sessions
        except ImportError:
            return False
        try:
            session = sessions.read_recovery()
        except (ValueError, OSError) as exc:
            self.show_message(f"Recovery file unreadable, ignored: {error_message(exc)}")
            sessions.clear_recovery()
            return False
        if session is None:
            return False
        if ask is None:
            def ask(text: str) -> bool:
                return QMessageBox.question(self, "Recover unsaved work?", text) == \
                    QMessageBox.StandardButton.Yes
        n_points = len(np.asarray(session.points).reshape(-1, 3))
        text = (f"SSM Studio did not close normally last time. Restore the unsaved session "
                f"({n_points} contour point(s))?")
        if not ask(text):
            sessions.clear_recovery()
            return False
        try:
            self.apply_session(session)
        except (ValueError, OSError) as exc:
            self.show_error(exc)
            return False
        self.unsaved = True                      # recovered work is not saved anywhere yet
        self._update_title()
        self.show_message("Recovered the unsaved session")
        return True

    # -- builder tab --------------------------------------------------------------------------
    def _on_tab(self, index: int) -> None:
        if self.tabs.widget(index) is self._builder_placeholder:
            self.ensure_builder()
        self._show_segment_controls(self.tabs.currentWidget() is self.workspace)

    def _show_segment_controls(self, visible: bool) -> None:
        """The side panel and the drawing tools belong to the Segment tab only."""
        self.side_dock.setVisible(visible)
        self.cursor_label.setVisible(visible)
        self.fit_label.setVisible(visible)
        for act in (*self.tool_actions.values(), self.act_undo, self.act_redo, self.act_place,
                    self.act_reset_views):
            act.setVisible(visible)

    def ensure_builder(self):
        if self.builder is not None:
            return self.builder
        try:
            from app.panels.builder import BuilderPanel
        except ImportError as exc:
            self._builder_placeholder.setText(f"Model builder unavailable: {exc}")
            return None
        index = self.tabs.indexOf(self._builder_placeholder)
        self.builder = BuilderPanel()
        self.builder.use_for_segmentation.connect(self._use_built_model)
        self.tabs.blockSignals(True)
        self.tabs.removeTab(index)
        self.tabs.insertTab(index, self.builder, "Build model")
        self.tabs.setCurrentIndex(index)
        self.tabs.blockSignals(False)
        self._show_segment_controls(self.tabs.currentWidget() is self.workspace)
        return self.builder

    def _use_built_model(self, path: str) -> None:
        """The builder's "Use for segmentation": load that model here and switch tabs."""
        self.tabs.setCurrentWidget(self.workspace)
        self._guarded(lambda: self.load_model(path))

    # -- rendering and closing ----------------------------------------------------------------
    def render_now(self) -> None:
        """Flush pending view updates (before a screenshot)."""
        app = QApplication.instance()
        app.processEvents()
        if self.workspace.volume_view is not None:
            self.workspace.volume_view.flush()
        for view in self.workspace.views.values():
            view.repaint()
        app.processEvents()

    def save_screenshot(self, path: str | os.PathLike) -> None:
        self.render_now()
        image = self.grab()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not image.save(str(path)):
            raise OSError(f"{path}: could not write the screenshot")

    def closeEvent(self, event) -> None:  # noqa: N802
        if self._closing:
            event.accept()
            return
        if self.unsaved and not self._quiet_errors() and self.state.image_path is not None:
            answer = QMessageBox.question(
                self, "Unsaved changes", "Save the session before closing?",
                QMessageBox.StandardButton.Save | QMessageBox.StandardButton.Discard
                | QMessageBox.StandardButton.Cancel, QMessageBox.StandardButton.Save)
            if answer == QMessageBox.StandardButton.Cancel or (
                    answer == QMessageBox.StandardButton.Save and not self.save_session()):
                event.ignore()
                return
        self._closing = True
        self._autosave_timer.stop()
        self.runner.cancel()
        self.runner.wait(5000)
        if self.recovery_enabled:
            try:
                from core import session as sessions

                sessions.clear_recovery()
            except ImportError:
                pass
        if self.builder is not None:
            self.builder.close()
        if self.workspace.volume_view is not None:
            self.workspace.volume_view.close()
        self.closed.emit()
        event.accept()


def _builder_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("app.panels.builder") is not None


def run_gui(image: str | None = None, model: str | None = None, session: str | None = None,
            screenshot: str | None = None, tab: str = "segment") -> int:
    """Open the main window; with ``screenshot`` render it to that PNG and exit. Exit code."""
    app = QApplication.instance() or QApplication(sys.argv[:1])
    app.setApplicationName("SSM Studio")
    app.setStyle("Fusion")
    started = time.perf_counter()
    window = MainWindow(recovery=screenshot is None, defer_3d=screenshot is None)
    window.resize(1600, 1000)
    try:
        if session:
            window.open_session(session)
        else:
            if image:
                window.load_image(image)
            else:
                window.load_demo()
            if model:
                window.load_model(model)
    except (ValueError, OSError) as exc:
        print(f"ssm-studio: error: {error_message(exc)}", file=sys.stderr)
        window.recovery_enabled = False
        window.close()
        return 2
    if tab == "build" and window.ensure_builder() is not None:
        window.tabs.setCurrentWidget(window.builder)
    window.show()
    if screenshot:
        app.processEvents()
        try:
            window.save_screenshot(screenshot)
        except OSError as exc:
            print(f"ssm-studio: error: {error_message(exc)}", file=sys.stderr)
            return 2
        finally:
            window.unsaved = False               # nothing to ask when only rendering
            window.close()
        print(f"ssm-studio: wrote {screenshot} ({time.perf_counter() - started:.1f} s)",
              file=sys.stderr)
        return 0
    QTimer.singleShot(100, window.workspace.create_volume_view)   # after the first paint
    QTimer.singleShot(0, window.offer_recovery)
    return app.exec()
