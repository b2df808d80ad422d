"""Navigation and display tools of the segmentation workspace (issue 17), as Slicer and
ITK-SNAP users expect them.

:class:`Navigation` (the window's feature ``"navigation"``) registers on the main window:

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
from PySide6.QtWidgets import QDialog, QDialogButtonBox, QDoubleSpinBox, QFileDialog, QFormLayout

from app.actions import add_help_shortcuts

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


def save_screenshot_dialog(window) -> None:
    start = str(Path(window._start_dir()) / "ssm-studio.png")
    path, _ = QFileDialog.getSaveFileName(window, "Save screenshot", start, "PNG images (*.png)")
    if path:
        window._guarded(lambda: (window.save_screenshot(path),
                                 window.show_message(f"Saved screenshot {Path(path).name}")))


# -- the feature -------------------------------------------------------------------------------
class Navigation:
    """The navigation and display actions and menus of main window ``window`` (see the module
    docstring), registered in ``window.registry``; the current layout and colour map."""

    def __init__(self, window):
        add_help_shortcuts(SHORTCUTS)
        self.window = window
        self.layout, self.colormap = "2 x 2", "grey"
        r = window.registry
        self.zoom_structure = r.add("zoom-structure", "&Zoom to structure",
                                    lambda: zoom_to_structure(window), "Z",
                                    "Centre and zoom the slice views on the active structure")
        self.maximise = r.add("maximise", "Maximise active view", self.toggle_maximised, "F",
                              "The active view alone / back to the 2 x 2 grid")
        self.window_level = r.add("window-level", "Window and level…",
                                  lambda: ask_window_level(window), "Ctrl+L",
                                  "Type the window width and level")
        self.screenshot = r.add("screenshot", "Save screenshot…",
                                lambda: save_screenshot_dialog(window), "F12",
                                "Save the window as a PNG image")
        self.show_planes = r.add("show-planes", "Slice planes in 3D",
                                 lambda on: self.show_3d(planes=on), checkable=True, checked=True)
        self.show_points = r.add("show-points", "Points in 3D",
                                 lambda on: self.show_3d(points=on), checkable=True, checked=True)
        r.place("view", None, "zoom-structure", "maximise")
        r.add_menu("view.layout", "Layout", parent="view")
        group = QActionGroup(window)
        self.layout_actions: dict[str, QAction] = {}
        for name in LAYOUTS:
            act = r.add(f"layout-{name.replace(' ', '')}",
                        name if name == "2 x 2" else f"{name} only",
                        lambda checked=False, n=name: self.set_layout(n),
                        checkable=True, checked=name == "2 x 2")
            group.addAction(act)
            self.layout_actions[name] = act
        r.place("view.layout", *self.layout_actions.values())
        r.place("view", "window-level")
        r.add_menu("view.colormap", "Colour map", parent="view")
        cgroup = QActionGroup(window)
        for name in COLORMAPS:
            act = r.add(f"colormap-{name.replace(' ', '-')}", name,
                        lambda checked=False, n=name: self.set_colormap(n),
                        checkable=True, checked=name == "grey")
            cgroup.addAction(act)
            r.place("view.colormap", act)
        r.place("view", None, "show-planes", "show-points")
        self.recent_menu = r.add_menu("file.recent", "Open &recent", parent="file",
                                      before="load-model")
        self.recent_menu.aboutToShow.connect(self.fill_recent)
        r.place("file", "screenshot", before="quit")
        events = window.state.events
        events.image.connect(lambda: remember(window.state.image_path))
        events.model.connect(lambda: remember(window.state.active.model_path))
        window.workspace.volume_view_created.connect(lambda: self.show_3d())

    def set_layout(self, layout: str) -> None:
        """Show all four views ("2 x 2") or one of them filling the grid."""
        if layout not in LAYOUTS:
            msg = f"layout must be one of {', '.join(LAYOUTS)}; got {layout!r}"
            raise ValueError(msg)
        ws = self.window.workspace
        cells = dict(ws.views)
        cells["3D"] = ws.volume_view if ws.volume_view is not None else \
            ws._layout.itemAtPosition(1, 1).widget()
        for name, widget in cells.items():
            if widget is not None:
                widget.setVisible(layout == "2 x 2" or layout == name)
        self.layout = layout
        for name, action in self.layout_actions.items():
            action.setChecked(name == layout)

    def toggle_maximised(self) -> None:
        """F: the active slice view alone, or back to the 2 x 2 grid."""
        self.set_layout(self.window.active_view if self.layout == "2 x 2" else "2 x 2")

    def set_colormap(self, name: str) -> None:
        lut = colormap_lut(name)
        for view in self.window.workspace.views.values():
            view.colormap = lut
            view._rebuild_image()
            view.update()
        self.colormap = name

    def fill_recent(self) -> None:
        """File > Open recent's entries, filled when it opens."""
        menu = self.recent_menu
        menu.clear()
        items = recent_files()
        for path in items:
            menu.addAction(Path(path).name,
                           lambda p=path: self.window.open_path(p)).setToolTip(path)
        if not items:
            menu.addAction("(none)").setEnabled(False)

    def show_3d(self, planes: bool | None = None, points: bool | None = None) -> None:
        """The slice planes and the points in the 3D view, as the View menu's toggles say."""
        view = self.window.workspace.volume_view
        if view is None:
            return
        view.show_planes = self.show_planes.isChecked() if planes is None else bool(planes)
        view.show_points = self.show_points.isChecked() if points is None else bool(points)
        view.apply_visibility()
        view.plotter.render()


__all__ = ["Navigation", "zoom_to_structure", "colormap_lut", "recent_files", "remember"]
