"""The demo tour: a scripted session on the demo data, played by the simulated user.

``ssm-studio demo`` (and *Help > Demo tour*) opens the demo image and model and plays:

1. zoom to the structure;
2. contours drawn slice by slice (axial, coronal, sagittal through the held-out caudate,
   ``resources/demo/heldout_caudate.vtk``), point by point as a user would click them
   (``core.evaluation.simulated_user.simulate_user`` on those slices), with the live refit after each
   point;
3. a sweep of the first factor's slider from -2 to +2 SD with its colour map in 3D;
4. an export (label map, surface, points) into a temporary folder (or ``DIR/export``);
5. a bilateral STN plan: left and right STN added from the library (placed on the demo
   template, which is their template), a few contours on each (the simulated user draws a
   synthetic individual: the model's own shape at +1 SD of its first factor, as the demo has
   no held-out STN), AC, PC and a midline point at the template's commissures, and per side
   an entry 60 mm above the model's target with a Medtronic 3389 lead whose tip sits
   :data:`STN_LEAD_DEPTH` past the target (contact 1 at the dorsolateral target, contacts 0-2
   in the STN, as STN leads are usually placed).

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
#: the demo template's commissures and a midline point (MNI152 2009a world mm, read off the
#: template's midsagittal slice)
TEMPLATE_AC = np.array([0.0, 2.0, -4.0])
TEMPLATE_PC = np.array([0.0, -24.0, -2.0])
TEMPLATE_MIDLINE = np.array([0.0, -10.0, 40.0])
#: entry from target (mm, before the side's sign on x): a usual frontal STN approach
STN_ENTRY_OFFSET = np.array([20.0, 25.0, 55.0])
STN_LEAD = "medtronic-3389"
# mm past the target: the 3389's contact 1 (centre 2.75 mm from the tip) at the dorsolateral
# target; on the demo STNs contacts 0-2 then lie inside (tip at the target: only contact 0)
STN_LEAD_DEPTH = 3.0


def truth_surface():
    """The held-out demo structure (vertices, faces) the simulated user draws, or None."""
    path = demo.resources_dir() / "demo" / "heldout_caudate.vtk"
    if not path.is_file():
        return None
    from core.io import load_mesh

    mesh = load_mesh(path)
    return mesh.vertices, mesh.faces


def tour_steps(window, truth, out_dir: Path | None, seed: int = 0,
               spacing: float = 3.0) -> list[tuple]:
    """The tour as a list of steps ``(kind, *args)`` for :class:`DemoTour`; ``spacing`` (mm)
    between the contour points the simulated user clicks; ``out_dir`` None: the export goes
    to a temporary folder made when the tour gets there."""
    vertices, faces = truth
    state = window.state
    steps: list[tuple] = [("message", "Demo tour: contours drawn slice by slice, the model "
                                      "follows (any key stops the tour)"),
                          ("zoom",)]
    rng = np.random.default_rng(seed)
    steps += contour_steps(state, vertices, faces, SLICES, spacing, rng)
    steps.append(("message", "Factor 1 from -2 to +2 SD: its colour map in 3D"))
    steps.extend(("factor", 0, sd) for sd in SWEEP_SD)
    steps.append(("export", out_dir))
    steps += stn_plan_steps()
    steps.append(("message", "Demo tour finished: the session is yours to edit"))
    return steps


def contour_steps(state, vertices, faces, slices, spacing: float, rng,
                  noise: float = 0.3) -> list[tuple]:
    """The simulated user's contour points of the surface (vertices, faces) on the slices
    named ``slices`` through its centre (``core.evaluation.simulated_user.simulate_user``)."""
    from core.evaluation.simulated_user import simulate_user
    from core.geometry.planes import FRAMES

    centre = vertices.mean(axis=0)
    steps: list[tuple] = []
    for name in slices:
        frame = FRAMES[name]
        depth = state.sampler.snap_depth(frame, frame.depth(centre))
        origin = np.asarray(frame.n) * depth
        user = simulate_user(vertices, faces, 1, planes=[(origin, np.asarray(frame.n))],
                             spacing=spacing, noise=noise, rng=rng)
        if len(user.points) == 0:
            continue
        steps.append(("slice", name, centre - (centre @ frame.n - depth) * np.asarray(frame.n)))
        for i, xyz in enumerate(user.points):
            steps.append(("point", xyz, name, depth, i == 0))
        steps.append(("wait_fit",))
    return steps


def stn_plan_steps() -> list[tuple]:
    """Steps of the bilateral STN plan (module docstring, 5.); the contours are made when the
    STN is in (``stn_contours``: they need the placed model)."""
    from core.io.model_library import RESOURCES_MODELS

    steps: list[tuple] = [("message", "A bilateral STN plan: both STN from the library, a few "
                                      "contours each, AC-PC, a trajectory and a lead per side")]
    for name, xyz in (("ac", TEMPLATE_AC), ("pc", TEMPLATE_PC), ("midline", TEMPLATE_MIDLINE)):
        steps.append(("landmark", name, xyz))
    for side, sign in (("left", -1.0), ("right", 1.0)):
        steps += [("add_structure", RESOURCES_MODELS / f"{side}_stn.npz"),
                  ("stn_contours",), ("wait_fit",),
                  ("entry", STN_ENTRY_OFFSET * [sign, 1.0, 1.0]), ("lead", STN_LEAD)]
    steps.append(("zoom",))
    return steps


def stn_contours(window, seed: int = 1, spacing: float = 1.5) -> list[tuple]:
    """Contour steps on the active (placed) structure: axial and coronal contours of its
    model's shape at +1 SD of the first factor (a synthetic individual)."""
    s = window.state.active
    coef = np.zeros(s.model.n_factors)
    coef[0] = 1.0
    local = s.model.instance(coef)
    world = local @ s.pose[:3, :3].T + s.pose[:3, 3]
    return contour_steps(window.state, world, s.model.faces, ("axial", "coronal"), spacing,
                         np.random.default_rng(seed), noise=0.2)


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
            # made only here, so a tour stopped before its export leaves no folder behind
            folder = step[1] or Path(tempfile.mkdtemp(prefix="ssm-studio-demo-"))
            w._guarded(lambda: w.export_all(folder))
        elif kind == "add_structure":
            w.add_structure(step[1])
        elif kind == "stn_contours":        # drawn on the structure just added and placed
            self.steps[self.index:self.index] = stn_contours(w)
        elif kind == "landmark":
            w.plan.planning.set_landmark(step[1], step[2])
        elif kind == "entry":
            s = w.state.active
            target = w.plan.planning.target_of(s)
            if target is not None:
                w.plan.planning.set_entry(s, target + step[1])
        elif kind == "lead":
            from core.planning.report import LeadChoice

            w.plan.planning.set_lead(w.state.active, LeadChoice(step[1], STN_LEAD_DEPTH))
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
    out = Path(record) / "export" if record is not None else None
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
