"""Navigation and display tools of the segmentation workspace (issue 17), as Slicer and
ITK-SNAP users expect them.

:func:`install_navigation` adds to a main window:

- *Zoom to structure* (Z): every slice view centred on the active structure's cross-section
  and zoomed so that it fills about 60% of the view; the crosshair moves to its centre;
- layouts: 2 x 2, or one view maximised (F toggles the active view; View > Layout);
- 3D: show or hide the slice planes and the contour points (the labelled orientation cube
  is :mod:`app.views.orientation`);
- typed window and level (Ctrl+L), image colour maps (grey, inverted, hot, bone, viridis);
- File > Open recent (images, models and sessions, kept in the state folder as
  ``recent.json``) and *Save screenshot…* (F12).

Ctrl+wheel zooms towards the cursor (``SliceView.zoom_at``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from PySide6.QtGui import QAction, QActionGroup
from PySide6.QtWidgets import (
    QDialog,
    QDialogButtonBox,
    QDoubleSpinBox,
    QFileDialog,
    QFormLayout,
    QMenu,
)

LAYOUTS = ("2 x 2", "axial", "sagittal", "coronal", "3D")
COLORMAPS = ("grey", "inverted grey", "hot", "bone", "viridis")
RECENT_MAX = 10
STRUCTURE_FILL = 0.6   # share of the view the structure's cross-section spans after zooming
SHORTCUTS = [("Z", "Zoom every slice view to the active structure"),
             ("F", "Maximise the active view / back to 2 x 2"),
             ("Ctrl+wheel", "Zoom towards the cursor"),
             ("Ctrl+L", "Type the window and level"),
             ("F12", "Save a screenshot of the window")]


def colormap_lut(name: str) -> np.ndarray | None:
    """(256, 3) uint8 lookup table for an image colour map; None for plain grey."""
    if name == "grey":
        return None
    ramp = np.arange(256, dtype=np.uint8)
    if name == "inverted grey":
        return np.repeat(ramp[::-1, None], 3, axis=1)
    if name not in COLORMAPS:
        msg = f"colour map must be one of {', '.join(COLORMAPS)}; got {name!r}"
        raise ValueError(msg)
    from matplotlib import colormaps

    rgba = colormaps[name](np.linspace(0.0, 1.0, 256))
    return np.ascontiguousarray(np.rint(255 * rgba[:, :3]).astype(np.uint8))


def zoom_to_structure(window) -> bool:
    """Centre and zoom every slice view on the active structure; False if it has no surface."""
    s = window.state.active
    vertices = s.surface_vertices()
    if vertices is None:
        window.show_message("No structure to zoom to: load a model first")
        return False
    window.state.set_crosshair(vertices.mean(axis=0))
    for view in window.workspace.views.values():
        uv = view.frame.to_plane(vertices)[:, :2]
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        view.zoom, view.center = 1.0, None
        fit, _ = view._base()                          # px/mm at zoom 1
        span = np.maximum(hi - lo, 1.0)
        want = STRUCTURE_FILL * min(view.width() / span[0], view.height() / span[1])
        view.zoom = float(np.clip(want / fit, 0.2, 40))
        view.center = (lo + hi) / 2
        view.update()
    return True


def set_layout(window, layout: str) -> None:
    """Show all four views ("2 x 2") or one of them filling the grid."""
    if layout not in LAYOUTS:
        msg = f"layout must be one of {', '.join(LAYOUTS)}; got {layout!r}"
        raise ValueError(msg)
    ws = window.workspace
    cells = dict(ws.views)
    three_d = ws.volume_view if ws.volume_view is not None else \
        ws._layout.itemAtPosition(1, 1).widget()
    cells["3D"] = three_d
    for name, widget in cells.items():
        if widget is not None:
            widget.setVisible(layout == "2 x 2" or layout == name)
    window.current_layout = layout
    for action in getattr(window, "layout_actions", {}).values():
        action.setChecked(action.data() == layout)


def toggle_maximised(window) -> None:
    """F: the active slice view alone, or back to the 2 x 2 grid."""
    current = getattr(window, "current_layout", "2 x 2")
    set_layout(window, window.active_view if current == "2 x 2" else "2 x 2")


class WindowLevelDialog(QDialog):
    """Type the window (width) and level (centre) of the image display."""

    def __init__(self, window):
        super().__init__(window)
        self.setWindowTitle("Window and level")
        state = window.state
        lo, hi = state.data_range
        span = max(hi - lo, 1e-6)
        self.width_box = QDoubleSpinBox()
        self.width_box.setRange(span / 1000, 10 * span)
        self.width_box.setDecimals(2)
        self.width_box.setValue(state.window)
        self.level_box = QDoubleSpinBox()
        self.level_box.setRange(lo - 5 * span, hi + 5 * span)
        self.level_box.setDecimals(2)
        self.level_box.setValue(state.level)
        form = QFormLayout(self)
        form.addRow("Window (width)", self.width_box)
        form.addRow("Level (centre)", self.level_box)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok
                                   | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)

    def values(self) -> tuple[float, float]:
        return float(self.width_box.value()), float(self.level_box.value())


def ask_window_level(window) -> None:
    if window.state.volume is None:
        return
    dialog = WindowLevelDialog(window)
    if os.environ.get("SSM_STUDIO_NO_DIALOGS") or dialog.exec():
        window.state.set_window(*dialog.values())


def set_colormap(window, name: str) -> None:
    lut = colormap_lut(name)
    for view in window.workspace.views.values():
        view.colormap = lut
        view._rebuild_image()
        view.update()
    window.current_colormap = name


# -- recent files ------------------------------------------------------------------------------
def recent_path() -> Path:
    from core.session.recovery import state_dir

    return state_dir() / "recent.json"


def recent_files() -> list[str]:
    """Recently opened files, newest first (missing or unreadable list: empty)."""
    try:
        items = json.loads(recent_path().read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    return [str(p) for p in items if isinstance(p, str)][:RECENT_MAX] if isinstance(items, list) \
        else []


def remember(path: str | os.PathLike | None) -> None:
    """Put ``path`` first in the recent list (written atomically; failures are ignored)."""
    if path is None:
        return
    from core.io.atomic import atomic_write_text

    path = str(Path(path).resolve())
    items = [path] + [p for p in recent_files() if p != path]
    try:
        recent_path().parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(recent_path(), json.dumps(items[:RECENT_MAX], indent=1))
    except OSError:
        pass


def _fill_recent(window, menu: QMenu) -> None:
    menu.clear()
    items = recent_files()
    for path in items:
        menu.addAction(Path(path).name, lambda p=path: window.open_path(p)).setToolTip(path)
    if not items:
        menu.addAction("(none)").setEnabled(False)


def save_screenshot_dialog(window) -> None:
    start = str(Path(window._start_dir()) / "ssm-studio.png")
    path, _ = QFileDialog.getSaveFileName(window, "Save screenshot", start, "PNG images (*.png)")
    if path:
        window._guarded(lambda: (window.save_screenshot(path),
                                 window.show_message(f"Saved screenshot {Path(path).name}")))


# -- installation ------------------------------------------------------------------------------
def _menu(window, title: str) -> QMenu | None:
    return next((a.menu() for a in window.menuBar().actions() if a.text() == title), None)


def install_navigation(window) -> None:
    """Add the navigation and display actions and menus to ``window`` (see module docstring)."""
    from app.actions import SHORTCUTS as HELP_SHORTCUTS
    from app.actions import _action

    HELP_SHORTCUTS.extend(row for row in SHORTCUTS if row not in HELP_SHORTCUTS)
    window.current_layout, window.current_colormap = "2 x 2", "grey"
    view_menu, file_menu = _menu(window, "&View"), _menu(window, "&File")
    window.act_zoom_structure = _action(window, "&Zoom to structure",
                                        lambda: zoom_to_structure(window), "Z",
                                        "Centre and zoom the slice views on the active structure")
    window.act_maximise = _action(window, "Maximise active view", lambda: toggle_maximised(window),
                                  "F", "The active view alone / back to the 2 x 2 grid")
    window.act_window_level = _action(window, "Window and level…",
                                      lambda: ask_window_level(window), "Ctrl+L",
                                      "Type the window width and level")
    window.act_screenshot = _action(window, "Save screenshot…",
                                    lambda: save_screenshot_dialog(window), "F12",
                                    "Save the window as a PNG image")
    window.act_show_planes = _action(window, "Slice planes in 3D", lambda on: _show_3d(
        window, planes=on))
    window.act_show_points = _action(window, "Points in 3D", lambda on: _show_3d(
        window, points=on))
    for act in (window.act_show_planes, window.act_show_points):
        act.setCheckable(True)
        act.setChecked(True)
    if view_menu is not None:
        view_menu.addSeparator()
        for act in (window.act_zoom_structure, window.act_maximise):
            view_menu.addAction(act)
        layouts = view_menu.addMenu("Layout")
        group = QActionGroup(window)
        window.layout_actions = {}
        for name in LAYOUTS:
            act = QAction(name if name == "2 x 2" else f"{name} only", window)
            act.setCheckable(True)
            act.setData(name)
            act.setChecked(name == "2 x 2")
            act.triggered.connect(lambda checked=False, n=name: set_layout(window, n))
            group.addAction(act)
            layouts.addAction(act)
            window.layout_actions[name] = act
        view_menu.addAction(window.act_window_level)
        colours = view_menu.addMenu("Colour map")
        cgroup = QActionGroup(window)
        for name in COLORMAPS:
            act = QAction(name, window)
            act.setCheckable(True)
            act.setChecked(name == "grey")
            act.triggered.connect(lambda checked=False, n=name: set_colormap(window, n))
            cgroup.addAction(act)
            colours.addAction(act)
        view_menu.addSeparator()
        view_menu.addAction(window.act_show_planes)
        view_menu.addAction(window.act_show_points)
    if file_menu is not None:
        first = file_menu.actions()[2] if len(file_menu.actions()) > 2 else None
        window.recent_menu = QMenu("Open &recent", file_menu)
        window.recent_menu.aboutToShow.connect(lambda: _fill_recent(window, window.recent_menu))
        file_menu.insertMenu(first, window.recent_menu)
        file_menu.insertAction(file_menu.actions()[-1], window.act_screenshot)
    events = window.state.events
    events.image.connect(lambda: remember(window.state.image_path))
    events.model.connect(lambda: remember(window.state.active.model_path))
    window.workspace.volume_view_created.connect(lambda: _show_3d(window))


def _show_3d(window, planes: bool | None = None, points: bool | None = None) -> None:
    view = window.workspace.volume_view
    if view is None:
        return
    view.show_planes = window.act_show_planes.isChecked() if planes is None else bool(planes)
    view.show_points = window.act_show_points.isChecked() if points is None else bool(points)
    view.apply_visibility()
    view.plotter.render()


__all__ = ["install_navigation", "zoom_to_structure", "set_layout", "set_colormap",
           "colormap_lut", "recent_files", "remember"]
