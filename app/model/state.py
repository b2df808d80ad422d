"""The segmentation workspace model: image, crosshair, window/level and a list of structures.

Plain Python, no Qt (napari's ``ViewerModel`` is the pattern; a test checks that this module
imports no Qt). :class:`WorkspaceState` holds the image and the structures being segmented;
each :class:`Structure` has its own shape model, placement (pose), coefficients, contour
points, last fit read-out and undo history. One structure is *active*: drawing, the factor
sliders, the refit and undo act on it.

Every setter validates, changes the data and emits one event from :attr:`WorkspaceState.events`
(see :mod:`app.model.events`); views and panels subscribe and redraw, and never change each other.
Events about "the" model, points, surface, fit and history are those of the active
structure (so a view written for one structure keeps working); ``structure_changed(structure,
what)`` reports a change of any structure, and ``structures`` / ``active`` a change of the
list or of the active one. Edits the user can undo go through :meth:`Structure.checkpoint`
first, which pushes a snapshot on that structure's undo stack.

Contour points are kept with the slice they were drawn on (frame name and depth), in drawing
order; their normals are derived per slice from the contour tangent and the slice normal,
and oriented by the current surface (``core.geometry.planes.slice_contour_normals``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from app.model.events import EmitterGroup
from app.model.history import UndoHistory
from core.geometry.planes import FRAMES, SliceSampler, auto_window, slice_contour_normals
from core.io import Volume
from core.io.model_library import structure_info
from core.models.shape_model import ShapeModel
from core.reconstruction.plausibility import plausibility_warnings

FRAME_NAMES = ("axial", "coronal", "sagittal")
MAX_HISTORY = 200

# Distinct, colour-blind-friendly structure colours (RGB 0-255); the first is the
# historical orange of the single-structure workspace.
STRUCTURE_COLORS = ((255, 170, 0), (0, 200, 255), (230, 80, 200), (120, 220, 60),
                    (255, 90, 70), (160, 130, 255), (240, 230, 80), (60, 220, 190))
SIDES = ("", "left", "right", "midline")


@dataclass(frozen=True)
class Points:
    """Contour points: world positions with the slice and the stroke each was drawn in.

    xyz (P, 3) world RAS mm; frame (P,) index into FRAME_NAMES; depth (P,) slice depth (mm);
    stroke (P,) int: points of one stroke are joined in the views and get their normals from
    each other. A stroke is one drag, or a chain of single clicks on one slice. Without
    stroke labels (e.g. from a session file) each slice is one stroke.
    """

    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    frame: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    depth: np.ndarray = field(default_factory=lambda: np.zeros(0))
    stroke: np.ndarray | None = None
    dragged: np.ndarray | None = None      # (P,) bool: added by a drag (not a click chain)
    given: np.ndarray | None = None        # (P, 3) normals that came with the points (NaN: none)

    def __post_init__(self) -> None:
        if self.stroke is None or len(self.stroke) != len(self.xyz):
            object.__setattr__(self, "stroke", self.slice_ids())
        if self.dragged is None or len(self.dragged) != len(self.xyz):
            object.__setattr__(self, "dragged", np.zeros(len(self.xyz), dtype=bool))
        if self.given is None or len(self.given) != len(self.xyz):
            object.__setattr__(self, "given", np.full((len(self.xyz), 3), np.nan))

    def __len__(self) -> int:
        return int(len(self.xyz))

    def append(self, xyz: np.ndarray, frame: int, depth: float, stroke: str = "click") -> Points:
        """A new point: ``stroke`` "click" extends the slice's click chain (or starts one),
        "drag" continues the drag that the previous point started or continued."""
        here = np.flatnonzero(self.on_slice(frame, depth, 1e-6))
        ids, dragged = self.stroke.copy(), self.dragged.copy()
        fresh = int(ids.max()) + 1 if len(ids) else 0
        if stroke == "drag" and len(self):
            if not dragged[-1] and len(self) > 1 and ids[-2] == ids[-1]:
                ids[-1] = fresh                       # the press point leaves the click chain
                fresh += 1
            dragged[-1] = True
            label = ids[-1]
        elif len(here) and not dragged[here[-1]]:
            label = ids[here[-1]]
        else:
            label = fresh
        return Points(np.vstack([self.xyz, np.reshape(xyz, (1, 3))]),
                      np.append(self.frame, int(frame)), np.append(self.depth, float(depth)),
                      np.append(ids, label), np.append(dragged, stroke == "drag"),
                      np.vstack([self.given, np.full((1, 3), np.nan)]))

    def extend(self, other: Points) -> Points:
        """These points, then ``other``'s (its strokes kept apart from these)."""
        offset = int(self.stroke.max()) + 1 if len(self) else 0
        return Points(np.vstack([self.xyz, other.xyz]), np.append(self.frame, other.frame),
                      np.append(self.depth, other.depth), np.append(self.stroke, other.stroke + offset),
                      np.append(self.dragged, other.dragged), np.vstack([self.given, other.given]))

    def remove(self, mask_or_index) -> Points:
        keep = np.ones(len(self), dtype=bool)
        keep[mask_or_index] = False
        return Points(self.xyz[keep], self.frame[keep], self.depth[keep], self.stroke[keep],
                      self.dragged[keep], self.given[keep])

    def stroke_ids(self) -> np.ndarray:
        """(P,) int: one label per (slice, stroke)."""
        if len(self) == 0:
            return np.zeros(0, dtype=np.int64)
        keys = np.stack([self.slice_ids(), self.stroke], axis=1)
        return np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1)

    def on_slice(self, frame: int, depth: float, tolerance: float) -> np.ndarray:
        """Mask (P,) of points drawn on the slice (frame, depth)."""
        return (self.frame == frame) & (np.abs(self.depth - depth) <= tolerance)

    def slice_ids(self) -> np.ndarray:
        """(P,) int: one label per distinct slice (frame, depth to 1 um)."""
        if len(self) == 0:
            return np.zeros(0, dtype=np.int64)
        keys = np.stack([self.frame.astype(np.float64), np.round(self.depth, 3)], axis=1)
        return np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1)

    def n_slices(self) -> int:
        return int(len(np.unique(self.slice_ids())))

    def normals(self, surface: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(P, 3) unit in-plane normals, NaN rows for single points on their slice.

        Per stroke, from the drawing order (outwards from the points' centroid); with
        ``surface`` = (vertices (N, 3), vertex normals (N, 3)) of the current fit, each
        stroke's sign is the one agreeing with the surface (``core.geometry.planes.slice_contour_normals``).
        """
        plane_normals = np.array([FRAMES[name].n for name in FRAME_NAMES], dtype=np.float64)
        out = slice_contour_normals(self.xyz, self.stroke_ids(), plane_normals[self.frame], surface)
        given = np.all(np.isfinite(self.given), axis=1)
        out[given] = self.given[given]            # normals that came with imported points
        return out


@dataclass(frozen=True)
class ModelRecord:
    """Which model a structure holds, with what it took from the model's header."""

    model: ShapeModel | None
    path: Path | None
    name: str
    side: str
    color: tuple[int, int, int]
    demo: bool


@dataclass(frozen=True)
class Snapshot:
    points: Points
    coef: np.ndarray | None
    pose: np.ndarray | None
    placement: np.ndarray | None = None
    edits: object = None              # core.geometry.labelmap.ManualEdits (brush / eraser), or None
    model: ModelRecord | None = None  # None: the snapshot does not change the model
    absent: bool = False              # before the structure was added: undo removes it


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
    level: str = "error"                   # of the message: "error" (red) or "info" (a hint)
    kind: str = "fit"                      # "fit", "manual" (slider edit), "restored" (session)
    out_of_date: bool = False              # the points changed since (automatic refit off)
    warnings: tuple[str, ...] = ()         # why the fit looks implausible (empty: plausible)

    @classmethod
    def from_result(cls, result, seconds: float) -> FitInfo:
        """The read-out of a ``core.reconstruction.FitResult`` applied ``seconds`` after the edit."""
        info = cls(residual_mm=float(result.residual_mm), n_iter=int(result.n_iter),
                   converged=bool(result.converged), stop_reason=result.stop_reason,
                   seconds=float(seconds), fit_seconds=float(result.elapsed_s),
                   warnings=plausibility_warnings(result.plausibility()))
        if getattr(result, "mirror_restart", "") == "mirror":  # the surface may have jumped
            info.level, info.message = "info", MIRROR_MESSAGE
        return info


#: Said when the fit of parallel contours kept its restart from the other side of the slices.
MIRROR_MESSAGE = ("Parallel contours only: the structure fitted better on the other side of "
                  "the slices and was moved there. A contour in another view settles the side.")


_ids = itertools.count(1)


class Structure:
    """One structure of the workspace: its model, fit, contour points and undo history.

    Changes are reported to the owning :class:`WorkspaceState` (which emits the events);
    a structure on its own (not in a workspace) reports to nobody.
    """

    def __init__(self, name: str = "", side: str = "", color: tuple[int, int, int] | None = None):
        self.id = next(_ids)
        self.name = name
        self.side = side
        self.color = tuple(int(c) for c in (color or STRUCTURE_COLORS[0]))
        self.visible = True
        self.locked = False
        self.customised = False                # renamed/recoloured/... by the user (sessions keep it)
        self.demo = False                      # the model is a demo model (its header says so)
        self.model: ShapeModel | None = None
        self.model_path: Path | None = None
        self.coef: np.ndarray | None = None
        self.pose: np.ndarray | None = None
        # The pose the user set (model file's placement, Place here, a restored session's
        # pose): the fit starts there and its pose prior is centred on it.
        self.placement: np.ndarray | None = None
        self.points = Points()
        self.fit_info = FitInfo()
        self.last_fit = None                   # core FitResult of the current surface (warm start)
        self.manual_edit = False               # factors set by hand since the last refit
        self.edits = None                      # core.geometry.labelmap.ManualEdits: brush/eraser voxels
        self.model_version = 0                 # bumped when the model is replaced
        self.history = UndoHistory(self._snapshot, self._restore,
                                   lambda: self._notify(self, "history"), MAX_HISTORY)
        self._vertices_cache: tuple[int, np.ndarray] | None = None
        self._normals_cache: tuple[int, np.ndarray] | None = None
        self._factor_cache: tuple[tuple[int, int], np.ndarray] | None = None
        self._surface_version = 0
        self._notify: Callable[[Structure, str], None] = lambda structure, what: None

    def __repr__(self) -> str:
        return f"<Structure {self.id} {self.label!r}: {len(self.points)} points>"

    @property
    def label(self) -> str:
        """Name with side, as the structure list shows it."""
        name = self.name or "(unnamed)"
        return f"{name} ({self.side})" if self.side else name

    # -- properties --------------------------------------------------------------------------
    def set_properties(self, *, name: str | None = None, side: str | None = None,
                       color: tuple[int, int, int] | None = None, visible: bool | None = None,
                       locked: bool | None = None) -> None:
        """Rename, recolour, show/hide, lock/unlock; emits ``structure_changed(s, "properties")``."""
        if side is not None and side not in SIDES:
            raise ValueError(f"side must be one of {', '.join(repr(s) for s in SIDES)}; got {side!r}")
        if color is not None:
            color = tuple(int(c) for c in color)
            if len(color) != 3 or not all(0 <= c <= 255 for c in color):
                raise ValueError(f"colour must be three values 0-255, got {color}")
            self.color = color
        if name is not None:
            self.name = str(name).strip()
        if side is not None:
            self.side = side
        if visible is not None:
            self.visible = bool(visible)
        if locked is not None:
            self.locked = bool(locked)
        self.customised = True
        self._notify(self, "properties")
        self._notify(self, "edited")

    # -- model, coefficients and pose ----------------------------------------------------
    def set_model(self, model: ShapeModel, path: str | Path | None = None,
                  coef: np.ndarray | None = None, pose: np.ndarray | None = None) -> None:
        self.model = model
        self.model_path = Path(path) if path else None
        self.coef = np.zeros(model.n_factors) if coef is None else np.asarray(coef, float).copy()
        self.pose = model.world_transform.copy() if pose is None else np.asarray(pose, float).copy()
        self.placement = self.pose.copy()
        self.fit_info = FitInfo()
        self.last_fit = None
        self.model_version += 1
        self._surface_version += 1
        # one rule however the model came (Load model, the library, a drop, a session without
        # colours): name, side and colour from the model's header (core.io.model_library), made
        # distinct from the other structures' by the workspace; what the user set is kept
        info = structure_info(model, self.model_path)
        self.demo = info.demo
        if not self.customised:
            self.name = info.name
            self.side = info.side if info.side in SIDES else ""
            self.color = tuple(int(round(255 * c)) for c in info.color)
        self._notify(self, "model")
        self._notify(self, "surface")
        self._notify(self, "fit_info")

    def surface_vertices(self) -> np.ndarray | None:
        """World vertices (N, 3) of the current instance, or None without a model."""
        if self.model is None:
            return None
        if self._vertices_cache is None or self._vertices_cache[0] != self._surface_version:
            local = self.model.instance(self.coef)
            world = local @ self.pose[:3, :3].T + self.pose[:3, 3]
            self._vertices_cache = (self._surface_version, world)
        return self._vertices_cache[1]

    def surface_normals(self) -> np.ndarray | None:
        """Vertex normals (N, 3) of the current instance (cached with it)."""
        if self.model is None:
            return None
        if self._normals_cache is None or self._normals_cache[0] != self._surface_version:
            from core.geometry.toolkit import vertex_normals

            self._normals_cache = (self._surface_version,
                                   vertex_normals(self.surface_vertices(), self.model.faces))
        return self._normals_cache[1]

    def factor_displacement(self, index: int) -> np.ndarray:
        """How far factor ``index`` moves each vertex at one prior SD, (N,) mm (cached)."""
        key = (self.model_version, int(index))
        if self._factor_cache is None or self._factor_cache[0] != key:
            factor = self.model.factors[index]
            move = float(np.sqrt(self.model.coef_var[index])) * np.sqrt(
                np.einsum("ij,ij->i", factor, factor))
            self._factor_cache = (key, move)
        return self._factor_cache[1]

    def set_surface(self, coef: np.ndarray, pose: np.ndarray,
                    vertices: np.ndarray | None = None) -> None:
        """Replace coefficients and pose (e.g. by a refit or a slider); emits surface."""
        if self.model is None:
            return
        self.coef = np.asarray(coef, dtype=np.float64).copy()
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self._surface_version += 1
        if vertices is not None and np.shape(vertices) == self.model.mean.shape:
            self._vertices_cache = (self._surface_version, np.asarray(vertices, dtype=np.float64))
        self._notify(self, "surface")

    def set_coefficient(self, index: int, value: float) -> None:
        """A factor set by hand (slider): the read-out shows the residual of the new shape."""
        coef = self.coef.copy()
        coef[index] = value
        self.set_surface(coef, self.pose)
        self._manual_readout()
        self._notify(self, "edited")

    def residual_mm(self) -> float:
        """Mean distance (mm) from the contour points to the current surface (NaN if none)."""
        if self.model is None or len(self.points) == 0:
            return float("nan")
        from core.geometry.toolkit import surface_distance

        return float(np.mean(surface_distance(self.points.xyz, self.surface_vertices(),
                                              self.model.faces)))

    def _manual_readout(self) -> None:
        self.manual_edit = True
        self.set_fit_info(FitInfo(residual_mm=self.residual_mm(), kind="manual", level="info",
                                  message="Shape set with the sliders (not refitted): the next "
                                          "refit starts from it and re-optimises the factors."))

    def reset_coefficients(self) -> None:
        """Back to the mean shape, keeping the pose (undoable)."""
        if self.model is None:
            return
        self.checkpoint()
        self.set_surface(np.zeros(self.model.n_factors), self.pose)
        self._manual_readout()
        self._notify(self, "edited")

    def place_at(self, xyz: np.ndarray) -> None:
        """Translate the model so that its centroid sits at world point ``xyz`` (undoable)."""
        if self.model is None:
            return
        self.checkpoint()
        centroid = self.surface_vertices().mean(axis=0)
        pose = self.pose.copy()
        pose[:3, 3] += np.asarray(xyz, dtype=np.float64) - centroid
        self.placement = pose.copy()
        self.last_fit = None
        self.set_surface(self.coef, pose)
        self._notify(self, "edited")

    def set_pose(self, pose: np.ndarray, checkpoint: bool = True, edited: bool = True) -> None:
        """Place the model by hand (the move tool): the pose, which becomes the placement the
        next fit's pose prior is centred on. ``edited`` False while a drag is in progress."""
        if self.model is None:
            return
        if checkpoint:
            self.checkpoint()
        self.placement = np.asarray(pose, dtype=np.float64).copy()
        self.last_fit = None
        self.set_surface(self.coef, pose)
        if edited:
            self._notify(self, "edited")

    def reset_placement(self) -> None:
        """Back to the model's stored world placement and zero coefficients (undoable)."""
        if self.model is None:
            return
        self.checkpoint()
        self.placement = self.model.world_transform.copy()
        self.set_surface(np.zeros(self.model.n_factors), self.model.world_transform)
        self._notify(self, "edited")

    def set_fit_info(self, info: FitInfo) -> None:
        self.fit_info = info
        self._notify(self, "fit_info")

    def point_normals(self) -> np.ndarray:
        """(P, 3) normals of the contour points, oriented by the current surface; 0 = unknown."""
        surface = None
        if self.model is not None:
            surface = (self.surface_vertices(), self.surface_normals())
        return np.nan_to_num(self.points.normals(surface), nan=0.0)

    # -- points --------------------------------------------------------------------------
    def set_points(self, points: Points, checkpoint: bool = True, edited: bool = True) -> None:
        """Replace the contour points (one undo step unless ``checkpoint`` is False)."""
        if checkpoint:
            self.checkpoint()
        self.points = points
        self._notify(self, "points")
        if edited:
            self._notify(self, "edited")

    def add_point(self, xyz: np.ndarray, frame_name: str, depth: float, checkpoint: bool = True,
                  stroke: str = "click") -> None:
        """Append a contour point drawn on slice (frame, depth). ``checkpoint`` starts an undo
        step; ``stroke`` is "click" or "drag" (see :meth:`Points.append`)."""
        self.set_points(self.points.append(xyz, FRAME_NAMES.index(frame_name), depth, stroke),
                        checkpoint)

    def remove_point(self, index: int) -> None:
        if 0 <= index < len(self.points):
            self.set_points(self.points.remove(index))

    def clear_slice(self, frame_name: str, depth: float, tolerance: float) -> int:
        """Remove the points of one slice; returns how many were removed."""
        mask = self.points.on_slice(FRAME_NAMES.index(frame_name), depth, tolerance)
        if mask.any():
            self.set_points(self.points.remove(mask))
        return int(mask.sum())

    def clear_points(self) -> None:
        if len(self.points):
            self.set_points(Points())

    # -- manual label edits (app.tools: brush and eraser) -----------------------------------
    def set_edits(self, edits, checkpoint: bool = True) -> None:
        """Replace the manual label edits (an immutable ``ManualEdits``; one undo step)."""
        if checkpoint:
            self.checkpoint()
        self.edits = edits
        self._notify(self, "edits")
        self._notify(self, "edited")

    # -- undo / redo ---------------------------------------------------------------------
    def _snapshot(self) -> Snapshot:
        return Snapshot(self.points,
                        None if self.coef is None else self.coef.copy(),
                        None if self.pose is None else self.pose.copy(),
                        None if self.placement is None else self.placement.copy(),
                        self.edits,
                        ModelRecord(self.model, self.model_path, self.name, self.side,
                                    self.color, self.demo))

    def replace_model(self, model: ShapeModel, path: str | Path | None = None,
                      coef: np.ndarray | None = None, pose: np.ndarray | None = None) -> None:
        """Load another model into this structure as one undo step (name, side and colour
        follow the new model unless the user set them; the points stay)."""
        self.checkpoint()
        self.set_model(model, path, coef=coef, pose=pose)
        self._notify(self, "properties")
        self._notify(self, "edited")

    def mark_added(self) -> None:
        """Make the structure's first undo step "not there": undo removes it again."""
        self.history.push(Snapshot(Points(), None, None, absent=True))

    def checkpoint(self) -> None:
        """Record the current state as one undo step (call before an undoable edit)."""
        self.history.checkpoint()

    def can_undo(self) -> bool:
        return self.history.can_undo()

    def can_redo(self) -> bool:
        return self.history.can_redo()

    def undo(self) -> bool:
        return self.history.undo()

    def redo(self) -> bool:
        return self.history.redo()

    def clear_history(self) -> None:
        self.history.clear()

    def _restore(self, snap: Snapshot) -> None:
        if snap.absent:                        # undoing the structure's addition
            self._notify(self, "discard")
            return
        points_differ = snap.points is not self.points
        self.points = snap.points
        if snap.model is not None and snap.model.model is not self.model:
            self._restore_model(snap)
        if self.model is not None and snap.coef is not None and len(snap.coef) == self.model.n_factors:
            if snap.placement is not None:
                self.placement = snap.placement.copy()
            self.set_surface(snap.coef, snap.pose)
        if snap.edits is not self.edits:
            self.edits = snap.edits
            self._notify(self, "edits")
        if points_differ:
            self._notify(self, "points")
        self._notify(self, "history")
        self._notify(self, "edited")


    def _restore_model(self, snap: Snapshot) -> None:
        record = snap.model
        self.model, self.model_path = record.model, record.path
        self.name, self.side, self.color, self.demo = (record.name, record.side, record.color,
                                                       record.demo)
        self.coef = None if snap.coef is None else snap.coef.copy()
        self.pose = None if snap.pose is None else snap.pose.copy()
        self.placement = None if snap.placement is None else snap.placement.copy()
        self.last_fit = None
        self.model_version += 1
        self._surface_version += 1
        self.fit_info = FitInfo(residual_mm=self.residual_mm(), kind="restored")
        for what in ("model", "surface", "fit_info", "properties"):
            self._notify(self, what)


# Per-structure changes re-emitted as the workspace's events of the active structure.
_ACTIVE_EVENTS = ("model", "points", "surface", "fit_info", "history")


class WorkspaceState:
    """Evented state of the segmentation workspace (see the module docstring).

    Events (``state.events.<name>.connect(callback)``): ``image``, ``window``, ``crosshair``;
    ``structures`` (added/removed), ``active`` (another structure is active),
    ``structure_changed(structure, what)`` with what in model/points/surface/fit_info/
    history/properties; of the active structure: ``model``, ``points``, ``surface``,
    ``fit_info``, ``history``; ``edited(what)`` after any user edit (for autosave).
    """

    def __init__(self) -> None:
        self.events = EmitterGroup(
            image=(), window=(), crosshair=(), structures=(), active=(),
            structure_changed=("structure", "what"), model=(), points=(), surface=(),
            fit_info=(), history=(), edited=("what",))
        self.volume: Volume | None = None
        self.sampler: SliceSampler | None = None
        self.image_path: Path | None = None
        self.crosshair = np.zeros(3)
        # where the user last clicked or moved the crosshair to, not snapped to a voxel centre
        # (in a slice view: exact in its plane, at the slice's depth)
        self.picked = np.zeros(3)
        self.window = 1.0
        self.level = 0.5
        self.data_range = (0.0, 1.0)
        self.structures: list[Structure] = []
        self._active: Structure | None = None
        self.add_structure(Structure())

    # -- structures ----------------------------------------------------------------------
    @property
    def active(self) -> Structure:
        return self._active

    def add_structure(self, structure: Structure | None = None, activate: bool = True) -> Structure:
        """Append a structure (a new empty one by default) and make it active."""
        structure = structure or Structure()
        if structure in self.structures:
            raise ValueError(f"{structure.label} is already in the workspace")
        if structure.color == STRUCTURE_COLORS[0] and self.structures:
            structure.color = self.unused_color()
        structure._notify = self._on_structure
        self.structures.append(structure)
        self.events.structures()
        if activate or self._active is None:
            self.set_active(structure)
        return structure

    def replace_structures(self, structures: list[Structure], active: int = 0) -> None:
        """Start over with ``structures`` (e.g. from a session); ``active`` indexes them."""
        if not structures:
            structures = [Structure()]
        for old in self.structures:
            old._notify = lambda s, what: None
        for structure in structures:
            structure._notify = self._on_structure
        self.structures = list(structures)
        self._active = structures[min(max(int(active), 0), len(structures) - 1)]
        self.events.structures()
        self.events.active()
        for name in _ACTIVE_EVENTS:
            getattr(self.events, name)()

    def unused_color(self, preferred: tuple[int, int, int] | None = None,
                     exclude: Structure | None = None) -> tuple[int, int, int]:
        """``preferred`` if no structure (but ``exclude``) has it, else the first palette
        colour not in use."""
        used = {s.color for s in self.structures if s is not exclude}
        if preferred is not None and tuple(preferred) not in used:
            return tuple(int(c) for c in preferred)
        return next((c for c in STRUCTURE_COLORS if c not in used),
                    STRUCTURE_COLORS[len(self.structures) % len(STRUCTURE_COLORS)])

    def remove_structure(self, structure: Structure) -> None:
        """Remove a structure; the last one is replaced by an empty structure."""
        if structure not in self.structures:
            raise ValueError(f"{structure.label} is not in the workspace")
        index = self.structures.index(structure)
        self.structures.remove(structure)
        structure._notify = lambda s, what: None
        if not self.structures:
            self.replace_structures([Structure()])
        else:
            was_active = structure is self._active
            if was_active:
                self._active = self.structures[min(index, len(self.structures) - 1)]
            self.events.structures()
            if was_active:
                self.events.active()
                for name in _ACTIVE_EVENTS:
                    getattr(self.events, name)()
        self.events.edited("structures")

    def set_active(self, structure: Structure | int) -> None:
        if isinstance(structure, (int, np.integer)):
            structure = self.structures[int(structure)]
        if structure not in self.structures:
            raise ValueError(f"{structure.label} is not in the workspace")
        if structure is self._active:
            return
        self._active = structure
        self.events.active()
        for name in _ACTIVE_EVENTS:
            getattr(self.events, name)()

    def structure_by_id(self, structure_id: int) -> Structure | None:
        return next((s for s in self.structures if s.id == structure_id), None)

    def _on_structure(self, structure: Structure, what: str) -> None:
        if what == "discard":                  # undo of the structure's addition
            self.remove_structure(structure)
            return
        if what == "model" and not structure.customised:   # distinct from the others
            structure.color = self.unused_color(structure.color, exclude=structure)
        if what == "edited":
            self.events.edited("structure" if structure is not self._active else "points")
            return
        self.events.structure_changed(structure, what)
        if structure is self._active and what in _ACTIVE_EVENTS:
            getattr(self.events, what)()

    # -- the active structure's points of one slice (the tolerance is the image's) -------
    def clear_slice(self, frame_name: str, depth: float) -> int:
        """Remove the active structure's points of one slice; returns how many."""
        tol = 0.5 * (self.sampler.step(FRAMES[frame_name]) if self.sampler else 1.0)
        return self._active.clear_slice(frame_name, depth, tol)

    def clear_history(self) -> None:
        for structure in self.structures:
            structure.clear_history()

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
        self.picked = self.crosshair.copy()
        self.events.image()
        self.events.window()
        self.events.crosshair()

    @property
    def orientation_known(self) -> bool:
        """False when the image's file does not say how its voxels lie (left/right unknown)."""
        return self.volume is None or self.volume.orientation_known

    def set_window(self, window: float, level: float) -> None:
        self.window = max(float(window), 1e-6)
        self.level = float(level)
        self.events.window()

    def window_preset(self, kind: str | None) -> tuple[float, float]:
        """(window, level) of a preset: None = auto (1-99.5 %), "full", "contrast", "bright"."""
        if self.volume is None:
            return self.window, self.level
        lo, hi = self.data_range
        if kind is None:
            return auto_window(self.volume.data)
        if kind == "full":
            return hi - lo, (hi + lo) / 2
        if kind == "contrast":
            window, level = auto_window(self.volume.data, 30.0, 95.0)
            return 0.8 * window, level
        if kind == "bright":
            return auto_window(self.volume.data, 1.0, 90.0)
        raise ValueError(f"unknown window preset {kind!r}")

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
        """Move the crosshair (world mm); snapped to voxel centres for axis-aligned images.
        The point itself, unsnapped, is kept as :attr:`picked` (plan points go there)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        if self.volume is not None:
            lo, hi = self.volume.world_bounds()
            self.picked = np.clip(xyz, lo, hi)
        else:
            self.picked = xyz.copy()
        xyz = self._snap(xyz)
        if self.volume is not None:
            xyz = np.clip(xyz, lo, hi)
        if np.allclose(xyz, self.crosshair):
            return
        self.crosshair = xyz
        self.events.crosshair()

    def step_slice(self, frame_name: str, steps: int) -> None:
        """Move the crosshair ``steps`` slices along the view's normal."""
        frame = FRAMES[frame_name]
        step = self.sampler.step(frame) if self.sampler else 1.0
        self.set_crosshair(self.picked + steps * step * np.asarray(frame.n))
        axis = int(np.argmax(np.abs(frame.n)))       # on the slice now shown
        self.picked[axis] = self.crosshair[axis]

    def describe(self, point: np.ndarray) -> str:
        """Status-bar text for a world point: RAS mm, voxel index, intensity."""
        volume = self.volume
        if volume is None:
            return ""
        ijk = volume.world_to_voxel(point)
        value = volume.value_at(point) if bool(volume.contains_voxel(ijk)) else None
        idx = np.rint(ijk).astype(int)
        text = (f"R {point[0]:+.1f}  A {point[1]:+.1f}  S {point[2]:+.1f} mm   "
                f"voxel ({idx[0]}, {idx[1]}, {idx[2]})   ")
        return text + (f"value {value:.4g}" if value is not None else "outside the image")


# The name the single-structure code used.
SegmentationState = WorkspaceState
