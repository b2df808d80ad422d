"""*Place models automatically*: register the image to the models' template, then place them.

The registration (``core.registration.volumes``: affine, Mattes mutual information, multi-resolution)
runs in a :class:`app.workers.Worker` behind a progress dialog with *Cancel*; the GUI stays
responsive and a cancelled run changes nothing. Its result maps the patient image's world
onto the template's; every structure whose model lives in that template space is then placed
through it (``core.registration.placement.placement_through``), as one undoable step per structure, and the
active one is refitted if it has points. *Place here* stays for manual placement.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import QObject, Signal
from PySide6.QtWidgets import QWidget

from app.state import WorkspaceState
from app.workers import DialogTask


class AutoPlacement(QObject):
    """Runs one automatic placement at a time; ``finished(message)`` / ``failed(message)``."""

    finished = Signal(str)
    failed = Signal(str)

    def __init__(self, state: WorkspaceState, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        self.task = DialogTask("Place models automatically",
                               "Registering the image to the template…", parent)
        self.task.succeeded.connect(self._on_done)
        self.task.failed.connect(lambda m: self.failed.emit(f"Automatic placement failed: {m}"))
        self.task.cancelled.connect(
            lambda: self.failed.emit("Automatic placement cancelled: nothing moved"))

    @property
    def is_running(self) -> bool:
        return self.task.is_running

    @property
    def worker(self):
        return self.task.worker

    def start(self, template: str | Path | None = None, show_dialog: bool = True,
              **options) -> bool:
        """Start registering the image to ``template`` (default: the bundled MNI template);
        ``options`` go to ``core.registration.volumes.register_volumes`` (e.g. ``levels_mm``)."""
        from core.registration import volumes as registration

        if self.task.is_running:
            return False
        if self.state.volume is None:
            self.failed.emit("Place models automatically: open an image first")
            return False
        if not any(s.model is not None for s in self.state.structures):
            self.failed.emit("Place models automatically: add a structure with a model first")
            return False
        template = Path(template) if template else registration.default_template_path()
        return self.task.start(_register, self.state.volume, template, show_dialog=show_dialog,
                               **options)

    def cancel(self) -> None:
        self.task.cancel()

    def wait(self, msecs: int = 60000) -> bool:
        return self.task.wait(msecs)

    def _on_done(self, result) -> None:
        from core.registration.placement import placement_through

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


def _register(image, template_path: Path, progress=None, **options):
    from core.registration.placement import register_to_template

    return register_to_template(image, template_path, progress=progress, **options)
