"""Opening files from the main window: the open dialogs, DICOM series choice, drag and drop.

What is opened is decided by the file's type (:mod:`app.formats`); reading and checking is
the :class:`app.model.controllers.SessionController`'s job. This only asks (file dialogs, the
series chooser) and routes a path to the window's ``load_model`` / ``import_points``. An
image, or a session's image, is read in a worker behind a progress dialog with Cancel (a DICOM
series of a few hundred files takes a second or more; a folder's series are listed in a worker
too) and then shown by the window's ``show_image`` / ``apply_session``. The window delegates
its ``open_*`` methods here.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from PySide6.QtWidgets import QFileDialog, QInputDialog, QMessageBox

from app import formats
from app.model.controllers import read_image
from app.workers import DialogTask
from core.io.model_library import structure_from_name
from core.io.points import is_markups_file, markups_name

OPEN_DIALOGS = {"image": ("Open image", formats.IMAGE_FILTER),
                "second": ("Open a second image (T2, FLAIR, CT…)", formats.IMAGE_FILTER),
                "model": ("Load shape model", formats.MODEL_FILTER),
                "session": ("Open session", "Sessions (*.json);;All files (*)"),
                "structure": ("Add a structure's model", "Shape models (*.npz *.h5);;All files (*)"),
                "points": ("Import points", "Points (*.csv *.tsv *.fcsv *.mrk.json *.json);;"
                                             "All files (*)")}


class FileActions:
    """Open dialogs and file routing for main window ``window``."""

    def __init__(self, window):
        self.w = window
        self.image_task = DialogTask("Opening image", "Reading the image…", window)
        self.image_task.succeeded.connect(self._on_read)
        self.image_task.failed.connect(window.show_error)
        self.image_task.cancelled.connect(lambda: window.show_message("Opening the image was cancelled"))
        self._then: Callable[[Any], None] | None = None  # what to do with the job's result

    def start_dir(self) -> str:
        """The folder file dialogs start in: the session's, else the image's, else the cwd."""
        for p in (self.w.session_path, self.w.state.image_path):
            if p is not None:
                return str(Path(p).parent)
        return str(Path.cwd())

    def resolve_image(self, path: str | os.PathLike, ask: bool | None,
                      notes: list[str], series: list | None = None) -> str | os.PathLike | None:
        """``path``, or the DICOM series chosen in it (asks the user unless ``ask`` is False:
        then the one with most files, said in ``notes``); None if the user cancelled.
        ``series``: the folder's series, listed already (:func:`app.formats.folder_series`)."""
        if ask is None:
            ask = not os.environ.get("SSM_STUDIO_NO_DIALOGS")
        chooser = None
        if ask:
            from app.series_dialog import ask_series

            chooser = lambda found: ask_series(self.w, found)  # noqa: E731
        if series is None:
            return formats.resolve_dicom_choice(path, chooser, notes.append)
        return formats.choose_series_file(path, series, chooser, notes.append)

    def open_path(self, path: str | os.PathLike, dropped: bool = False) -> None:
        """Open any supported file by its type (drag and drop, recent files); errors shown.

        A dropped model adds a structure (or, if the user says so, replaces the active
        structure's model); points go to the structure the file names, else the one the user
        picks (see :meth:`points_structure`)."""
        w, name = self.w, str(path).lower()
        try:
            if formats.is_image_path(path):
                self.open_image(path)
            elif formats.is_model_path(path):
                if dropped:
                    self.open_dropped_model(path)
                else:
                    w.load_model(path)
            elif name.endswith((".mrk.json", ".csv", ".tsv", ".fcsv")) or \
                    (name.endswith(".json") and is_markups_file(path)):
                structure = self.points_structure(path)
                if structure is not None:
                    w.import_points(path, structure)
            elif name.endswith(".json"):
                self.open_session(path)
            else:
                raise ValueError(f"{path}: unsupported file type (expected an image: .nii/.nii.gz,"
                                 " .nrrd, .mha or a DICOM folder/file; a .npz or .h5 model; a "
                                 ".json session; or .csv/.mrk.json points)")
        except (ValueError, OSError) as exc:
            w.show_error(exc)

    def open_image(self, path: str | os.PathLike) -> bool:
        """Read the image at ``path`` in a worker, then show it. A DICOM folder's series are
        listed in a worker first, and the user picks one between the two jobs."""
        self._check_idle(path)

        def listed(series: list) -> None:
            notes: list[str] = []
            resolved = self.resolve_image(path, None, notes, series=series)
            if resolved is not None:
                self._start(lambda volume: self.w.show_image(resolved, volume, notes),
                            read_image, resolved, None, path if notes else None)

        return self._start(listed, formats.folder_series, path)

    def open_session(self, path: str | os.PathLike) -> bool:
        """Open the session file ``path``: its image read in a worker, then everything
        restored (a damaged session file raises before anything changes)."""
        self._check_idle(path)
        session = self.w.sessions.read(path)
        if session.image_path is None:
            self.restore_session(session, path)
            return True
        return self._start(lambda volume: self.restore_session(session, path, volume), read_image,
                           session.image_path)

    def restore_session(self, session, path: str | os.PathLike, volume=None) -> None:
        """Apply ``session``, read from ``path`` (``volume``: its image, read already)."""
        self.w.apply_session(session, volume=volume)
        self.w.set_session(Path(path))
        self.w.show_message(f"Opened session {Path(path).name}")

    def wait_for_image(self, msecs: int = 60000) -> None:
        """Block until the image being read is shown (tests, scripts)."""
        from PySide6.QtCore import QCoreApplication

        self.image_task.wait(msecs)
        while self.image_task.is_running:  # its outcome arrives as a queued call
            QCoreApplication.processEvents()
            self.image_task.wait(msecs)    # (a folder's listing is followed by the read)

    def _check_idle(self, path: str | os.PathLike) -> None:
        if self.image_task.is_running:
            raise ValueError(f"{path}: an image is still being read; wait or cancel it first")

    def _start(self, then: Callable[[Any], None], fn: Callable[..., Any], *args: Any) -> bool:
        """Run ``fn(*args)`` behind the progress dialog; ``then(result)`` in the GUI thread."""
        self._then = then
        return self.image_task.start(fn, *args, show_dialog=not self.w._quiet_errors())

    def _on_read(self, result: Any) -> None:
        then, self._then = self._then, None
        if then is not None:
            self.w._guarded(lambda: then(result))

    def open_dialog(self, what: str) -> None:
        """The open dialog for ``what`` (a key of :data:`OPEN_DIALOGS`), then open the file."""
        w = self.w
        title, filt = OPEN_DIALOGS[what]
        path, _ = QFileDialog.getOpenFileName(w, title, self.start_dir(), filt)
        if not path:
            return
        if what == "structure":
            w.add_structure(path)
        elif what == "second":
            w._guarded(lambda: w.load_second_image(path))
        else:
            self.open_path(path)

    def open_dicom_dialog(self) -> None:
        folder = QFileDialog.getExistingDirectory(self.w, "Open DICOM folder", self.start_dir())
        if folder:
            self.open_path(folder)

    def drop(self, event) -> None:
        """Open every local file dropped on the window."""
        for url in event.mimeData().urls():
            if url.isLocalFile():
                self.open_path(url.toLocalFile(), dropped=True)
        event.acceptProposedAction()

    # -- where a dropped model or imported points go --------------------------------------
    def open_dropped_model(self, path: str | os.PathLike) -> None:
        """An empty workspace takes the model; otherwise it becomes a new structure, unless
        the user chooses to replace the active structure's model (one undo step either way)."""
        w = self.w
        active = w.state.active
        if active.model is None and len(active.points) == 0:
            w.load_model(path)
            return
        choice = "add"
        if not w._quiet_errors():
            box = QMessageBox(QMessageBox.Icon.Question, "Dropped a model",
                              f"What should {Path(path).name} do?", parent=w)
            add = box.addButton("Add as a new structure", QMessageBox.ButtonRole.AcceptRole)
            replace = box.addButton(f"Replace the model of {active.label}",
                                    QMessageBox.ButtonRole.DestructiveRole)
            box.addButton(QMessageBox.StandardButton.Cancel)
            box.setDefaultButton(add)
            box.exec()
            choice = {id(add): "add", id(replace): "replace"}.get(id(box.clickedButton()))
        if choice == "add":
            w.add_structure(path)
        elif choice == "replace":
            w.load_model(path)

    def points_structure(self, path: str | os.PathLike):
        """The structure points from ``path`` go to: the one the file names (a Slicer markups
        node's name, else the file's name), else the user's choice (the active one without
        dialogs); None if the user cancelled."""
        w = self.w
        structures = w.state.structures
        named = markups_name(path) if str(path).lower().endswith(".json") else None
        stem = Path(path).name.split(".")[0]
        for text in (named, stem):
            found = [s for s in structures if text and _names_match(text, s)]
            if len(found) == 1:
                return found[0]
        if len(structures) == 1 or w._quiet_errors():
            return w.state.active
        labels = [s.label for s in structures]
        current = structures.index(w.state.active)
        label, ok = QInputDialog.getItem(w, "Import points",
                                         f"Which structure are the points of {Path(path).name}?",
                                         labels, current, False)
        return structures[labels.index(label)] if ok else None


def _words(text: str) -> set[str]:
    return set(re.findall(r"[a-z0-9]+", text.lower()))


def _names_match(text: str, structure) -> bool:
    """Whether a file's structure name ('left_caudate', 'caudate nucleus (left)') means
    ``structure``: the words of one name hold the other's, and the sides agree."""
    info = structure_from_name(text)
    mine, theirs = _words(structure.name), _words(info.name)
    if not mine or not theirs or not (mine <= theirs or theirs <= mine):
        return False
    return not (info.side and structure.side) or info.side == structure.side
