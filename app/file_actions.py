"""Opening files from the main window: the open dialogs, DICOM series choice, drag and drop.

What is opened is decided by the file's type (:mod:`app.formats`); reading and checking is
the :class:`app.controllers.SessionController`'s job. This only asks (file dialogs, the
series chooser) and routes a path to the window's ``load_image`` / ``load_model`` /
``import_points`` / ``open_session``. The window delegates its ``open_*`` methods here.
"""

from __future__ import annotations

import os
from pathlib import Path

from PySide6.QtWidgets import QFileDialog

from app import formats
from core.io.points import is_markups_file

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

    def start_dir(self) -> str:
        """The folder file dialogs start in: the session's, else the image's, else the cwd."""
        for p in (self.w.session_path, self.w.state.image_path):
            if p is not None:
                return str(Path(p).parent)
        return str(Path.cwd())

    def resolve_image(self, path: str | os.PathLike, ask: bool | None,
                      notes: list[str]) -> str | os.PathLike | None:
        """``path``, or the DICOM series chosen in it (asks the user unless ``ask`` is False:
        then the one with most files, said in ``notes``); None if the user cancelled."""
        if ask is None:
            ask = not os.environ.get("SSM_STUDIO_NO_DIALOGS")
        chooser = None
        if ask:
            from app.series_dialog import ask_series

            chooser = lambda found: ask_series(self.w, found)  # noqa: E731
        return formats.resolve_dicom_choice(path, chooser, notes.append)

    def open_path(self, path: str | os.PathLike) -> None:
        """Open any supported file by its type (drag and drop, recent files); errors shown."""
        w, name = self.w, str(path).lower()
        try:
            if formats.is_image_path(path):
                w.load_image(path)
            elif formats.is_model_path(path):
                w.load_model(path)
            elif name.endswith((".mrk.json", ".csv", ".tsv", ".fcsv")) or \
                    (name.endswith(".json") and is_markups_file(path)):
                w.import_points(path)
            elif name.endswith(".json"):
                w.open_session(path)
            else:
                raise ValueError(f"{path}: unsupported file type (expected an image: .nii/.nii.gz,"
                                 " .nrrd, .mha or a DICOM folder/file; a .npz or .h5 model; a "
                                 ".json session; or .csv/.mrk.json points)")
        except (ValueError, OSError) as exc:
            w.show_error(exc)

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
                self.open_path(url.toLocalFile())
        event.acceptProposedAction()
