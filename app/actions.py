"""The main window's actions, menus and toolbar (what each menu entry and key calls)."""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtGui import QKeySequence
from PySide6.QtWidgets import QMessageBox, QToolBar

from app import formats
from app.panels.tools import WINDOW_PRESETS
from core import __version__

SHORTCUTS = [
    ("Ctrl+O", "Open image"), ("Ctrl+M", "Load model"), ("Ctrl+Shift+O", "Open session"),
    ("Ctrl+S", "Save session"), ("Ctrl+E", "Export label map, mesh and points"),
    ("Ctrl+Z", "Undo"), ("Ctrl+Shift+Z", "Redo"),
    ("Delete", "Remove the point under the cursor (else the last one on this slice)"),
    ("Page Up / Page Down, wheel", "Next / previous slice in the active view"),
    ("N / D / W", "Tool: navigate / draw contour / window-level"),
    ("P", "Place the model at the crosshair"), ("Ctrl+P", "Place models automatically"),
    ("R", "Reset the views"),
    ("F9", "Show / hide the side panel"),
    ("Left click (navigate)", "Move the crosshair"),
    ("Left click or drag (draw)", "Add contour points on the slice"),
    ("Ctrl+left click (draw)", "Delete the point under the cursor"),
    ("Shift+left drag", "Window/level"), ("Right drag / Ctrl+wheel", "Zoom"),
    ("Middle drag", "Pan"),
    ("Alt+A / Alt+P / Alt+M", "Plan: set AC / PC / midline point at the crosshair"),
    ("T / E", "Plan: set the active structure's target / entry at the crosshair"),
    ("S", "Plan: move to the suggested next slice (most uncertain)"),
    ("Alt+Z / Alt+Shift+Z", "Plan: undo / redo a landmark, target or entry edit"),
]

ABOUT = (f"<b>SSM Studio {__version__}</b><br>Shape-model-based interactive segmentation of "
         "deep brain structures.<br>Slice views in world RAS coordinates, radiological "
         "convention (patient right on screen left).<br><br>Demo data: the MNI ICBM152 2009a "
         "nonlinear symmetric template (Fonov et al., NeuroImage 2011; copyright McConnell "
         "Brain Imaging Centre). The STN, GPi, GPe, red nucleus and substantia nigra models "
         "are derived from the CIT168 subcortical atlas (Pauli, Nili &amp; Tyszka, Scientific "
         "Data 2018, doi:10.1038/sdata.2018.63; CC BY 4.0).")


def add_help_shortcuts(rows: list[tuple[str, str]]) -> None:
    """Rows ``(keys, what they do)`` a feature adds to Help > Keyboard shortcuts."""
    SHORTCUTS.extend(row for row in rows if row not in SHORTCUTS)


def show_shortcuts(parent) -> None:
    rows = "".join(f"<tr><td><b>{k}</b></td><td>&nbsp;&nbsp;{v}</td></tr>" for k, v in SHORTCUTS)
    QMessageBox.information(parent, "Keyboard and mouse", f"<table>{rows}</table>")


def create_actions(w) -> None:
    """Register the actions of main window ``w``'s own menus (File, Edit, View, Help) by id."""
    key, state, a = QKeySequence.StandardKey, w.state, w.registry.add
    a("open-image", "&Open image…", lambda: w.open_dialog("image"), key.Open,
      "Open an image: NIfTI, NRRD, MetaImage, or one file of a DICOM series")
    a("open-dicom", "Open &DICOM folder…", w.open_dicom_dialog, None,
      "Open a DICOM series from its folder")
    a("load-model", "Load &model…", lambda: w.open_dialog("model"), "Ctrl+M",
      "Load a shape model (.npz, or statismo/Scalismo .h5)")
    a("open-session", "Open &session…", lambda: w.open_dialog("session"), "Ctrl+Shift+O")
    a("save-session", "&Save session", w.save_session, key.Save)
    a("save-session-as", "Save session &as…", lambda: w.save_session(ask=True))
    a("export-all", "&Export all…", w.export_all_dialog, "Ctrl+E",
      "Export the label map (NIfTI), the surface mesh and the points")
    a("export-labels", "Export label map…", lambda: w.export_dialog("labels"))
    a("export-mesh", "Export surface mesh…", lambda: w.export_dialog("mesh"))
    a("export-points", "Export points…", lambda: w.export_dialog("points"))
    a("import-points", "Import points…", lambda: w.open_dialog("points"))
    a("quit", "&Quit", w.close, key.Quit)
    a("undo", "&Undo", w.undo, "Ctrl+Z")
    a("redo", "&Redo", w.redo, "Ctrl+Shift+Z")
    a("delete-point", "&Delete point", w.delete_point, key.Delete,
      "Remove the point under the cursor, else the last one on this slice")
    a("clear-slice", "Clear &slice", w.clear_active_slice, None,
      "Remove the points of the active view's slice")
    a("clear-points", "Clear &all points", state.active.clear_points)
    a("place-here", "&Place model here", w.place_here, "P",
      "Move the model so that its centre is at the crosshair")
    a("auto-place", "Place models &automatically", w.place_automatically, "Ctrl+P",
      "Register the image to the models' template (affine, mutual information) and place "
      "every structure through it")
    a("reset-pose", "Reset model pose", state.active.reset_placement, None,
      "Back to the model's stored position and mean shape")
    a("next-slice", "Next slice", lambda: state.step_slice(w.active_view, 1),
      QKeySequence(Qt.Key.Key_PageUp))
    a("previous-slice", "Previous slice", lambda: state.step_slice(w.active_view, -1),
      QKeySequence(Qt.Key.Key_PageDown))
    a("reset-views", "&Reset views", w.reset_views, "R")
    a("side-panel", "Side &panel", lambda checked=False: None, "F9",
      "Show or hide the side panel (more room for the views)", checkable=True, checked=True)
    a("shortcuts", "&Keyboard shortcuts", lambda: show_shortcuts(w), key.HelpContents)
    a("about", "&About SSM Studio", lambda: QMessageBox.about(w, "About SSM Studio", ABOUT))


def create_menus(w) -> None:
    """The menu bar of main window ``w``: menus ``file``, ``edit``, ``view`` and ``help`` (and
    ``view.presets``) in its registry, their entries by action id."""
    r = w.registry
    menus = {
        ("file", "&File"): ("open-image", "open-dicom", "load-model", None, "open-session",
                            "save-session", "save-session-as", None, "import-points",
                            "export-all", "export-labels", "export-mesh", "export-points", None,
                            "quit"),
        ("edit", "&Edit"): ("undo", "redo", None, "delete-point", "clear-slice", "clear-points",
                            None, "place-here", "auto-place", "reset-pose"),
        ("view", "&View"): (*(f"tool-{t}" for t in w.tools.actions),),
        ("help", "&Help"): ("shortcuts", "about"),
    }
    for (menu_id, title), entries in menus.items():
        r.add_menu(menu_id, title)
        r.place(menu_id, *entries)
        if menu_id == "view":   # more tools go before this separator (app.panels.editing)
            r.separator("view", "view.tools-end")
            r.place("view", "next-slice", "previous-slice", "reset-views", "side-panel")
    presets = r.add_menu("view.presets", "Window/level preset", parent="view")
    for name in WINDOW_PRESETS:
        presets.addAction(name, lambda n=name: w.apply_window_preset(n))


def create_toolbar(w) -> QToolBar:
    """The main toolbar of main window ``w``."""
    bar = QToolBar("Main")
    bar.setObjectName("main-toolbar")
    bar.setMovable(False)
    r = w.registry
    for act in (r["open-image"], r["load-model"], r["save-session"], r["export-all"], None,
                *w.tools.actions.values(), None, r["undo"], r["redo"], r["place-here"],
                r["reset-views"]):
        bar.addSeparator() if act is None else bar.addAction(act)
    w.addToolBar(Qt.ToolBarArea.TopToolBarArea, bar)
    return bar


def update_actions(w) -> None:
    """Enable the actions of main window ``w`` that have something to act on."""
    state, r = w.state, w.registry
    r["undo"].setEnabled(state.active.can_undo())
    r["redo"].setEnabled(state.active.can_redo())
    has_model = state.active.model is not None
    for act in ("place-here", "auto-place", "reset-pose", "export-labels", "export-mesh"):
        r[act].setEnabled(has_model)
    has_points = len(state.active.points) > 0
    for act in ("delete-point", "clear-slice", "clear-points", "export-points"):
        r[act].setEnabled(has_points)


def update_title(w) -> None:
    """Window title: session, image and model names, '*' when there is unsaved work."""
    state = w.state
    parts = [formats.display_name(state.image_path)] if state.image_path else []
    parts += [state.active.model_path.name] if state.active.model_path is not None else []
    if w.session_path is not None:
        parts.insert(0, w.session_path.name)
    title = "SSM Studio" + (" — " + " + ".join(parts) if parts else "")
    w.setWindowTitle(title + (" *" if w.unsaved else ""))


def show_segment_controls(w, visible: bool) -> None:
    """The side panel, the toolbar and the drawing tools belong to the Segment tab only."""
    w.toolbar.setVisible(visible)  # the Build tab has its own buttons (issue 17, 8)
    r = w.registry
    shown = visible and r["side-panel"].isChecked()     # F9 hides the side docks
    w.side_dock.setVisible(shown)
    w.plan.dock.setVisible(shown)
    w.cursor_label.setVisible(visible)
    w.fit_label.setVisible(visible)
    for act in (*w.tools.actions.values(), r["undo"], r["redo"], r["place-here"],
                r["reset-views"]):
        act.setVisible(visible)
