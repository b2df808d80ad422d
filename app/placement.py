"""*Place models automatically*: register the image to the models' template, then place them.

The registration (``core.registration.volumes``: affine, Mattes mutual information, multi-resolution)
runs in a :class:`app.workers.Worker` behind a progress dialog with *Cancel*; the GUI stays
responsive and a cancelled run changes nothing. Its result maps the patient image's world
onto the template's; every structure whose model lives in that template space is then placed
through it (``core.registration.placement.placement_through``), as one undoable step per structure, and the
active one is refitted if it has points. *Place here* stays for manual placement.

The placement can then be nudged by hand (:meth:`AutoPlacement.nudge`: shift and turn the
registration, ``core.registration.placement.nudged``, every placed structure together), each nudge one
step of its own undo (:meth:`AutoPlacement.undo_nudge`) and of each structure's; the read-out
(:meth:`AutoPlacement.readout`) gives the nudge so far and the contour points' mean distance
to the surfaces.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from PySide6.QtCore import QObject, Signal
from PySide6.QtWidgets import QWidget

from app.model.state import WorkspaceState
from app.workers import DialogTask


class AutoPlacement(QObject):
    """Runs one automatic placement at a time; ``finished(message)`` / ``failed(message)``."""

    finished = Signal(str)
    failed = Signal(str)
    nudged = Signal()

    def __init__(self, state: WorkspaceState, parent: QWidget | None = None):
        super().__init__(parent)
        self.state = state
        self.task = DialogTask("Place models automatically",
                               "Registering the image to the template…", parent)
        self.task.succeeded.connect(self._on_done)
        self.task.failed.connect(lambda m: self.failed.emit(f"Automatic placement failed: {m}"))
        self.task.cancelled.connect(
            lambda: self.failed.emit("Automatic placement cancelled: nothing moved"))
        self.result = None                   # the last core.registration.volumes.RegistrationResult
        self.transform: np.ndarray | None = None   # image -> template, with the nudges
        self._nudges: list[np.ndarray] = []        # the transforms before each nudge
        self._placed_ids: list[int] = []           # the structures placed through it

    def structures_at_template(self) -> list:
        """Structures whose model sits where its file puts it in its template space (not
        placed on this image: no Place here, no automatic placement, no fit moved it)."""
        from core.io.model_library import structure_info

        return [s for s in self.state.structures
                if s.model is not None and not s.locked and structure_info(s.model).template_space
                and np.allclose(s.pose, s.model.world_transform, atol=1e-6)]

    def offer(self, window, message: str = "") -> bool:
        """A new image while models sit at template coordinates: offer *Place models
        automatically* (the placement itself has Cancel); True if it was started. Declined
        (or without dialogs), the hint follows the image's ``message`` in the status bar."""
        from core.registration.volumes import default_template_path

        waiting = self.structures_at_template()
        image = self.state.image_path
        if not waiting or image is None or self.is_running:
            return False
        if Path(os.path.abspath(image)) == Path(os.path.abspath(default_template_path())):
            return False                 # the template itself: the models are in place
        names = ", ".join(s.label for s in waiting)
        question = (f"{names} still sit{'s' if len(waiting) == 1 else ''} at the template's "
                    f"coordinates, not on this image. Place the models automatically now "
                    f"(registration to the template; Cancel stops it)?")
        if not window.ask(question):
            window.show_message(f"{message + '. ' if message else ''}{names}: at template "
                                f"coordinates; Edit > Place models automatically (Ctrl+P) "
                                f"puts them on this image", 12000)
            return False
        return window.place_automatically()

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

    def _place_through(self, transform: np.ndarray, structures, keep_shape: bool) -> list[str]:
        """Place ``structures`` through ``transform`` (one undo step each)."""
        from core.registration.placement import placement_through

        placed = []
        for s in structures:
            s.checkpoint()
            pose = placement_through(s.model, transform)
            s.placement = pose.copy()
            s.last_fit = None
            s.set_surface(s.coef if keep_shape else np.zeros(s.model.n_factors), pose)
            placed.append(s.label)
        return placed

    def placed_structures(self) -> list:
        """The structures of the last automatic placement still in the workspace."""
        return [s for s in self.state.structures
                if s.id in self._placed_ids and s.model is not None and not s.locked]

    def nudge(self, rotation_deg=(0.0, 0.0, 0.0), shift_mm=(0.0, 0.0, 0.0)) -> bool:
        """Turn the registration by ``rotation_deg`` about the world x, y, z axes (through
        the placed structures' centre) and shift it by ``shift_mm``; False without a
        placement to nudge."""
        from core.registration.placement import nudged

        structures = self.placed_structures()
        if self.transform is None or not structures:
            return False
        centre = np.vstack([s.surface_vertices() for s in structures]).mean(axis=0)
        self._nudges.append(self.transform.copy())
        self.transform = nudged(self.transform, np.radians(np.asarray(rotation_deg, float)),
                                np.asarray(shift_mm, float), centre)
        self._place_through(self.transform, structures, keep_shape=True)
        self.nudged.emit()
        return True

    def undo_nudge(self) -> bool:
        """Back to the placement before the last nudge."""
        structures = self.placed_structures()
        if not self._nudges or not structures:
            return False
        self.transform = self._nudges.pop()
        self._place_through(self.transform, structures, keep_shape=True)
        self.nudged.emit()
        return True

    def can_undo_nudge(self) -> bool:
        return bool(self._nudges)

    def readout(self) -> str:
        """The nudge so far (shift and turn of the structures against the registration) and
        the contour points' mean distance to the surfaces."""
        from core.registration.placement import nudge_of

        if self.transform is None or self.result is None:
            return "No automatic placement yet: Place models automatically first."
        structures = self.placed_structures()
        centre = np.vstack([s.surface_vertices() for s in structures]).mean(axis=0) \
            if structures else np.zeros(3)
        shift, angle = nudge_of(self.result.transform, self.transform, centre)
        text = (f"Nudged {shift:.1f} mm and {angle:.1f}° from the registration "
                f"({len(self._nudges)} step(s))")
        with_points = [s for s in structures if len(s.points)]
        if with_points:
            n = sum(len(s.points) for s in with_points)
            mean = sum(s.residual_mm() * len(s.points) for s in with_points) / n
            text += f"; {n} contour point(s) {mean:.2f} mm from the surfaces on average"
        else:
            text += "; draw contour points to see their distance to the surfaces"
        return text

    def _on_done(self, result) -> None:
        structures = [s for s in self.state.structures if s.model is not None and not s.locked]
        self.result = result
        self.transform = np.asarray(result.transform, dtype=np.float64).copy()
        self._nudges.clear()
        self._placed_ids = [s.id for s in structures]
        placed = self._place_through(self.transform, structures, keep_shape=False)
        self.finished.emit(f"Placed {len(placed)} structure(s) by registration to the template "
                           f"({result.transform_class}, {result.seconds:.1f} s, metric "
                           f"{result.metric:.3f}): {', '.join(placed)}")


def _register(image, template_path: Path, progress=None, **options):
    from core.registration.placement import register_to_template

    return register_to_template(image, template_path, progress=progress, **options)
