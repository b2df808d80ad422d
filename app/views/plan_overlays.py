"""The plan drawn in the views: landmarks, targets, entries and trajectories; the probe's eye.

- :class:`SlicePlanOverlay` paints in every slice view (a painter of ``SliceView.overlays``):
  AC, PC and the midline point as labelled diamonds on their slice, each structure's target
  (a cross in its colour) and entry, and each trajectory as its projection on the slice
  (dashed) with the point where it pierces the slice (a ring); a lead's contacts as bands
  (``core.planning.lead.contact_extents``) projected on the slice, as wide as the lead,
  solid where the contact crosses the slice.
- :class:`VolumePlanOverlay` keeps the 3D view's plan meshes (``VolumeView.set_overlay``): a
  tube per trajectory, the lead's contacts as short cylinders on it, spheres at targets and
  entries, the landmarks, and the target's uncertainty ellipsoid when shown.
- :class:`ProbeView` is the probe's-eye view: the image on the plane orthogonal to the
  trajectory at an adjustable depth (``core.geometry.planes.frame_along`` / ``sample_patch``), with the
  structures' cross-sections and the trajectory's centre.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from PySide6.QtCore import QPointF, QRectF, Qt
from PySide6.QtGui import QColor, QImage, QPainter, QPen
from PySide6.QtWidgets import QSizePolicy, QWidget

from app.model.planning import LANDMARK_LABELS, PlanningState
from core.geometry.planes import frame_along, window_to_uint8
from core.geometry.slicing import intersect_plane
from core.planning.lead import across_in_plane, contact_extents
from core.reconstruction.uncertainty import section_sd

LANDMARK_COLOR = QColor(255, 80, 200)
LANDMARK_RGB = (1.0, 0.31, 0.78)
TRAJECTORY_RGB = (1.0, 1.0, 0.3)
#: a lead's contacts in every view (distinct from the trajectory's yellow)
CONTACT_RGB = (0.2, 0.85, 1.0)


class SlicePlanOverlay:
    """Paints the plan on one slice view (see the module docstring)."""

    def __init__(self, planning: PlanningState):
        self.planning = planning
        self.sd: tuple[int, np.ndarray, float] | None = None   # (structure id, (N,) SD, max SD)

    def __call__(self, painter: QPainter, view) -> None:
        planning = self.planning
        if self.sd is not None:
            self._paint_sd_contour(painter, view)
        tolerance = view._step() / 2 + 1e-6
        depth_of = view.frame.depth
        for name, xyz in planning.landmarks.items():
            if xyz is None or abs(float(depth_of(xyz)) - view.depth) > tolerance:
                continue
            x, y = view.world_to_screen(xyz)
            painter.setPen(QPen(LANDMARK_COLOR, 2))
            painter.setBrush(Qt.BrushStyle.NoBrush)
            painter.drawPolygon([QPointF(x, y - 6), QPointF(x + 6, y), QPointF(x, y + 6),
                                 QPointF(x - 6, y)])
            painter.drawText(QPointF(x + 8, y - 6), LANDMARK_LABELS[name])
        for s in planning.workspace.structures:
            if not s.visible:
                continue
            color = QColor(*s.color)
            target, entry = planning.target_of(s), planning.entry_of(s)
            traj = planning.trajectory_of(s)
            if traj is not None:
                self._paint_trajectory(painter, view, traj, color)
            placed = planning.placed_lead_of(s)
            if placed is not None:
                self._paint_contacts(painter, view, placed)
            for point, kind in ((target, "target"), (entry, "entry")):
                if point is None or abs(float(depth_of(point)) - view.depth) > tolerance:
                    continue
                x, y = view.world_to_screen(point)
                painter.setPen(QPen(color, 2))
                if kind == "target":
                    painter.drawLine(QPointF(x - 6, y), QPointF(x + 6, y))
                    painter.drawLine(QPointF(x, y - 6), QPointF(x, y + 6))
                else:
                    painter.drawRect(QRectF(x - 4, y - 4, 8, 8))

    def _paint_sd_contour(self, painter: QPainter, view) -> None:
        """The structure's contour on this slice coloured by its posterior SD (blue to yellow)."""
        sid, sd, top = self.sd
        s = self.planning.workspace.structure_by_id(sid)
        if s is None or s.model is None or len(sd) != s.model.n_vertices:
            return
        n = np.asarray(view.frame.n)
        segments, seg_sd = section_sd(s.surface_vertices(), s.model.faces, sd, view.depth * n, n)
        if len(segments) == 0:
            return
        xy = view.world_to_screen(segments.reshape(-1, 3)).reshape(-1, 4)
        level = np.clip(seg_sd / max(top, 1e-9), 0.0, 1.0)
        for (a, b, c, d), t in zip(xy.tolist(), level.tolist()):
            painter.setPen(QPen(QColor(int(40 + 215 * t), int(60 + 170 * t), int(230 * (1 - t))), 3))
            painter.drawLine(QPointF(a, b), QPointF(c, d))

    @staticmethod
    def _paint_trajectory(painter: QPainter, view, traj, color: QColor) -> None:
        a, b = view.world_to_screen(np.stack([traj.entry, traj.target]))
        pen = QPen(QColor(255, 255, 80, 170), 1.5, Qt.PenStyle.DashLine)
        painter.setPen(pen)
        painter.drawLine(QPointF(*a), QPointF(*b))
        n = np.asarray(view.frame.n)
        denom = float(traj.direction @ n)
        if abs(denom) > 1e-9:  # where the trajectory pierces this slice
            t = (view.depth - float(traj.entry @ n)) / denom
            if 0.0 <= t <= traj.length:
                x, y = view.world_to_screen(traj.point_at(t))
                painter.setPen(QPen(QColor(255, 255, 80), 2))
                painter.drawEllipse(QPointF(x, y), 5, 5)


    @staticmethod
    def contact_bands(view, placed) -> list[tuple[str, np.ndarray, np.ndarray, float, bool]]:
        """Per contact (name, screen start, screen end, width px, crosses the slice): its
        band on the lead's axis projected on the slice; crossing when the slice's plane cuts
        the band's extent along the lead (within half a voxel step)."""
        n = np.asarray(view.frame.n, dtype=np.float64)
        across = across_in_plane(placed, n, view.frame.u)
        half_step = view._step() / 2
        out = []
        for band in contact_extents(placed):
            a, b = view.world_to_screen(np.stack([band["start"], band["end"]]))
            edge = view.world_to_screen(band["start"] + 2 * band["radius_mm"] * across)
            width = max(3.0, float(np.hypot(*(np.asarray(edge) - a))))
            depths = sorted((float(band["start"] @ n), float(band["end"] @ n)))
            crosses = depths[0] - half_step <= view.depth <= depths[1] + half_step
            out.append((band["name"], np.asarray(a), np.asarray(b), width, crosses))
        return out

    def _paint_contacts(self, painter: QPainter, view, placed) -> None:
        rgb = QColor(*(int(255 * c) for c in CONTACT_RGB))
        for name, a, b, width, crosses in self.contact_bands(view, placed):
            color = QColor(rgb)
            color.setAlpha(255 if crosses else 110)
            pen = QPen(color, width)
            pen.setCapStyle(Qt.PenCapStyle.FlatCap)
            painter.setPen(pen)
            if np.hypot(*(b - a)) < 1.0:          # seen end on: a disc
                painter.setBrush(color)
                painter.drawEllipse(QPointF(*a), width / 2, width / 2)
                painter.setBrush(Qt.BrushStyle.NoBrush)
            else:
                painter.drawLine(QPointF(*a), QPointF(*b))


class VolumePlanOverlay:
    """Keeps the 3D view's plan meshes in step with the planning state.

    Each mesh is rebuilt and handed to the view only when its geometry changed: the plan is
    asked to update after every refit of every structure, and building spheres and tubes for
    all of them each time cost ~20 ms of the GUI thread per refit with three structures.
    """

    def __init__(self, planning: PlanningState, volume_view):
        self.planning = planning
        self.view = volume_view
        self._keys: dict[str, tuple] = {}   # name -> the geometry and style last shown
        self.ellipsoid = None            # core.reconstruction.uncertainty.Ellipsoid of the active target

    def update(self) -> None:
        planning = self.planning
        wanted: dict[str, tuple] = {}     # name -> (key, build the mesh, style)

        def want(name, key, build, **style):
            wanted[name] = (key + (tuple(sorted(style.items())),), build, style)

        for name, xyz in planning.landmarks.items():
            if xyz is not None:
                want(f"landmark-{name}", tuple(xyz),
                     lambda c=xyz: _sphere(1.2, c), color=LANDMARK_RGB)
        for s in planning.workspace.structures:
            if not s.visible:
                continue
            rgb = tuple(c / 255 for c in s.color)
            target, entry = planning.target_of(s), planning.entry_of(s)
            if target is not None:
                want(f"target-{s.id}", tuple(target),
                     lambda c=target: _sphere(1.0, c), color=rgb)
            if entry is not None:
                want(f"entry-{s.id}", tuple(entry),
                     lambda c=entry: pv.Cube(center=c, x_length=2, y_length=2, z_length=2),
                     color=rgb)
            traj = planning.trajectory_of(s)
            if traj is not None:
                want(f"trajectory-{s.id}", tuple(traj.entry) + tuple(traj.target),
                     lambda t=traj: pv.Line(t.entry, t.target).tube(radius=0.4),
                     color=TRAJECTORY_RGB)
            placed = planning.placed_lead_of(s)
            if placed is not None:
                want(f"lead-{s.id}", tuple(placed.tip) + tuple(placed.axis) +
                     (placed.lead.key, placed.rotation_deg),
                     lambda p=placed: _contact_cylinders(p), color=CONTACT_RGB)
        e = self.ellipsoid
        if e is not None and e.radius_mm > 0:
            want("target-ellipsoid", tuple(e.centre) + tuple(np.ravel(e.semi_axes)) +
                 tuple(np.ravel(e.axes)), lambda e=e: _ellipsoid_mesh(e),
                 color=(1.0, 0.3, 0.3), opacity=0.35)
        for name, (key, build, style) in wanted.items():
            if self._keys.get(name) != key:
                self.view.set_overlay(name, build(), **style)
        for name in self._keys.keys() - wanted.keys():
            self.view.set_overlay(name, None)
        self._keys = {name: key for name, (key, _, _) in wanted.items()}


_SPHERES: dict[float, pv.PolyData] = {}


def _sphere(radius: float, centre) -> pv.PolyData:
    """A sphere mesh of ``radius`` at ``centre`` (a translated copy of one cached mesh)."""
    if radius not in _SPHERES:
        _SPHERES[radius] = pv.Sphere(radius=radius)
    mesh = _SPHERES[radius].copy()
    mesh.points = mesh.points + np.asarray(centre, dtype=np.float64)
    return mesh


def _contact_cylinders(placed) -> pv.PolyData:
    """One mesh of the lead's contacts: a short cylinder per level (directional segments
    drawn as their level's ring), slightly wider than the trajectory's tube."""
    cylinders = []
    seen = set()
    for band in contact_extents(placed):
        key = tuple(np.round(band["start"], 6))
        if key in seen:                 # the segments of one level share its band
            continue
        seen.add(key)
        centre = (band["start"] + band["end"]) / 2
        cylinders.append(pv.Cylinder(center=centre, direction=placed.axis,
                                     radius=max(band["radius_mm"], 0.6),
                                     height=float(band["length_mm"]),
                                     resolution=24))
    return pv.merge(cylinders) if len(cylinders) > 1 else cylinders[0]


def _ellipsoid_mesh(e) -> pv.PolyData:
    """A sphere mesh stretched onto ``core.reconstruction.uncertainty.Ellipsoid`` ``e``."""
    sphere = pv.Sphere(radius=1.0, theta_resolution=24, phi_resolution=16)
    sphere.points = np.asarray(sphere.points) * np.maximum(e.semi_axes, 1e-3) @ e.axes + e.centre
    return sphere


class ProbeView(QWidget):
    """The probe's-eye view: the slice orthogonal to a trajectory at a depth from its entry."""

    HALF_SIZE_MM = 20.0

    def __init__(self, planning: PlanningState, parent: QWidget | None = None):
        super().__init__(parent)
        self.planning = planning
        self.trajectory = None
        self.depth = 0.0
        self._image: QImage | None = None
        self._contours: list[tuple[QColor, np.ndarray]] = []
        self.setMinimumSize(180, 180)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Fixed)

    def set_view(self, trajectory, depth: float) -> None:
        self.trajectory, self.depth = trajectory, float(depth)
        self._image, self._contours = None, []
        ws = self.planning.workspace
        if trajectory is not None and ws.sampler is not None:
            frame = frame_along(trajectory.direction)
            centre = trajectory.point_at(self.depth)
            patch = ws.sampler.sample_patch(frame, centre, self.HALF_SIZE_MM, step=0.5)
            grey = np.ascontiguousarray(window_to_uint8(patch.data, ws.window, ws.level))
            h, w = grey.shape
            self._image = QImage(grey.data, w, h, w, QImage.Format.Format_Grayscale8).copy()
            axes = frame.axes
            for s in ws.structures:
                vertices = s.surface_vertices()
                if vertices is None or not s.visible:
                    continue
                segments = intersect_plane(vertices, s.model.faces, centre, axes[2])
                if segments is not None and len(segments):
                    uv = (np.asarray(segments) - centre) @ axes[:2].T   # (S, 2, 2) mm
                    self._contours.append((QColor(*s.color), uv))
        self.update()

    def paintEvent(self, event) -> None:  # noqa: N802 - Qt API
        painter = QPainter(self)
        painter.fillRect(self.rect(), QColor(0, 0, 0))
        side = min(self.width(), self.height())
        x0, y0 = (self.width() - side) / 2, (self.height() - side) / 2
        if self._image is None:
            painter.setPen(QColor(160, 160, 160))
            painter.drawText(self.rect(), Qt.AlignmentFlag.AlignCenter,
                             "Set a target and an entry\nfor the probe's-eye view")
            painter.end()
            return
        painter.drawImage(QRectF(x0, y0, side, side), self._image)
        scale = side / (2 * self.HALF_SIZE_MM)
        cx, cy = x0 + side / 2, y0 + side / 2
        painter.setRenderHint(QPainter.RenderHint.Antialiasing, True)
        for color, uv in self._contours:
            painter.setPen(QPen(color, 1.5))
            for (u1, v1), (u2, v2) in uv:
                painter.drawLine(QPointF(cx + u1 * scale, cy - v1 * scale),
                                 QPointF(cx + u2 * scale, cy - v2 * scale))
        painter.setPen(QPen(QColor(255, 255, 80), 2))
        painter.drawEllipse(QPointF(cx, cy), 4, 4)
        painter.setPen(QColor(255, 255, 120))
        painter.drawText(QRectF(x0 + 4, y0 + 2, side - 8, 18), Qt.AlignmentFlag.AlignLeft,
                         f"{self.depth:.1f} mm")
        painter.drawText(QRectF(x0 + 4, y0 + 2, side - 8, 18), Qt.AlignmentFlag.AlignRight,
                         f"{2 * self.HALF_SIZE_MM:.0f} mm")
        painter.end()
