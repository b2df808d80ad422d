"""The main window: layout and actions of the segmentation workspace (and the builder tab).

Layout (ITK-SNAP-like): a 2x2 grid of the axial, sagittal and coronal slice views and the 3D
view (:class:`app.views.grid.SegmentWorkspace`), linked by one crosshair in world (RAS, mm)
coordinates; a side panel with the tools, the fit settings and read-out, and one slider per
deformation factor; a status bar with the world position, voxel index and intensity under
the cursor.

Wiring (3D Slicer's Widget/Logic split): the state is the Qt-free
:class:`app.model.state.WorkspaceState`; views and panels subscribe to its events. The logic is in
controllers: :class:`app.refit.RefitController` refits the edited structure in a worker
thread (newest edit wins, warm-started from the current fit),
:class:`app.model.controllers.SessionController` opens images, models and sessions and writes the
crash-recovery file after each edit, :class:`app.model.controllers.ExportController` writes label
maps, meshes and points. This module only builds the window and turns actions into calls.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from PySide6.QtCore import QSize, Qt, QTimer, Signal
from PySide6.QtGui import QScreen
from PySide6.QtWidgets import QApplication, QMainWindow, QMessageBox

from app import demo
from app.actions import (
    SHORTCUTS,
    create_actions,
    create_menus,
    create_toolbar,
    show_segment_controls,
    update_actions,
    update_title,
)
from app.dialogs import ExportActions, SessionActions
from app.edit_commands import EditCommands
from app.file_actions import OPEN_DIALOGS, FileActions
from app.model.controllers import ExportController, SessionController, read_image
from app.model.state import WorkspaceState
from app.paint_gate import PaintGate
from app.panels.factors import FactorsPanel
from app.panels.fit import FitPanel
from app.panels.side import DrawingBar, SidePanel
from app.panels.status import status_readouts
from app.panels.structures import StructuresPanel
from app.panels.tools import WINDOW_PRESETS, ToolsPanel
from app.placement import AutoPlacement
from app.plan_controller import install_planning
from app.refit import RefitController
from app.registry import ActionRegistry, SliceTools
from app.tabs import WorkspaceTabs
from app.tools_install import install_segment_tools
from app.views.grid import SegmentWorkspace
from app.workers import error_message, settle_at_exit
from core.io.model_library import list_library

__all__ = ["MainWindow", "SegmentWorkspace", "SHORTCUTS", "OPEN_DIALOGS", "run_gui"]

BASE_TOOLS = {"navigate": ("Navigate", "N", "Navigate: click to move the crosshair"),
              "draw": ("Draw contour", "D", "Draw: click or drag on the structure's outline to "
                                            "add contour points; Ctrl+click deletes a point"),
              "window": ("Window/level", "W",
                         "Window/level: drag left-right for width, up-down for level")}


def _single_shot(parent, msecs: int, slot) -> QTimer:
    """A single-shot timer of ``parent`` that calls ``slot`` ``msecs`` after each start."""
    timer = QTimer(parent)
    timer.setSingleShot(True)
    timer.setInterval(msecs)
    timer.timeout.connect(slot)
    return timer


class MainWindow(QMainWindow):
    """SSM Studio's main window (see the module docstring)."""

    refit_applied = Signal(object)         # FitResult applied to the state
    closed = Signal()

    def __init__(self, with_3d: bool = True, recovery: bool = True, defer_3d: bool = False):
        super().__init__()
        self.setWindowTitle("SSM Studio")
        self.setAcceptDrops(True)
        self.state = WorkspaceState()
        self.sessions = SessionController(self.state)
        self.exports = ExportController(self.state)
        self.export_actions = ExportActions(self)
        self.auto_place = AutoPlacement(self.state, self)
        self.auto_place.finished.connect(self._on_auto_placed)
        self.auto_place.failed.connect(lambda m: self.show_message(m, 10000))
        self.session_actions = SessionActions(self)
        self.files = FileActions(self)
        self.edit_commands = EditCommands(self)
        self.session_path: Path | None = None
        self.active_view = "axial"
        self._closing = False
        self._unattended = False           # closing without questions (a recording's end)
        self.recovery_enabled = recovery
        self.unsaved = False

        self.registry = ActionRegistry(self)   # every action and menu, by id
        self.features: dict[str, object] = {}   # the Segment tab's tools, by name
        self.tools = SliceTools(self.registry, self.set_tool)   # one at a time
        self.tools.add(BASE_TOOLS, tips=False)
        self.tools.actions["navigate"].setChecked(True)
        create_actions(self)
        self.workspace = SegmentWorkspace(self.state, with_3d=with_3d, defer_3d=defer_3d)
        self.fit_panel = FitPanel(self.state)
        self.refit = RefitController(self.state, lambda: self.fit_panel.settings,
                                     self.fit_panel.auto.isChecked, self)
        self.paint_gate = PaintGate(self, self.refit)   # one repaint per edit and its refit
        self.refit.applied.connect(self._on_refit_applied)
        self.refit.failed.connect(lambda m: self.statusBar().showMessage(f"Fit not updated: {m}", 8000))
        self.factors_panel = FactorsPanel(self.state)
        self.tools_panel = ToolsPanel(self)
        self.structures_panel = StructuresPanel(self.state, self.sessions, self.refit, list_library)
        self.structures_panel.add_file.connect(lambda: self.open_dialog("structure"))
        self.structures_panel.message.connect(self.show_message)
        self.structures_panel.error.connect(self.show_error)
        create_menus(self)
        self.toolbar = create_toolbar(self)
        self.drawing_bar = DrawingBar(self.tools_panel.count, self.fit_panel.result,
                                      self.registry["undo"], self.registry["redo"])
        self.side_dock = SidePanel([("Structures", self.structures_panel, 0),
                                    ("Tools", self.tools_panel, 0), ("Fit", self.fit_panel, 0),
                                    ("Deformation factors", self.factors_panel, 1)], self,
                                   footer=self.drawing_bar)
        self.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, self.side_dock)
        self.resizeDocks([self.side_dock], [340], Qt.Orientation.Horizontal)
        self.registry["side-panel"].toggled.connect(lambda on: self._show_segment_controls(
            self.tabs.currentWidget() is self.workspace if hasattr(self, "tabs") else True))
        self.plan = install_planning(self)    # .planning, .panel, .dock, the Plan menu

        self.workspace.volume_view_created.connect(self._wire_volume_view)
        if self.workspace.volume_view is not None:
            self._wire_volume_view()
        self.factors_panel.factor_touched.connect(self._show_factor_region)
        self._factor_timer = _single_shot(self, 2500, lambda: self._show_factor_region(-1))
        self.tabs = WorkspaceTabs(self.workspace)
        self.tabs.segment_shown.connect(self._show_segment_controls)
        self.tabs.use_model.connect(self._use_built_model)
        self.setCentralWidget(self.tabs)

        self.cursor_label, self.fit_label = status_readouts(self)
        for view in self.workspace.views.values():
            view.activated.connect(self.set_active_view)
            view.message.connect(self.show_message)
        events = self.state.events
        events.points.connect(self._update_actions)
        events.history.connect(self._update_actions)
        events.model.connect(self._update_actions)
        events.image.connect(self._update_title)
        events.model.connect(self._update_title)
        events.edited.connect(self._on_edited)
        self.fit_panel.settings_changed.connect(self.refit.settings_changed)
        self.fit_panel.refit_requested.connect(lambda: self.schedule_refit(force=True))
        self._autosave_timer = _single_shot(self, 250, self.write_recovery)
        self._update_actions()
        install_segment_tools(self)  # labels, measurements, second_image, navigation, tour

    def add_feature(self, name: str, feature: object) -> None:
        """Compose a feature (it has registered its actions and menus in ``self.registry``)."""
        if name in self.features:
            raise ValueError(f"feature {name!r} is already installed")
        self.features[name] = feature

    @property
    def runner(self):
        """The active structure's refit runner (tests and scripts wait on it)."""
        return self.refit.runner

    # -- opening files --------------------------------------------------------------------------
    def load_image(self, path: str | os.PathLike, series: str | None = None,
                   ask: bool | None = None, notify=None) -> None:
        """Load an image: NIfTI, NRRD, MetaImage or a DICOM series (raises DataFileError).

        A DICOM folder with several series asks which one (app.series_dialog) unless
        ``series`` names it or ``ask`` is False (then: the one with most files, said in the
        status bar and to ``notify``; if it cannot be read, the error names the others).
        """
        notes: list[str] = []
        folder = path
        if series is None:
            path = self.files.resolve_image(path, ask, notes)
            if path is None:
                return  # the user cancelled the series choice
        for note in notes if notify is not None else ():
            notify(note)
        # a series taken by default from a folder holding several: its error names the others
        self.show_image(path, read_image(path, series, folder if notes else None), notes)

    def show_image(self, path: str | os.PathLike, volume, notes: list[str] | tuple = ()) -> None:
        """``volume``, read from ``path`` (here, or in a worker: app.file_actions), shown."""
        message = self.sessions.open_image(path, volume=volume)
        message = self.sessions.overlap_warning() or message
        self.show_message(message + (f" ({notes[0]})" if notes else ""))
        self.auto_place.offer(self, message)

    def load_model(self, path: str | os.PathLike, coef=None, pose=None) -> None:
        """Load a shape model into the active structure at its stored placement."""
        message = self.sessions.open_model(path, coef=coef, pose=pose)   # raises: nothing changed
        self.refit.cancel(self.state.active)      # a fit of the previous model is dropped
        self.show_message(message)
        if len(self.state.active.points) and not self.refit.is_suspended:
            self.schedule_refit()

    def load_second_image(self, path: str | os.PathLike, transform=None) -> bool:
        """Show a second image over the first: read, registered rigidly when the grids differ
        and resampled in a worker (progress, Cancel); False if it could not start."""
        return self.features["second-image"].controller.load(path, transform,
                                                             show_dialog=not self._quiet_errors())

    def load_demo(self) -> None:
        """The demo image and model (raises DataFileError when resources/ is incomplete)."""
        self.load_image(demo.require_demo_image())
        if demo.demo_model() is not None:
            self.load_model(demo.demo_model())
        self.state.clear_history()

    def add_structure(self, path: str | os.PathLike) -> bool:
        """A new structure with the model file ``path``, made active (errors are shown)."""
        return self.structures_panel.add_structure(path)

    def remove_structure(self, structure) -> None:
        self.structures_panel.remove_structure(structure, ask=not self._quiet_errors())

    def import_points(self, path: str | os.PathLike, structure=None) -> None:
        """Points from a file into ``structure`` (default: the active one, made active)."""
        if structure is not None:
            self.state.set_active(structure)
        self.show_message(self.exports.import_points(path))

    def open_path(self, path: str | os.PathLike) -> None:
        """Open any supported file by its type (drag and drop, recent files)."""
        self.files.open_path(path)

    def _start_dir(self) -> str:
        return self.files.start_dir()

    def open_dialog(self, what: str) -> None:
        self.files.open_dialog(what)

    def open_dicom_dialog(self) -> None:
        self.files.open_dicom_dialog()

    def dragEnterEvent(self, event) -> None:  # noqa: N802
        if event.mimeData().hasUrls():
            event.acceptProposedAction()

    def dropEvent(self, event) -> None:  # noqa: N802
        self.files.drop(event)

    # -- export ---------------------------------------------------------------------------------
    def confirm_orientation(self) -> bool:
        return self.export_actions.confirm_orientation()

    def export_all(self, folder: str | os.PathLike) -> list[Path]:
        return self.export_actions.export_all(folder)

    def export_dialog(self, what: str) -> None:
        self.export_actions.export_dialog(what)

    def export_all_dialog(self) -> None:
        self.export_actions.export_all_dialog()

    def ask(self, question: str) -> bool:
        """A yes/no question (without dialogs, e.g. in tests: no)."""
        if self._quiet_errors():
            return False
        return QMessageBox.question(self, "SSM Studio", question) == QMessageBox.StandardButton.Yes

    def _guarded(self, fn) -> bool:
        try:
            fn()
            return True
        except (ValueError, OSError) as exc:
            self.show_error(exc)
            return False

    # -- sessions and recovery ------------------------------------------------------------------
    def session_object(self):
        """The current work as a :class:`core.session.document.Session`."""
        return self.sessions.to_session(self.fit_panel.settings)

    def apply_session(self, session, volume=None) -> None:
        """Restore image, model, fit, points, window and crosshair (``volume``: read already)."""
        self.session_actions.apply_session(session, volume)

    def open_session(self, path: str | os.PathLike) -> None:
        self.files.restore_session(self.sessions.read(path), path)

    def save_session(self, ask: bool = False, path: str | os.PathLike | None = None) -> bool:
        return self.session_actions.save_session(ask, path)

    def write_recovery(self) -> None:
        self.session_actions.write_recovery()

    def offer_recovery(self, ask=None) -> bool:
        """If a recovery file exists, ask (``ask(text) -> bool``) and restore it; True if restored."""
        return self.session_actions.offer_recovery(ask)

    def _on_edited(self, what: str = "") -> None:
        if not self.unsaved:
            self.unsaved = True
            self._update_title()
        if self.recovery_enabled and not self._closing:
            self._autosave_timer.start()

    def set_session(self, path: Path | None, unsaved: bool = False) -> None:
        """The session file the work is saved to, and whether the work has changed since."""
        self.session_path = path
        self.unsaved = unsaved
        self._update_title()

    # -- tools and editing ----------------------------------------------------------------------
    def set_tool(self, tool: str) -> None:
        for view in self.workspace.views.values():
            view.set_tool(tool)
        self.tools.actions[tool].setChecked(True)
        self.show_message(self.tools.hints[tool])

    def set_active_view(self, name: str) -> None:
        """The slice view that Page Up/Down, F and Delete act on (the last one clicked)."""
        self.active_view = name

    def undo(self) -> None:
        if self.state.active.undo():
            self.show_message("Undone")

    def redo(self) -> None:
        if self.state.active.redo():
            self.show_message("Redone")

    def delete_point(self) -> None:
        """The point under the cursor, else the last point drawn on the active view's slice."""
        self.edit_commands.delete_point()

    def clear_active_slice(self) -> None:
        self.edit_commands.clear_active_slice()

    def place_here(self) -> None:
        self.edit_commands.place_here()

    def place_automatically(self, template=None, **options) -> bool:
        """Register the image to the template in a worker and place every structure."""
        return self.auto_place.start(template, show_dialog=not self._quiet_errors(), **options)

    def _on_auto_placed(self, message: str) -> None:
        self.show_message(message + "; nudge it with Edit > Adjust automatic placement…", 10000)
        if len(self.state.active.points):
            self.schedule_refit()

    def reset_views(self) -> None:
        self.workspace.reset_views()

    def apply_window_preset(self, name: str) -> None:
        if self.state.volume is not None:
            self.state.set_window(*self.state.window_preset(WINDOW_PRESETS.get(name)))

    def _wire_volume_view(self) -> None:
        self.workspace.volume_view.defer = lambda: self.refit.is_busy
        self.plan.attach_volume_view(self.workspace.volume_view)

    def _show_factor_region(self, index: int) -> None:
        """Colour the 3D surface by the touched factor's displacement for a few seconds."""
        if index >= 0 and self.state.active.model is not None:
            self._factor_timer.start()
            self.show_message(self.factors_panel.describe(index), 4000)
        if self.workspace.volume_view is not None:
            self.workspace.volume_view.show_factor(index)

    # -- refit ----------------------------------------------------------------------------------
    def schedule_refit(self, force: bool = False) -> int | None:
        """Submit a refit of the active structure's points (newest wins); its generation."""
        return self.refit.schedule()

    def _on_refit_applied(self, result) -> None:
        self.refit_applied.emit(result)
        if self.recovery_enabled and not self._closing:
            self._autosave_timer.start()

    def wait_for_refit(self, timeout_ms: int = 10000) -> bool:
        """Process events until no refit is pending (tests, scripts)."""
        return self.refit.wait_idle(timeout_ms)

    # -- status ---------------------------------------------------------------------------------
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

    def _update_actions(self) -> None:
        update_actions(self)

    def _update_title(self) -> None:
        update_title(self)

    # -- builder tab ----------------------------------------------------------------------------
    def _show_segment_controls(self, visible: bool) -> None:
        show_segment_controls(self, visible)

    @property
    def builder(self):
        return self.tabs.builder

    def ensure_builder(self):
        return self.tabs.ensure_builder()

    def _use_built_model(self, path: str) -> None:
        """The builder's "Use for segmentation": load that model here and switch tabs."""
        self.tabs.setCurrentWidget(self.workspace)
        self._guarded(lambda: self.load_model(path))

    # -- rendering and closing ------------------------------------------------------------------
    def render_now(self) -> None:
        """Flush pending view updates (before a screenshot)."""
        self.workspace.render_now()

    def save_screenshot(self, path: str | os.PathLike) -> None:
        self.render_now()
        image = self.grab()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not image.save(str(path)):
            raise OSError(f"{path}: could not write the screenshot")

    def close_unattended(self) -> None:
        """Close without asking anything (the end of ``ssm-studio demo --record``): the
        work is a demo's, and no one is there to answer."""
        self._unattended = True
        self.close()

    def closeEvent(self, event) -> None:  # noqa: N802
        if self._closing:
            event.accept()
            return
        if not self._unattended and not self.session_actions.confirm_close():
            event.ignore()
            return
        self._closing = True
        self._autosave_timer.stop()
        self.refit.cancel()
        self.refit.wait(5000)
        for task in (self.auto_place, self.files.image_task,
                     self.features["second-image"].controller):
            task.cancel()
            task.wait(10000)
        if self.recovery_enabled:
            self.sessions.clear_recovery()
        if self.builder is not None:
            self.builder.close()
        if self.workspace.volume_view is not None:
            self.workspace.volume_view.close()
        self.closed.emit()
        event.accept()


WINDOW_SIZE = QSize(1600, 1000)  # what the window asks for, and what screenshots are rendered at
TITLE_BAR = 40                   # px the window manager's frame may add above it


def fits_screen(screen: QScreen | None) -> bool:
    """Whether :data:`WINDOW_SIZE` and a title bar fit the screen's available area. Where they
    do not (a 1280 x 800 laptop), the window opens maximised instead of with its panel and
    status bar off the screen."""
    if screen is None:
        return True
    available = screen.availableGeometry()
    return available.width() >= WINDOW_SIZE.width() \
        and available.height() >= WINDOW_SIZE.height() + TITLE_BAR


def run_gui(image: str | None = None, model: str | None = None, session: str | None = None,
            screenshot: str | None = None, tab: str = "segment", series: str | None = None,
            tour: bool = False, record: str | None = None) -> int:
    """Open the main window; with ``screenshot`` render it to that PNG and exit. Exit code."""
    app = QApplication.instance() or QApplication(sys.argv[:1])
    app.setApplicationName("SSM Studio")
    app.setStyle("Fusion")
    started = time.perf_counter()
    window = MainWindow(recovery=screenshot is None, defer_3d=screenshot is None)
    window.resize(WINDOW_SIZE)
    # screenshots and recorded tours are the same picture on any screen
    maximise = screenshot is None and record is None and not fits_screen(app.primaryScreen())
    try:
        if session:
            window.open_session(session)
        else:
            if image:
                window.load_image(image, series=series, ask=not screenshot,
                                  notify=lambda note: print(f"ssm-studio: {note}",
                                                            file=sys.stderr))
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
    if maximise:   # sized to the screen too: without a window manager, maximised does nothing
        window.setGeometry(app.primaryScreen().availableGeometry())
        window.showMaximized()
    else:
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
    QTimer.singleShot(1500, window.tabs.prepare_builder)          # then the Build tab, idle
    if tour:                                     # ssm-studio demo [--record DIR]
        from app.demo_tour import start_tour

        def play() -> None:
            window.unsaved = False
            if start_tour(window, record=record, quit_at_end=record is not None) is None \
                    and record is not None:
                window.close_unattended()

        QTimer.singleShot(800, play)
    else:
        QTimer.singleShot(0, window.offer_recovery)
    return settle_at_exit(app.exec())
