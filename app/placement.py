"""*Place models automatically*: register the image to the models' template, then place them.

The registration (``core.registration``: affine, Mattes mutual information, multi-resolution)
runs in a :class:`app.workers.Worker` behind a progress dialog with *Cancel*; the GUI stays
responsive and a cancelled run changes nothing. Its result maps the patient image's world
onto the template's; every structure whose model lives in that template space is then placed
through it (``core.placement.placement_through``), as one undoable step per structure, and the
active one is refitted if it has points. *Place here* stays for manual placement.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import QObject, Qt, Signal
from PySide6.QtWidgets import QProgressDialog, QWidget

from app.state import WorkspaceState
from app.workers import Worker


class AutoPlacement(QObject):
    """Runs one automatic placement at a time; ``finished(message)`` / ``failed(message)``."""

    finished = Signal(str)
    failed = Signal(str)

    def __init__(self, state: WorkspaceState, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        self.worker: Worker | None = None
        self.dialog: QProgressDialog | None = None
        self._parent = parent

    @property
    def is_running(self) -> bool:
        return self.worker is not None

    def start(self, template: str | Path | None = None, show_dialog: bool = True,
              **options) -> bool:
        """Start registering the image to ``template`` (default: the bundled MNI template);
        ``options`` go to ``core.registration.register_volumes`` (e.g. ``levels_mm``)."""
        from core import registration

        if self.worker is not None:
            return False
        if self.state.volume is None:
            self.failed.emit("Place models automatically: open an image first")
            return False
        if not any(s.model is not None for s in self.state.structures):
            self.failed.emit("Place models automatically: add a structure with a model first")
            return False
        template = Path(template) if template else registration.default_template_path()
        image = self.state.volume
        self.worker = Worker(_register, image, template, **options)
        self.worker.succeeded.connect(self._on_done)
        self.worker.failed.connect(self._on_failed)
        self.worker.cancelled.connect(self._on_cancelled)
        if show_dialog:
            self.dialog = QProgressDialog("Registering the image to the template…", "Cancel",
                                          0, 100, self._parent)
            self.dialog.setWindowTitle("Place models automatically")
            self.dialog.setWindowModality(Qt.WindowModality.WindowModal)
            self.dialog.setMinimumDuration(0)
            self.dialog.canceled.connect(self.cancel)
            self.worker.progress.connect(
                lambda f, m: self.dialog is not None and self.dialog.setValue(int(100 * f)))
        self.worker.start()
        return True

    def cancel(self) -> None:
        if self.worker is not None:
            self.worker.cancel()

    def wait(self, msecs: int = 60000) -> bool:
        return self.worker.wait(msecs) if self.worker is not None else True

    def _close(self) -> None:
        self.worker = None
        if self.dialog is not None:
            self.dialog.canceled.disconnect(self.cancel)
            self.dialog.close()
            self.dialog = None

    def _on_done(self, result) -> None:
        from core.placement import placement_through

        self._close()
        placed = []
        for s in self.state.structures:
            if s.model is None or s.locked:
                continue
            s.checkpoint()
            pose = placement_through(s.model, result.transform)
            s.placement = pose.copy()
            s.last_fit = None
            s.set_surface(np.zeros(s.model.n_factors), pose)
            placed.append(s.label)
        self.finished.emit(f"Placed {len(placed)} structure(s) by registration to the template "
                           f"({result.transform_class}, {result.seconds:.1f} s, metric "
                           f"{result.metric:.3f}): {', '.join(placed)}")

    def _on_failed(self, message: str) -> None:
        self._close()
        self.failed.emit(f"Automatic placement failed: {message}")

    def _on_cancelled(self) -> None:
        self._close()
        self.failed.emit("Automatic placement cancelled: nothing moved")


def _register(image, template_path: Path, progress=None, **options):
    from core.placement import register_to_template

    return register_to_template(image, template_path, progress=progress, **options)
