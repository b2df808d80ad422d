"""The segmentation workspace's state: image, model, contour points, fit and crosshair.

No widgets here. :class:`SegmentationState` is a QObject whose setters validate, change the
data and emit one signal; views and panels listen and redraw, and never change each other.
Edits that the user can undo (points, manual coefficients, placement) go through
:meth:`SegmentationState.checkpoint` first, which pushes a snapshot on the undo stack.

Contour points are kept with the slice they were drawn on (frame name and depth), in
drawing order; their normals are derived per slice from the contour tangent and the slice
normal (``core.planes.contour_normals``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PySide6.QtCore import QObject, Signal

from core.io import Volume
from core.planes import FRAMES, SliceSampler, auto_window, contour_normals
from core.shape_model import ShapeModel

FRAME_NAMES = ("axial", "coronal", "sagittal")
MAX_HISTORY = 200


@dataclass(frozen=True)
class Points:
    """Contour points: world positions with the slice each was drawn on.

    xyz (P, 3) world RAS mm; frame (P,) index into FRAME_NAMES; depth (P,) slice depth (mm).
    """

    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    depth: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return int(len(self.xyz))

    def append(self, xyz: np.ndarray, frame: int, depth: float) -> Points:
        return Points(np.vstack([self.xyz, np.reshape(xyz, (1, 3))]),
                      np.append(self.frame, int(frame)), np.append(self.depth, float(depth)))

    def remove(self, mask_or_index) -> Points:
        keep = np.ones(len(self), dtype=bool)
        keep[mask_or_index] = False
        return Points(self.xyz[keep], self.frame[keep], self.depth[keep])

    def on_slice(self, frame: int, depth: float, tolerance: float) -> np.ndarray:
        """Mask (P,) of points drawn on the slice (frame, depth)."""
        return (self.frame == frame) & (np.abs(self.depth - depth) <= tolerance)

    def normals(self, surface: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(P, 3) unit in-plane normals, NaN rows for single points on their slice.

        Per slice, from the drawing order (``core.planes.contour_normals``: outwards from the
        points' centroid). With ``surface`` = (vertices (N, 3), vertex normals (N, 3)) of the
        current fit, each slice's sign is instead the one agreeing with the surface normals
        at the nearest vertices (majority vote): right also for an open stroke along one
        side of the structure, where the centroid rule is ambiguous.
        """
        out = np.full((len(self), 3), np.nan)
        if len(self) == 0:
            return out
        keys = np.stack([self.frame.astype(np.float64), np.round(self.depth, 3)], axis=1)
        groups = np.unique(keys, axis=0)
        nearest = None
        if surface is not None:
            from scipy.spatial import cKDTree

            _, nearest = cKDTree(surface[0]).query(self.xyz)
        for f, d in groups:
            idx = np.flatnonzero((keys[:, 0] == f) & (keys[:, 1] == d))
            normals = contour_normals(self.xyz[idx], FRAMES[FRAME_NAMES[int(f)]].n)
            if nearest is not None:
                agree = np.nansum(np.einsum("ij,ij->i", normals, surface[1][nearest[idx]]))
                if agree < 0:
                    normals = -normals
            out[idx] = normals
        return out


@dataclass(frozen=True)
class Snapshot:
    points: Points
    coef: np.ndarray | None
    pose: np.ndarray | None
    placement: np.ndarray | None = None


@dataclass
class FitInfo:
    """What the fit panel shows about the last refit."""

    residual_mm: float = float("nan")
    n_iter: int = 0
    converged: bool = False
    stop_reason: str = ""
    seconds: float = float("nan")          # round trip: edit -> result applied
    fit_seconds: float = float("nan")      # the fit alone, in the worker
    message: str = ""


class SegmentationState(QObject):
    """Evented state of the segmentation workspace (see module docstring)."""

    image_changed = Signal()
    model_changed = Signal()
    points_changed = Signal()
    surface_changed = Signal()
    crosshair_changed = Signal()
    window_changed = Signal()
    history_changed = Signal()
    fit_info_changed = Signal()
    edited = Signal(str)          # any user edit (for autosave); argument: what changed

    def __init__(self, parent: QObject | None = None):
        super().__init__(parent)
        self.volume: Volume | None = None
        self.sampler: SliceSampler | None = None
        self.image_path: Path | None = None
        self.model: ShapeModel | None = None
        self.model_path: Path | None = None
        self.coef: np.ndarray | None = None
        self.pose: np.ndarray | None = None
        # The pose the user set (model file's placement, Place here, a restored session's
        # pose): the fit starts there and its pose prior is centred on it.
        self.placement: np.ndarray | None = None
        self.points = Points()
        self.crosshair = np.zeros(3)
        self.window = 1.0
        self.level = 0.5
        self.data_range = (0.0, 1.0)
        self.fit_info = FitInfo()
        self._undo: list[Snapshot] = []
        self._redo: list[Snapshot] = []
        self._vertices_cache: tuple[int, np.ndarray] | None = None
        self._surface_version = 0

    # -- image ---------------------------------------------------------------------------
    def set_image(self, volume: Volume, path: str | Path | None = None) -> None:
        self.volume = volume
        self.sampler = SliceSampler(volume)
        self.image_path = Path(path) if path else volume.path
        finite = np.asarray(volume.data)[:: max(1, volume.data.size // 500_000)]
        self.data_range = (float(np.nanmin(finite)), float(np.nanmax(finite)))
        self.window, self.level = auto_window(volume.data)
        bounds = volume.world_bounds()
        self.crosshair = self._snap(bounds.mean(axis=0))
        self.image_changed.emit()
        self.window_changed.emit()
        self.crosshair_changed.emit()

    def set_window(self, window: float, level: float) -> None:
        self.window = max(float(window), 1e-6)
        self.level = float(level)
        self.window_changed.emit()

    # -- crosshair -----------------------------------------------------------------------
    def _snap(self, xyz: np.ndarray) -> np.ndarray:
        xyz = np.asarray(xyz, dtype=np.float64).copy()
        if self.sampler is not None and self.sampler.aligned:
            for name in FRAME_NAMES:
                frame = FRAMES[name]
                axis = int(np.argmax(np.abs(frame.n)))
                xyz[axis] = self.sampler.snap_depth(frame, frame.depth(xyz)) * np.sign(frame.n[axis])
        return xyz

    def set_crosshair(self, xyz: np.ndarray) -> None:
        """Move the crosshair (world mm); snapped to voxel centres for axis-aligned images."""
        xyz = self._snap(xyz)
        if self.volume is not None:
            lo, hi = self.volume.world_bounds()
            xyz = np.clip(xyz, lo, hi)
        if np.allclose(xyz, self.crosshair):
            return
        self.crosshair = xyz
        self.crosshair_changed.emit()

    def step_slice(self, frame_name: str, steps: int) -> None:
        """Move the crosshair ``steps`` slices along the view's normal."""
        frame = FRAMES[frame_name]
        step = self.sampler.step(frame) if self.sampler else 1.0
        self.set_crosshair(self.crosshair + steps * step * np.asarray(frame.n))

    # -- model, coefficients and pose ----------------------------------------------------
    def set_model(self, model: ShapeModel, path: str | Path | None = None,
                  coef: np.ndarray | None = None, pose: np.ndarray | None = None) -> None:
        self.model = model
        self.model_path = Path(path) if path else None
        self.coef = np.zeros(model.n_factors) if coef is None else np.asarray(coef, float).copy()
        self.pose = model.world_transform.copy() if pose is None else np.asarray(pose, float).copy()
        self.placement = self.pose.copy()
        self.fit_info = FitInfo()
        self._surface_version += 1
        self.model_changed.emit()
        self.surface_changed.emit()
        self.fit_info_changed.emit()

    def surface_vertices(self) -> np.ndarray | None:
        """World vertices (N, 3) of the current instance, or None without a model."""
        if self.model is None:
            return None
        if self._vertices_cache is None or self._vertices_cache[0] != self._surface_version:
            local = self.model.instance(self.coef)
            world = local @ self.pose[:3, :3].T + self.pose[:3, 3]
            self._vertices_cache = (self._surface_version, world)
        return self._vertices_cache[1]

    def set_surface(self, coef: np.ndarray, pose: np.ndarray,
                    vertices: np.ndarray | None = None) -> None:
        """Replace coefficients and pose (e.g. by a refit or a slider); emits surface_changed."""
        if self.model is None:
            return
        self.coef = np.asarray(coef, dtype=np.float64).copy()
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self._surface_version += 1
        if vertices is not None and np.shape(vertices) == self.model.mean.shape:
            self._vertices_cache = (self._surface_version, np.asarray(vertices, dtype=np.float64))
        self.surface_changed.emit()

    def set_coefficient(self, index: int, value: float) -> None:
        coef = self.coef.copy()
        coef[index] = value
        self.set_surface(coef, self.pose)
        self.edited.emit("coef")

    def place_at(self, xyz: np.ndarray) -> None:
        """Translate the model so that its centroid sits at world point ``xyz`` (undoable)."""
        if self.model is None:
            return
        self.checkpoint()
        centroid = self.surface_vertices().mean(axis=0)
        pose = self.pose.copy()
        pose[:3, 3] += np.asarray(xyz, dtype=np.float64) - centroid
        self.placement = pose.copy()
        self.set_surface(self.coef, pose)
        self.edited.emit("pose")

    def reset_placement(self) -> None:
        """Back to the model's stored world placement and zero coefficients (undoable)."""
        if self.model is None:
            return
        self.checkpoint()
        self.placement = self.model.world_transform.copy()
        self.set_surface(np.zeros(self.model.n_factors), self.model.world_transform)
        self.edited.emit("pose")

    def set_fit_info(self, info: FitInfo) -> None:
        self.fit_info = info
        self.fit_info_changed.emit()

    # -- points --------------------------------------------------------------------------
    def add_point(self, xyz: np.ndarray, frame_name: str, depth: float, checkpoint: bool = True) -> None:
        """Append a contour point drawn on slice (frame, depth). ``checkpoint`` starts an undo step."""
        if checkpoint:
            self.checkpoint()
        self.points = self.points.append(xyz, FRAME_NAMES.index(frame_name), depth)
        self.points_changed.emit()
        self.edited.emit("points")

    def remove_point(self, index: int) -> None:
        if not 0 <= index < len(self.points):
            return
        self.checkpoint()
        self.points = self.points.remove(index)
        self.points_changed.emit()
        self.edited.emit("points")

    def clear_slice(self, frame_name: str, depth: float) -> int:
        """Remove the points of one slice; returns how many were removed."""
        tol = 0.5 * (self.sampler.step(FRAMES[frame_name]) if self.sampler else 1.0)
        mask = self.points.on_slice(FRAME_NAMES.index(frame_name), depth, tol)
        if not mask.any():
            return 0
        self.checkpoint()
        self.points = self.points.remove(mask)
        self.points_changed.emit()
        self.edited.emit("points")
        return int(mask.sum())

    def clear_points(self) -> None:
        if len(self.points) == 0:
            return
        self.checkpoint()
        self.points = Points()
        self.points_changed.emit()
        self.edited.emit("points")

    def set_points(self, points: Points, checkpoint: bool = True) -> None:
        if checkpoint:
            self.checkpoint()
        self.points = points
        self.points_changed.emit()
        self.edited.emit("points")

    # -- undo / redo ---------------------------------------------------------------------
    def _snapshot(self) -> Snapshot:
        return Snapshot(self.points,
                        None if self.coef is None else self.coef.copy(),
                        None if self.pose is None else self.pose.copy(),
                        None if self.placement is None else self.placement.copy())

    def checkpoint(self) -> None:
        """Record the current state as one undo step (call before an undoable edit)."""
        self._undo.append(self._snapshot())
        del self._undo[:-MAX_HISTORY]
        self._redo.clear()
        self.history_changed.emit()

    def can_undo(self) -> bool:
        return bool(self._undo)

    def can_redo(self) -> bool:
        return bool(self._redo)

    def undo(self) -> bool:
        if not self._undo:
            return False
        self._redo.append(self._snapshot())
        self._restore(self._undo.pop())
        return True

    def redo(self) -> bool:
        if not self._redo:
            return False
        self._undo.append(self._snapshot())
        self._restore(self._redo.pop())
        return True

    def clear_history(self) -> None:
        self._undo.clear()
        self._redo.clear()
        self.history_changed.emit()

    def _restore(self, snap: Snapshot) -> None:
        points_differ = snap.points is not self.points
        self.points = snap.points
        if self.model is not None and snap.coef is not None and len(snap.coef) == self.model.n_factors:
            if snap.placement is not None:
                self.placement = snap.placement.copy()
            self.set_surface(snap.coef, snap.pose)
        if points_differ:
            self.points_changed.emit()
        self.history_changed.emit()
        self.edited.emit("undo")
