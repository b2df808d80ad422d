"""The window's file dialogs and questions around exports, sessions and crash recovery.

What happens is in the controllers (:mod:`app.model.controllers`); these only ask the user (file
dialogs, yes/no questions through the window's ``ask``, which tests replace) and report in
the window's status bar. The window delegates its ``export_*`` and session methods here.
"""

from __future__ import annotations

import os
from pathlib import Path

from PySide6.QtWidgets import QFileDialog, QMessageBox

from app import formats
from app.model.controllers import RECOVERED_PATH_KEY
from app.workers import error_message

EXPORTS = {"labels": ("label map", formats.LABEL_FILTER, "segmentation.nii.gz"),
           "mesh": ("surface mesh", "Meshes (*.vtk *.vtp *.stl *.ply *.obj)", "surface.vtk"),
           "points": ("points", "CSV (*.csv);;Slicer markups (*.mrk.json)", "points.csv")}


class ExportActions:
    """Export dialogs: say why nothing can be exported before any dialog, confirm an unknown
    orientation, and never overwrite an earlier export without asking."""

    def __init__(self, window):
        self.w = window

    def confirm_orientation(self) -> bool:
        """Exports of an image whose orientation is unknown need an explicit yes."""
        w = self.w
        return w.state.orientation_known or w.ask(
            "The image's file has neither sform nor qform: its orientation is unknown and left "
            "and right may be swapped in what you export. Export anyway?")

    def confirm_fit(self) -> bool:
        """Exporting a fit flagged as implausible needs an explicit yes."""
        w = self.w
        warnings = w.state.active.fit_info.warnings
        return not warnings or w.ask("The fit looks implausible: " + "; ".join(warnings)
                                     + ". Export it anyway?")

    def export_all(self, folder: str | os.PathLike) -> list[Path]:
        w = self.w
        if not w.confirm_orientation():
            w.show_message("Export cancelled: the image's orientation is unknown")
            return []
        if not self.confirm_fit():
            w.show_message("Export cancelled: the fit looks implausible")
            return []
        written = w.exports.export_all(folder)
        w.show_message("; ".join([f"Exported {len(written)} file(s) to {folder}"]
                                 + w.exports.notes))
        return written

    def export_dialog(self, what: str) -> None:
        w = self.w
        problem = w.exports.nothing_to_export(what)
        if problem:                                  # say so before any file dialog
            w.show_error(problem)
            return
        if not w.confirm_orientation():
            w.show_message("Export cancelled: the image's orientation is unknown")
            return
        if what != "points" and not self.confirm_fit():
            w.show_message("Export cancelled: the fit looks implausible")
            return
        title, filt, default = EXPORTS[what]
        path, _ = QFileDialog.getSaveFileName(w, f"Export {title}",
                                              str(Path(w._start_dir()) / default), filt)
        if path:
            w._guarded(lambda: w.show_message(getattr(w.exports, f"export_{what}")(path)))

    def export_all_dialog(self) -> None:
        w = self.w
        problem = w.exports.nothing_to_export("all")
        if problem:
            w.show_error(problem)
            return
        folder = QFileDialog.getExistingDirectory(w, "Export into folder", w._start_dir())
        if not folder:
            return
        existing = w.exports.existing_outputs(folder)
        if existing and not w.ask(f"{', '.join(p.name for p in existing)} already exist in "
                                  f"{folder}. Overwrite?"):
            w.show_message("Export cancelled: nothing overwritten")
            return
        w._guarded(lambda: w.export_all(folder))


class SessionActions:
    """Save-session dialog, autosave and the recovery offer at start-up."""

    def __init__(self, window):
        self.w = window

    def save_session(self, ask: bool = False, path: str | os.PathLike | None = None) -> bool:
        w = self.w
        if w.state.image_path is None:            # say so before any file dialog
            w.show_error("nothing to save: open an image first")
            return False
        target = Path(path) if path else w.session_path
        if target is None or ask:
            chosen, _ = QFileDialog.getSaveFileName(w, "Save session",
                                                    str(Path(w._start_dir()) / "session.json"),
                                                    "Sessions (*.json)")
            if not chosen:
                return False
            target = Path(chosen)
        message = []
        if not w._guarded(lambda: message.append(w.sessions.save(target, w.fit_panel.settings))):
            return False
        w.set_session(target)
        w.show_message(message[0])
        return True

    def apply_session(self, session, volume=None) -> None:
        """Restore image, model, fit, points, window, crosshair and plan from a Session
        (without a refit: the stored fit is shown; ``volume``: its image, read already)."""
        w = self.w
        w.refit.cancel()
        with w.refit.suspended():
            fit = w.sessions.apply(session, volume)
            was_blocked = w.fit_panel.blockSignals(True)
            try:
                w.fit_panel.set_settings(fit.get("method"), fit.get("pose"),
                                         fit.get("prior_weight"), fit.get("pose_spread"))
            finally:
                w.fit_panel.blockSignals(was_blocked)
        w.plan.planning.apply_document(session.info.get("planning"))
        w._update_actions()

    def confirm_close(self) -> bool:
        """Unsaved work: ask to save it before closing; False if the user cancels (or the save
        fails)."""
        w = self.w
        if not w.unsaved or w._quiet_errors() or w.state.image_path is None:
            return True
        buttons = QMessageBox.StandardButton
        answer = QMessageBox.question(w, "Unsaved changes", "Save the session before closing?",
                                      buttons.Save | buttons.Discard | buttons.Cancel, buttons.Save)
        return answer != buttons.Cancel and (answer != buttons.Save or w.save_session())

    def write_recovery(self) -> None:
        w = self.w
        if not w.recovery_enabled:
            return
        try:     # with the session's file, so that Ctrl+S after a recovery saves there
            w.sessions.write_recovery(w.fit_panel.settings, w.session_path)
        except (ValueError, OSError) as exc:
            w.statusBar().showMessage(f"Autosave failed: {error_message(exc)}", 8000)

    def offer_recovery(self, ask=None) -> bool:
        """If a recovery file exists, ask (``ask(text) -> bool``) and restore it; True if restored."""
        w = self.w
        if ask is None and w._quiet_errors():
            # no one to answer (SSM_STUDIO_NO_DIALOGS): the question waits for a start that
            # can ask it, with the left-over files unclaimed (a modal box here kept the app
            # from ever ending)
            return False
        try:
            pending = w.sessions.pending_recovery()
        except (ValueError, OSError) as exc:
            w.show_message(f"Recovery file unreadable, ignored: {error_message(exc)}")
            return False
        if pending is None:
            return False
        session, question = pending
        ask = ask or (lambda text: QMessageBox.question(w, "Recover unsaved work?", text)
                      == QMessageBox.StandardButton.Yes)
        if not ask(question):
            w.sessions.clear_recovery()
            return False
        if not w._guarded(lambda: w.apply_session(session)):
            return False
        saved_as = (session.info or {}).get(RECOVERED_PATH_KEY)
        # recovered work is not saved anywhere yet
        w.set_session(Path(saved_as) if saved_as else None, unsaved=True)
        w.show_message("Recovered the unsaved session")
        return True
