"""The demo tour: a scripted session on the demo data, played by the simulated user.

``ssm-studio demo`` (and *Help > Demo tour*) opens the demo image and model and plays:

1. zoom to the structure;
2. contours drawn slice by slice (axial, coronal, sagittal through the held-out caudate,
   ``resources/demo/heldout_caudate.vtk``), point by point as a user would click them
   (``core.evaluation.simulated_user.simulate_user`` on those slices), with the live refit after each
   point;
3. a sweep of the first factor's slider from -2 to +2 SD with its colour map in 3D;
4. an export (label map, surface, points) into a temporary folder (or ``DIR/export``).

Any key stops the tour and leaves the session as it is, editable. ``--record DIR`` writes a
PNG of the window after every step (``DIR/frame_0001.png``, ...) and quits at the end.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from PySide6.QtCore import QEvent, QObject, QTimer, Signal
from PySide6.QtWidgets import QApplication

from app import demo

SLICES = ("axial", "coronal", "sagittal")
SWEEP_SD = (-2.0, -1.0, 0.0, 1.0, 2.0, 0.0)
RECORD_EVERY = 5


def truth_surface():
    """The held-out demo structure (vertices, faces) the simulated user draws, or None."""
    path = demo.resources_dir() / "demo" / "heldout_caudate.vtk"
    if not path.is_file():
        return None
    from core.io import load_mesh

    mesh = load_mesh(path)
    return mesh.vertices, mesh.faces


def tour_steps(window, truth, out_dir: Path, seed: int = 0, spacing: float = 3.0) -> list[tuple]:
    """The tour as a list of steps ``(kind, *args)`` for :class:`DemoTour`; ``spacing`` (mm)
    between the contour points the simulated user clicks."""
    from core.geometry.planes import FRAMES
    from core.evaluation.simulated_user import simulate_user

    vertices, faces = truth
    state = window.state
    centre = vertices.mean(axis=0)
    steps: list[tuple] = [("message", "Demo tour: contours drawn slice by slice, the model "
                                      "follows (any key stops the tour)"),
                          ("zoom",)]
    rng = np.random.default_rng(seed)
    for name in SLICES:
        frame = FRAMES[name]
        depth = state.sampler.snap_depth(frame, frame.depth(centre))
        origin = np.asarray(frame.n) * depth
        user = simulate_user(vertices, faces, 1, planes=[(origin, np.asarray(frame.n))],
                             spacing=spacing, noise=0.3, rng=rng)
        if len(user.points) == 0:
            continue
        steps.append(("slice", name, centre - (centre @ frame.n - depth) * np.asarray(frame.n)))
        for i, xyz in enumerate(user.points):
            steps.append(("point", xyz, name, depth, i == 0))
        steps.append(("wait_fit",))
    steps.append(("message", "Factor 1 from -2 to +2 SD: its colour map in 3D"))
    steps.extend(("factor", 0, sd) for sd in SWEEP_SD)
    steps.append(("export", out_dir))
    steps.append(("message", "Demo tour finished: the session is yours to edit"))
    return steps


class DemoTour(QObject):
    """Plays :func:`tour_steps` on a main window with a timer; any key stops it.

    Signals: ``finished(bool)`` -- True when the tour ran to the end, False when stopped.
    """

    finished = Signal(bool)

    def __init__(self, window, steps: list[tuple], interval_ms: int = 120,
                 record: str | Path | None = None):
        super().__init__(window)
        self.window = window
        self.steps = list(steps)
        self.index = 0
        self.frames: list[Path] = []
        self.record = None if record is None else Path(record)
        self.running = False
        self._timer = QTimer(self)
        self._timer.setInterval(int(interval_ms))
        self._timer.timeout.connect(self._step)

    def start(self) -> None:
        if self.record is not None:
            self.record.mkdir(parents=True, exist_ok=True)
        self.running = True
        QApplication.instance().installEventFilter(self)
        self._timer.start()

    def stop(self, completed: bool = False) -> None:
        if not self.running:
            return
        self.running = False
        self._timer.stop()
        QApplication.instance().removeEventFilter(self)
        if not completed:
            self.window.show_message("Demo tour stopped: the session is yours to edit")
        self.finished.emit(completed)

    def eventFilter(self, obj, event) -> bool:  # noqa: N802 - Qt API
        if self.running and event.type() == QEvent.Type.KeyPress:
            self.stop()
            return True          # the key only stops the tour
        return False

    def _step(self) -> None:
        w = self.window
        if self.index >= len(self.steps):
            self.stop(completed=True)
            return
        step = self.steps[self.index]
        kind = step[0]
        if kind == "wait_fit" and w.refit.is_busy:
            return                                   # the live refit is still running
        self.index += 1
        if kind == "message":
            w.show_message(step[1], 8000)
        elif kind == "zoom":
            from app.panels.navigation import zoom_to_structure

            zoom_to_structure(w)
        elif kind == "slice":
            w.state.set_crosshair(step[2])
            w.set_active_view(step[1])
        elif kind == "point":
            _, xyz, name, depth, first = step
            w.state.active.add_point(xyz, name, depth, checkpoint=first)
        elif kind == "factor":
            w.factors_panel.set_factor_sd(step[1], step[2])
            w._show_factor_region(step[1])
        elif kind == "export":
            w._guarded(lambda: w.export_all(step[1]))
        # a frame after each step, but only every RECORD_EVERY-th contour point (a 3D
        # render under software OpenGL costs ~0.5 s)
        if self.record is not None and kind != "wait_fit" and \
                (kind != "point" or step[4] or self.index % RECORD_EVERY == 0):
            w.render_now()
            path = self.record / f"frame_{len(self.frames) + 1:04d}.png"
            if w.grab().save(str(path)):
                self.frames.append(path)


def start_tour(window, record: str | Path | None = None, interval_ms: int = 120,
               quit_at_end: bool = False, spacing: float = 3.0) -> DemoTour | None:
    """Load the demo data if needed and play the tour; None (with a message) without it."""
    truth = truth_surface()
    if truth is None or demo.demo_model() is None:
        window.show_message("Demo tour unavailable: resources/demo is incomplete")
        return None
    if window.state.volume is None or window.state.active.model is None:
        window.load_demo()
    out = Path(record) / "export" if record is not None else \
        Path(tempfile.mkdtemp(prefix="ssm-studio-demo-"))
    tour = DemoTour(window, tour_steps(window, truth, out, spacing=spacing), interval_ms, record)
    if quit_at_end:     # a recording has nobody to answer "save before closing?"
        tour.finished.connect(lambda completed: window.close_unattended())
    tour.start()
    return tour


class DemoTourFeature:
    """The window's feature ``"demo-tour"``: *Help > Demo tour* plays :func:`start_tour`
    (the tour is a child of the window: it lives as long as it plays)."""

    def __init__(self, window):
        self.action = window.registry.add(
            "demo-tour", "Demo tour", lambda: start_tour(window),
            tip="Play a scripted session on the demo data (any key stops it)")
        window.registry.place("help", "demo-tour")
