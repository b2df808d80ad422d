"""Wiring of the planning tools: overlays in every view, uncertainty, next slice, plan export.

Slicer's Logic/Widget split: the planning model is :class:`app.model.planning.PlanningState`, the
widget :class:`app.panels.planning.PlanningPanel`; this controller connects them to the views
and calls the engine (``core.reconstruction.uncertainty`` for the posterior, ``core.planning.report`` for the
files). The posterior of a 2,000-vertex model with a few dozen factors takes a few ms, so it is
computed on the GUI thread, after each refit of the active structure, only while shown.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PySide6.QtCore import QEventLoop, QObject, Qt
from PySide6.QtWidgets import QDockWidget, QFileDialog, QScrollArea
from threadpoolctl import threadpool_limits

from app.model.planning import PlanningState
from app.model.state import FRAME_NAMES
from app.panels.planning import PlanningPanel
from app.views.plan_overlays import SlicePlanOverlay, VolumePlanOverlay
from app.workers import DialogTask
from core.geometry.planes import PLANE_AXIS
from core.planning.frames import anchored_point_weights, format_acpc
from core.planning.report import all_structures_outputs, export_all_structures, export_plan
from core.reconstruction.uncertainty import ellipsoid, fit_posterior, suggest_slice


def install_planning(window) -> PlanController:
    """The window's planning feature: its state (``.planning``), side panel (``.panel``) in
    the Planning dock (``.dock``, tabbed with the segmentation dock ``window.side_dock``), the
    Plan menu, and the plan kept with the session (``info.planning``)."""
    planning = PlanningState(window.state)
    controller = PlanController(window, planning, PlanningPanel(planning))
    window.sessions.info_providers["planning"] = planning.to_document
    # Export all: every structure (label map with names and colours, DICOM SEG + RTSTRUCT
    # when the image came from DICOM), not only the active one
    window.exports.extra_exports.append((controller.export_structures,
                                         controller.structure_outputs))
    return controller


class PlanController(QObject):
    """See the module docstring; ``window`` is the :class:`app.window.MainWindow`."""

    def __init__(self, window, planning: PlanningState, panel):
        super().__init__(window)
        self.window = window
        self.planning = planning
        self.panel = panel
        self.workspace = planning.workspace
        self.dock = self._create_dock()
        self.volume_overlay: VolumePlanOverlay | None = None
        self.show_uncertainty = False
        self.last_sd: np.ndarray | None = None
        self.slice_overlay = SlicePlanOverlay(planning)
        for view in window.workspace.views.values():
            view.overlays.append(self.slice_overlay)
        planning.events.landmarks.connect(self._repaint)
        planning.events.trajectory.connect(lambda s: self._repaint())
        planning.events.edited.connect(window._on_edited)
        self.workspace.events.surface.connect(self._on_surface)
        self.workspace.events.active.connect(self._on_surface)
        panel.message.connect(window.show_message)
        panel.uncertainty_toggled.connect(self.set_uncertainty)
        panel.suggest_requested.connect(self.suggest_next_slice)
        panel.export_requested.connect(self.export_dialog)
        self._create_menu()

    def export_dialog(self) -> None:
        """Ask for a folder and write the plan's files into it."""
        w = self.window
        folder = QFileDialog.getExistingDirectory(w, "Export the plan into folder", w._start_dir())
        if folder:
            w._guarded(lambda: w.show_message(
                f"Exported the plan: {len(self.export(folder))} file(s) in {folder}"))

    def _create_dock(self) -> QDockWidget:
        w = self.window
        scroll = QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        scroll.setWidget(self.panel)
        # as wide as the panel wants: no coordinate, button or contact row is cut at 1280 x 800
        scroll.setMinimumWidth(self.panel.minimumSizeHint().width()
                               + scroll.verticalScrollBar().sizeHint().width() + 6)
        dock = QDockWidget("Planning", w)
        dock.setObjectName("planning-dock")
        dock.setFeatures(QDockWidget.DockWidgetFeature.DockWidgetMovable)
        dock.setWidget(scroll)
        w.addDockWidget(Qt.DockWidgetArea.RightDockWidgetArea, dock)
        w.tabifyDockWidget(w.side_dock, dock)
        w.side_dock.raise_()
        return dock

    def _create_menu(self) -> None:
        """The Plan menu: landmarks, target and entry at the crosshair, export (with keys)."""
        w, panel = self.window, self.panel
        entries = [("plan-set-ac", "Set &AC at crosshair", lambda: panel.set_landmark("ac"), "Alt+A"),
                   ("plan-set-pc", "Set &PC at crosshair", lambda: panel.set_landmark("pc"), "Alt+P"),
                   ("plan-set-midline", "Set &midline point at crosshair",
                    lambda: panel.set_landmark("midline"), "Alt+M"),
                   None,
                   ("plan-set-target", "Set &target at crosshair", panel.set_target_here, "T"),
                   ("plan-model-target", "Use the &model's target",
                    lambda: self.planning.set_target(self.workspace.active, None), None),
                   ("plan-set-entry", "Set &entry at crosshair", panel.set_entry_here, "E"),
                   None,
                   ("plan-undo", "Undo plan edit", self.planning.undo, "Alt+Z"),
                   ("plan-redo", "Redo plan edit", self.planning.redo, "Alt+Shift+Z"),
                   ("plan-suggest-slice", "Suggest next slice", self.suggest_next_slice, "S"),
                   None,
                   ("plan-export", "E&xport plan…", self.export_dialog, None)]
        w.registry.add_menu("plan", "P&lan")
        for entry in entries:
            if entry is not None:
                w.registry.add(*entry)
            w.registry.place("plan", None if entry is None else entry[0])

    def attach_volume_view(self, volume_view) -> None:
        self.volume_overlay = VolumePlanOverlay(self.planning, volume_view)
        volume_view.frame_points = self.trajectory_points
        # a new target or entry: the camera frames the whole trajectory again
        self.planning.events.edited.connect(
            lambda what: what in ("target", "entry", "planning") and volume_view.reframe())
        self._repaint()

    def trajectory_points(self) -> np.ndarray | None:
        """The targets and entries of the shown structures' trajectories (the 3D view frames
        them)."""
        points = []
        for s in self.workspace.structures:
            traj = self.planning.trajectory_of(s) if s.visible else None
            if traj is not None:
                points += [traj.entry, traj.target]
        return np.array(points, dtype=np.float64) if points else None

    def _repaint(self) -> None:
        for view in self.window.workspace.views.values():
            view.update()
        if self.volume_overlay is not None:
            self.volume_overlay.update()

    # -- uncertainty ------------------------------------------------------------------------
    def posterior(self):
        """The active structure's Laplace posterior at its current fit (None without a model).
        Computed on the GUI thread (4-6 ms median, 15 ms max for 2,000 vertices with one BLAS
        thread, bench_uncertainty); callers hold BLAS to one thread: a multi-threaded BLAS on a
        loaded machine took 25-350 ms for the same small matrices."""
        s = self.workspace.active
        if s.model is None:
            return None
        pose_mode = getattr(s.last_fit, "pose_mode", "similarity")
        # a statismo model's PPCA noise (core.io.statismo puts it in info) is the model's own
        # per-vertex uncertainty, added to the posterior's
        noise = float(s.model.info.get("noise_variance", 0.0) or 0.0)
        # the fit itself (when the surface comes from one) makes the posterior pose-aware and
        # honest about correlated residuals (as bench_uncertainty measures it)
        return fit_posterior(s.model, s.points.xyz, s.coef, s.pose, pose_mode=pose_mode,
                             model_noise_var=noise, fit=s.last_fit)

    def set_uncertainty(self, shown: bool) -> None:
        self.show_uncertainty = bool(shown)
        self._on_surface()

    def _on_surface(self) -> None:
        view = self.window.workspace.volume_view
        if not self.show_uncertainty or self.workspace.active.model is None:
            self.last_sd = None
            self.slice_overlay.sd = None
            if self.volume_overlay is not None:
                self.volume_overlay.ellipsoid = None
            if view is not None:
                view.show_scalars(None)
            self._repaint()
            return
        with threadpool_limits(limits=1, user_api="blas"):   # see posterior()
            post = self.posterior()
            sd = post.vertex_sd()
            notes = post.notes(sd)
        self.last_sd = sd
        s = self.workspace.active
        self.slice_overlay.sd = (s.id, sd, float(sd.max()))
        target = self.planning.target_of(s)
        radius = None
        if target is not None:
            idx, w = anchored_point_weights(s.surface_vertices(), target)
            e = ellipsoid(target, post.point_covariance(idx, w))
            radius = e.radius_mm
            if self.volume_overlay is not None:
                self.volume_overlay.ellipsoid = e
        self.panel.show_uncertainty(float(sd.mean()), float(sd.max()), radius, notes)
        if view is not None:
            view.show_scalars(sd, "SD mm")
        self._repaint()

    def suggest_next_slice(self) -> None:
        s = self.workspace.active
        if s.model is None:
            self.window.show_message("Load a model first")
            return
        with threadpool_limits(limits=1, user_api="blas"):
            sd = self.posterior().vertex_sd()
        drawn = sorted({(FRAME_NAMES[int(f)], float(d)) for f, d in zip(s.points.frame, s.points.depth)})
        volume = self.workspace.volume
        step = float(volume.spacing.min()) if volume is not None else 1.0
        best = suggest_slice(s.surface_vertices(), sd, spacing=step, drawn=drawn)
        axis = PLANE_AXIS[best.view]
        crosshair = self.workspace.crosshair.copy()
        crosshair[axis] = best.depth
        self.workspace.set_crosshair(crosshair)
        self.window.show_message(f"Draw next on the {best.view} slice at "
                                 f"{'xyz'[axis]} = {best.depth:.1f} mm (most uncertain there)")

    # -- read-outs and export -------------------------------------------------------------------
    def acpc_text(self, world) -> str:
        """'AC-PC: lat ... mm' for the status bar, or '' without a frame."""
        frame = self.planning.frame()
        return "" if frame is None or world is None else format_acpc(frame.to_acpc(world))

    def structure_outputs(self, folder) -> list[Path]:
        """The files :meth:`export_structures` would write into ``folder``."""
        from core.cli.plan import _dicom_files

        structures = self.planning.planned_structures()
        if not structures or self.workspace.volume is None:
            return []
        return all_structures_outputs(folder, structures, self.workspace.volume, stem="all",
                                      dicom_series=_dicom_files(self.workspace.image_path),
                                      meshes=False)

    def export_structures(self, folder) -> list[Path]:
        """Every fitted structure into ``folder`` (``core.planning.report.export_all_structures``:
        ``all_labels.seg.nrrd``/``.nii.gz``/``.txt``, and ``all_structures.seg.dcm`` +
        ``all_structures.rtstruct.dcm`` referencing the source series for a DICOM image); [] without
        an image or a fitted structure."""
        from core.cli.plan import _dicom_files

        structures = self.planning.planned_structures()
        volume = self.workspace.volume
        if not structures or volume is None:
            return []
        series = _dicom_files(self.workspace.image_path)
        # ~2 s for three structures on a 1 mm head: in a worker behind a progress dialog with
        # Cancel (stops before the next file), the caller waiting for the outcome
        task = DialogTask("Export all", "Writing every structure…", self.window)
        loop = QEventLoop()
        outcome: dict = {}
        task.succeeded.connect(lambda paths: outcome.update(paths=paths))
        task.failed.connect(lambda message: outcome.update(error=message))
        task.cancelled.connect(lambda: outcome.update(cancelled=True))
        for signal in (task.succeeded, task.failed, task.cancelled):
            signal.connect(loop.quit)
        task.start(export_all_structures, folder, structures, volume, stem="all",
                   dicom_series=series, meshes=False, notes=self.window.exports.notes,
                   show_dialog=not self.window._quiet_errors())
        loop.exec()     # the GUI keeps painting; the dialog's Cancel reaches the worker
        if "error" in outcome:
            raise ValueError(outcome["error"])
        if outcome.get("cancelled"):
            self.window.show_message("Export all: every-structure files cancelled")
            return []
        return outcome["paths"]

    def export(self, folder) -> list[Path]:
        """Every plan file plus one mesh per fitted structure into ``folder``."""
        folder = Path(folder)
        structures = self.planning.planned_structures()
        if not structures:
            raise ValueError("nothing to export: no structure has a model")
        image = self.workspace.image_path.name if self.workspace.image_path else None
        # the report puts one lead on every trajectory (core.planning.report.plan_report): the
        # active structure's, else the first one planned
        leads = self.planning.leads
        lead = leads.get(self.workspace.active.id) or next(iter(leads.values()), None)
        return export_plan(folder, structures, self.workspace.volume, self.planning.frame(),
                           image=image, lead=lead)
