"""Segmentation sessions on disk: the session JSON document.

A session is everything needed to pick up a segmentation where it was left: which image and
which shape model, the contour points (world RAS mm) with the slice each was drawn on, the
fitted coefficients and pose, the fit settings, window/level and the crosshair. It is a
small JSON file (issue 7, item 6) written atomically by :func:`save_session`. Image and model
paths are stored relative to the session file's folder, so a folder holding a session with
its data can be moved or copied elsewhere and still opens; a path on another drive (Windows)
is stored absolute. The absolute paths are recorded too, as a fallback for a session file
moved on its own. :func:`load_session` resolves the paths, checks the format name and
version and every array's shape, and raises :class:`core.io.DataFileError` naming the file
and the problem.

Crash recovery (the two-slot autosave, and which runs have ended) is
:mod:`core.session.recovery`; it stores the same document with the arrays packed.

The JSON layout (``format_version`` 1)::

    {
      "format": "ssm-studio-session", "format_version": 1,
      "image": "scans/t1.nii.gz",          # relative to the session file's folder, or absolute
      "model": "../models/stn-lsf.npz",    # or null
      "image_absolute": "/data/case01/scans/t1.nii.gz",  # where they were at saving: used
      "model_absolute": "/data/models/stn-lsf.npz",      # when the relative path is missing
      "points": [[x, y, z], ...],          # (P, 3) world RAS mm
      "normals": [[nx, ny, nz], ...],      # (P, 3) or null
      "point_slices": [["axial", 12.5], ...],  # per point: plane and its depth (mm), or null
      "coef": [a_1, ..., a_M],             # or null
      "pose": [[...], [...], [...], [...]],  # (4, 4) model frame -> world, or null
      "fit": {"method": "gmm-iso", "prior_weight": 1.0, ...},
      "window": [width, level],            # or null
      "crosshair": [x, y, z],              # or null
      "structures": [{...}, ...],          # optional: several structures (see below)
      "active_structure": 0,               # index into "structures"
      "info": {...}                        # free-form (e.g. when and by what it was saved)
    }

A session with several structures (issue 14) keeps format version 1: the top-level
``model``, ``points``, ``normals``, ``point_slices``, ``coef`` and ``pose`` are those of the
active structure (so an older reader opens that one), and ``structures`` lists every
structure as ``{"name", "side", "color": [r, g, b] (0..1), "visible", "locked", "model",
"model_absolute", "points", "normals", "point_slices", "coef", "pose", "placement"}`` with
the same conventions as the top level. A session with one plain structure has no
``structures`` key, as before.

Any array may also be written packed, ``{"dtype": "<f8", "shape": [P, 3], "base64": ...}``
(little-endian bytes), as the recovery files do; both forms are read.

Planes are named as the slice views: "sagittal" (normal along x, depth = x in mm),
"coronal" (y) and "axial" (z); world axis numbers 0, 1, 2 are accepted on input.
"""

from __future__ import annotations

import base64
import binascii
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from core.errors import require_file
from core.geometry.planes import PLANE_NAMES  # a point's plane is stored by its index
from core.io import DataFileError, atomic_path
from core.io.limits import coordinate_problem

SESSION_FORMAT = "ssm-studio-session"
SESSION_FORMAT_VERSION = 1

# More structures than any brain atlas a plan uses (CIT168: 16 per side); a session with
# 10,000 took 57 s and 1.7 GB to plan before it was limited.
MAX_STRUCTURES = 256
# A pose is a similarity (core.reconstruction.POSES; the GUI's handles, core.registration.handles): its
# 3x3 part s R with s in this range, the singular values equal to this relative tolerance.
POSE_SCALE_RANGE = (1e-3, 1e3)
POSE_SIMILARITY_TOLERANCE = 1e-2


@dataclass(init=False, eq=False)
class Session:
    """One segmentation session.

    Attributes
    ----------
    image_path, model_path : Path or None
        The image (NIfTI) and the shape model (.npz); absolute once loaded from a file.
    points : (P, 3) float ndarray
        Contour points, world RAS mm.
    normals : (P, 3) float ndarray or None
        Optional unit normals of the points.
    point_slices : list of (str, float) or None
        For each point, the plane it was drawn in (see :data:`PLANE_NAMES`) and that
        slice's depth in mm, so that "clear this slice" still works after reopening.
    coef : (M,) float ndarray or None
        Shape coefficients of the current fit.
    pose : (4, 4) float ndarray or None
        Model frame -> world transform of the current fit.
    fit : dict
        Fit settings: ``method``, ``prior_weight`` and any other options (JSON values).
    window : (2,) float tuple or None
        Display window width and level.
    crosshair : (3,) float ndarray or None
        Crosshair position, world RAS mm.
    info : dict
        Free-form metadata.
    structures : list of SessionStructure
        Every structure when there are several (else empty); the top-level model, points,
        coefficients and pose are then those of ``structures[active_structure]``.
    active_structure : int
        Index of the active structure in ``structures``.

    ``image=`` and ``model=`` are accepted as aliases of ``image_path=`` and ``model_path=``,
    and ``fit_method=`` / ``prior_weight=`` set the matching ``fit`` entries.
    """

    image_path: Path | None
    model_path: Path | None
    points: np.ndarray
    normals: np.ndarray | None
    point_slices: list[tuple[str, float]] | None
    coef: np.ndarray | None
    pose: np.ndarray | None
    fit: dict[str, Any]
    window: tuple[float, float] | None
    crosshair: np.ndarray | None
    info: dict[str, Any] = field(default_factory=dict)
    structures: list[SessionStructure] = field(default_factory=list)
    active_structure: int = 0

    def __init__(self, image_path: str | os.PathLike | None = None,
                 model_path: str | os.PathLike | None = None,
                 points: np.ndarray | None = None, normals: np.ndarray | None = None,
                 point_slices: Any = None, coef: np.ndarray | None = None,
                 pose: np.ndarray | None = None, fit: dict[str, Any] | None = None,
                 window: Any = None, crosshair: np.ndarray | None = None,
                 info: dict[str, Any] | None = None, *,
                 image: str | os.PathLike | None = None, model: str | os.PathLike | None = None,
                 fit_method: str | None = None, prior_weight: float | None = None,
                 structures: list[SessionStructure] | None = None, active_structure: int = 0):
        image_path = image_path if image_path is not None else image
        model_path = model_path if model_path is not None else model
        self.image_path = Path(image_path) if image_path not in (None, "") else None
        self.model_path = Path(model_path) if model_path not in (None, "") else None
        self.points = _float_array(np.zeros((0, 3)) if points is None else points, "points")
        if self.points.size == 0:
            self.points = self.points.reshape(0, 3)
        self.normals = None if normals is None else _float_array(normals, "normals")
        self.point_slices = None if point_slices is None else _plane_list(point_slices)
        self.coef = None if coef is None else _float_array(coef, "coef")
        self.pose = None if pose is None else _float_array(pose, "pose")
        self.fit = dict(fit or {})
        if fit_method is not None:
            self.fit["method"] = fit_method
        if prior_weight is not None:
            self.fit["prior_weight"] = float(prior_weight)
        self.window = None if window is None else tuple(_float_array(window, "window").tolist())
        self.crosshair = None if crosshair is None else _float_array(crosshair, "crosshair")
        self.info = dict(info or {})
        self.structures = list(structures or [])
        self.active_structure = int(active_structure)
        problem = self.validate()
        if problem:
            raise ValueError(problem)

    # -- aliases used by the GUI ---------------------------------------------------------------
    @property
    def image(self) -> str | None:
        return None if self.image_path is None else str(self.image_path)

    @property
    def model(self) -> str | None:
        return None if self.model_path is None else str(self.model_path)

    @property
    def fit_method(self) -> str | None:
        return self.fit.get("method")

    @property
    def prior_weight(self) -> float | None:
        value = self.fit.get("prior_weight")
        return None if value is None else float(value)

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def point_axes(self) -> np.ndarray | None:
        """World axis (0, 1, 2 = x, y, z) normal to each point's slice, (P,) int, or None."""
        if self.point_slices is None:
            return None
        return np.array([PLANE_NAMES.index(name) for name, _ in self.point_slices], np.int64)

    @property
    def point_depths(self) -> np.ndarray | None:
        """Depth (mm) of each point's slice, (P,), or None."""
        if self.point_slices is None:
            return None
        return np.array([depth for _, depth in self.point_slices], np.float64)

    def validate(self) -> str | None:
        """Describe the first inconsistency (shapes, NaN), or None if the session is valid."""
        p = self.n_points
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            return f"points must be (P, 3), got shape {self.points.shape}"
        if self.normals is not None and self.normals.shape != (p, 3):
            return f"normals must be ({p}, 3) like the points, got shape {self.normals.shape}"
        if self.point_slices is not None and len(self.point_slices) != p:
            return f"point_slices must have one entry per point ({p}), got {len(self.point_slices)}"
        if self.coef is not None and self.coef.ndim != 1:
            return f"coef must be a vector (M,), got shape {self.coef.shape}"
        if self.pose is not None:
            problem = pose_problem(self.pose, "pose")
            if problem:
                return problem
        if self.window is not None and len(self.window) != 2:
            return f"window must be [width, level], got {len(self.window)} values"
        if self.crosshair is not None and self.crosshair.shape != (3,):
            return f"crosshair must be (3,), got shape {self.crosshair.shape}"
        for name in ("points", "normals", "coef", "crosshair"):
            value = getattr(self, name)
            if value is not None and not np.all(np.isfinite(value)):
                return f"{name} contain NaN or infinite values"
        for name in ("points", "crosshair"):
            value = getattr(self, name)
            problem = None if value is None else coordinate_problem(value.reshape(-1, 3), name)
            if problem:
                return problem
        for name, path in (("image", self.image_path), ("model", self.model_path)):
            if path is not None and "\x00" in str(path):
                return f"the {name} path holds a null byte: not a file path"
        if len(self.structures) > MAX_STRUCTURES:
            return (f"{len(self.structures)} structures, more than the {MAX_STRUCTURES} a "
                    "session may hold")
        problem = planning_problem(self.info.get("planning"), max(len(self.structures), 1))
        if problem:
            return problem
        if self.window is not None and not all(np.isfinite(self.window)):
            return "window contains NaN or infinite values"
        if self.point_slices is not None and \
                not np.all(np.isfinite([d for _, d in self.point_slices])):
            return "point_slices depths contain NaN or infinite values"
        weight = self.fit.get("prior_weight")
        if weight is not None and (not isinstance(weight, (int, float)) or isinstance(weight, bool)
                                   or not np.isfinite(weight) or weight < 0):
            return f"fit prior_weight must be a number >= 0, got {_short(weight)}"
        from core.reconstruction import METHODS, POSES

        for key, allowed in (("method", METHODS), ("pose", POSES)):
            value = self.fit.get(key)
            if value is not None and value not in allowed:
                return f"fit {key} {_short(value)} is not one of {', '.join(allowed)}"
        for k, st in enumerate(self.structures):
            if not isinstance(st, SessionStructure):
                return f"structures[{k}] must be a SessionStructure"
        if self.structures and not 0 <= self.active_structure < len(self.structures):
            return (f"active_structure {self.active_structure} is not an index of the "
                    f"{len(self.structures)} structures")
        return None

    def model_problem(self, model) -> str | None:
        """Why this session's fit cannot be shown with ``model`` (a ShapeModel), or None."""
        if self.coef is not None and self.coef.shape[0] != model.n_factors:
            return (f"the session holds {self.coef.shape[0]} shape coefficients but the model "
                    f"has {model.n_factors} factors (was the model rebuilt since?)")
        return None

    def missing_files(self) -> list[Path]:
        """Referenced image/model files that do not exist (after :func:`load_session`)."""
        paths = [self.image_path, self.model_path] + [st.model_path for st in self.structures]
        return list(dict.fromkeys(p for p in paths if p is not None and not p.exists()))


@dataclass(eq=False)
class SessionStructure:
    """One structure of a session with several (``Session.structures``).

    ``color`` is RGB in 0..1 (or None: the GUI's default); the arrays follow the top-level
    conventions of :class:`Session`; ``placement`` is the pose the user set (the pose
    prior's centre), or None.
    """

    name: str = ""
    side: str = ""
    color: tuple[float, float, float] | None = None
    visible: bool = True
    locked: bool = False
    model_path: Path | None = None
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    normals: np.ndarray | None = None
    point_slices: list[tuple[str, float]] | None = None
    coef: np.ndarray | None = None
    pose: np.ndarray | None = None
    placement: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.name, self.side = str(self.name), str(self.side)
        self.visible, self.locked = bool(self.visible), bool(self.locked)
        if self.model_path not in (None, ""):
            self.model_path = Path(self.model_path)
        else:
            self.model_path = None
        if self.color is not None:
            color = _float_array(self.color, "structure color")
            if color.shape != (3,) or not np.all((color >= 0) & (color <= 1)):
                raise ValueError(f"structure color must be [r, g, b] in 0..1, got {self.color!r}")
            self.color = tuple(color.tolist())
        self.points = _float_array(self.points, "structure points").reshape(-1, 3)
        for name in ("normals", "coef", "pose", "placement"):
            value = getattr(self, name)
            if value is not None:
                setattr(self, name, _float_array(value, f"structure {name}"))
        if self.point_slices is not None:
            self.point_slices = _plane_list(self.point_slices)
        p = len(self.points)
        if self.normals is not None and self.normals.shape != (p, 3):
            raise ValueError(f"structure normals must be ({p}, 3), got {self.normals.shape}")
        if self.point_slices is not None and len(self.point_slices) != p:
            raise ValueError(f"structure point_slices must have {p} entries, got {len(self.point_slices)}")
        for name in ("pose", "placement"):
            value = getattr(self, name)
            problem = None if value is None else pose_problem(value, f"structure {name}")
            if problem:
                raise ValueError(problem)
        if self.model_path is not None and "\x00" in str(self.model_path):
            raise ValueError("the structure model path holds a null byte: not a file path")
        problem = coordinate_problem(self.points, "structure points")
        if problem:
            raise ValueError(problem)
        if not np.all(np.isfinite(self.points)):
            raise ValueError("structure points contain NaN or infinite values")


def pose_problem(pose: np.ndarray, name: str) -> str | None:
    """Why ``pose`` is not a usable model -> world transform, or None.

    A 4x4 similarity: finite, last row (0, 0, 0, 1), translation within
    :data:`core.io.limits.MAX_COORDINATE_MM`, 3x3 part s R with s in
    :data:`POSE_SCALE_RANGE` (singular values equal within :data:`POSE_SIMILARITY_TOLERANCE`).
    A pose holding 1e200 made the GUI fail deep in its geometry (an IndexError).
    """
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        return f"{name} must be 4x4, got shape {pose.shape}"
    if not np.all(np.isfinite(pose)):
        return f"{name} must be a finite, invertible 4x4 matrix (it holds NaN or inf)"
    from core.io.limits import MAX_COORDINATE_MM

    shift = float(np.abs(pose[:3, 3]).max())
    if shift > MAX_COORDINATE_MM:
        return (f"{name} moves the model {shift:.3g} mm, beyond {MAX_COORDINATE_MM:.0e} mm: "
                "not a pose in a scan")
    if np.abs(pose[:3, :3]).max() > 1e12:
        return f"{name} scales by up to {np.abs(pose[:3, :3]).max():.3g}: not a pose"
    singular = np.linalg.svd(pose[:3, :3], compute_uv=False)
    low, high = POSE_SCALE_RANGE
    if singular[-1] < low or singular[0] > high:
        return (f"{name} must be an invertible 4x4 matrix with a scale of {low:g}-{high:g} "
                f"(its 3x3 part scales by {singular[-1]:.3g}-{singular[0]:.3g})")
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        return f"{name} must end with the row 0 0 0 1, got {_short(pose[3].tolist())}"
    if singular[0] / singular[-1] - 1 > POSE_SIMILARITY_TOLERANCE:
        return (f"{name} is not a similarity (rotation, uniform scale, translation): its 3x3 "
                f"part scales by {singular[-1]:.4g}-{singular[0]:.4g} along different axes")
    return None


def _planning_vector(value: Any, what: str) -> str | None:
    if value is None:
        return None
    try:
        vector = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return f"info.planning {what} must be [x, y, z] (numbers), got {_short(value)}"
    if vector.shape != (3,):
        return f"info.planning {what} must be [x, y, z], got {_short(value)}"
    return coordinate_problem(vector[None], f"info.planning {what} point(s)")


def planning_problem(planning: Any, n_structures: int) -> str | None:
    """Why a session's ``info.planning`` block (the workspace's AC, PC, midline point and per
    structure a target and an entry point) cannot be used, or None (None or {}: no plan)."""
    if planning is None:
        return None
    if not isinstance(planning, dict):
        return f"info.planning must be a JSON object, got {_short(planning)}"
    for key in ("ac", "pc", "midline"):
        problem = _planning_vector(planning.get(key), key)
        if problem:
            return problem
    items = planning.get("structures", [])
    if items is None:
        return None
    if not isinstance(items, list):
        return f"info.planning structures must be a list, got {_short(items)}"
    if len(items) > MAX_STRUCTURES:
        return f"info.planning lists {len(items)} structures, more than {MAX_STRUCTURES}"
    for k, item in enumerate(items):
        if not isinstance(item, dict):
            return f"info.planning structures[{k}] must be an object, got {_short(item)}"
        index = item.get("structure")
        if not isinstance(index, int) or isinstance(index, bool):
            return f"info.planning structures[{k}].structure must be an index, got {_short(index)}"
        if not 0 <= index < n_structures:
            return (f"info.planning structures[{k}] refers to structure {index + 1}, the "
                    f"session has {n_structures}")
        for key in ("target", "entry"):
            problem = _planning_vector(item.get(key), f"structures[{k}].{key}")
            if problem:
                return problem
    return None


def _structure_document(st: SessionStructure, base: Path | None, array, packed: bool) -> dict[str, Any]:
    return {"name": st.name, "side": st.side,
            "color": None if st.color is None else list(st.color),
            "visible": st.visible, "locked": st.locked,
            "model": _relative(st.model_path, base), "model_absolute": _relative(st.model_path, None),
            "points": array(st.points), "normals": array(st.normals),
            "point_slices": _slices_document(st.point_slices, packed),
            "coef": array(st.coef), "pose": array(st.pose), "placement": array(st.placement)}


def _slices_document(slices: list[tuple[str, float]] | None, packed: bool) -> Any:
    if slices is None:
        return None
    if packed:
        return {"plane": _packed([PLANE_NAMES.index(n) for n, _ in slices], "<i1"),
                "depth": _packed([d for _, d in slices])}
    return [[name, depth] for name, depth in slices]


def _slices_from(slices: Any) -> Any:
    """Per-point slice records from their JSON form (lists, or packed planes and depths)."""
    if isinstance(slices, dict):
        planes = _unpacked(slices.get("plane"), "point_slices plane")
        depths = _unpacked(slices.get("depth"), "point_slices depth")
        if planes is None or depths is None or np.shape(planes) != np.shape(depths):
            raise ValueError("point_slices plane and depth lists differ in length")
        slices = list(zip(np.asarray(planes).tolist(), np.asarray(depths).tolist()))
    return slices


def _structures_from(value: Any, base: Path | None, source: Path) -> list[SessionStructure]:
    if value is None:
        return []
    if not isinstance(value, list):
        raise ValueError("structures must be a list of objects")
    if len(value) > MAX_STRUCTURES:  # before any is read: each loads a model to plan
        raise ValueError(f"{len(value)} structures, more than the {MAX_STRUCTURES} a session "
                         "may hold")
    out = []
    for k, doc in enumerate(value):
        if not isinstance(doc, dict):
            raise ValueError(f"structures[{k}] must be an object")
        try:
            points = _unpacked(doc.get("points"), "points")
            out.append(SessionStructure(
                name=doc.get("name") or "", side=doc.get("side") or "", color=doc.get("color"),
                visible=doc.get("visible", True), locked=doc.get("locked", False),
                model_path=_located(doc, "model", base, source),
                points=points if points is not None else np.zeros((0, 3)),
                normals=_unpacked(doc.get("normals"), "normals"),
                point_slices=_slices_from(doc.get("point_slices")),
                coef=_unpacked(doc.get("coef"), "coef"), pose=_unpacked(doc.get("pose"), "pose"),
                placement=_unpacked(doc.get("placement"), "placement")))
        except ValueError as exc:
            raise ValueError(f"structures[{k}]: {exc}") from None
    return out


def _active_index(value: Any) -> int:
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"active_structure must be an index, got {value!r}")
    return value


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_session_model(session: Session, model, source: str | os.PathLike) -> None:
    """Raise :class:`DataFileError` naming ``source`` (the session file) when the session's
    coefficients do not fit ``model``: refuse the session as a whole, before any of it is
    applied, instead of failing half-way."""
    problem = session.model_problem(model)
    if problem:
        raise DataFileError(source, problem)


def _float_array(value: Any, name: str) -> np.ndarray:
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers") from None


def _plane_list(value: Any) -> list[tuple[str, float]]:
    """Normalise per-point slice records to [(plane name, depth mm), ...]."""
    out = []
    for i, entry in enumerate(value):
        try:
            plane, depth = entry
            depth = float(depth)
        except (TypeError, ValueError):
            raise ValueError(f"point_slices[{i}] must be [plane, depth], got {entry!r}") from None
        if isinstance(plane, (int, np.integer, float, np.floating)) and float(plane) in (0, 1, 2):
            plane = PLANE_NAMES[int(plane)]
        if plane not in PLANE_NAMES:
            raise ValueError(f"point_slices[{i}] has unknown plane {plane!r} (use "
                             f"{', '.join(PLANE_NAMES)} or world axis 0, 1, 2)")
        out.append((str(plane), depth))
    return out


# --------------------------------------------------------------------------------------
# Session files
# --------------------------------------------------------------------------------------


def _relative(path: Path | None, base: Path | None) -> str | None:
    """``path`` relative to folder ``base`` (POSIX separators); absolute when not possible."""
    if path is None:
        return None
    absolute = Path(os.path.abspath(path))
    if base is None:
        return str(absolute)
    try:
        return Path(os.path.relpath(absolute, os.path.abspath(base))).as_posix()
    except ValueError:  # another drive on Windows
        return str(absolute)


def _resolve(stored: Any, base: Path | None, source: Path, key: str) -> Path | None:
    if stored is None or stored == "":
        return None
    if not isinstance(stored, str):
        raise DataFileError(source, f"'{key}' must be a file path (string), got {stored!r}")
    if "\x00" in stored:
        raise DataFileError(source, f"'{key}' holds a null byte: not a file path")
    path = Path(stored)
    if not path.is_absolute() and base is not None:
        path = base / path
    return Path(os.path.normpath(path))


def _located(doc: dict[str, Any], key: str, base: Path | None, source: Path) -> Path | None:
    """The file ``doc[key]`` refers to: relative to the session's folder first; if that is
    missing but the absolute path recorded at saving exists (the session file alone was
    moved), that one."""
    relative = _resolve(doc.get(key), base, source, key)
    absolute = _resolve(doc.get(f"{key}_absolute"), None, source, f"{key}_absolute")
    if relative is not None and not relative.exists() and absolute is not None and \
            absolute.exists():
        return absolute
    return relative if relative is not None else absolute


def _packed(a: ArrayLike, dtype: str = "<f8") -> dict[str, Any]:
    """An array as {"dtype", "shape", "base64"}: exact and fast (used by the recovery file)."""
    a = np.ascontiguousarray(a, dtype=dtype)
    return {"dtype": dtype, "shape": list(a.shape),
            "base64": base64.b64encode(a.tobytes()).decode("ascii")}


def _unpacked(value: Any, name: str) -> Any:
    """Inverse of :func:`_packed`; lists and None pass through."""
    if not isinstance(value, dict):
        return value
    try:
        dtype = np.dtype(value["dtype"])
        if dtype.kind not in "iuf":
            raise ValueError(f"dtype {dtype}")
        shape = tuple(int(s) for s in value["shape"])
        return np.frombuffer(base64.b64decode(value["base64"], validate=True),
                             dtype=dtype).reshape(shape)
    except (KeyError, TypeError, ValueError, binascii.Error) as exc:
        raise ValueError(f"{name} is not a valid packed array ({_one_line(exc)})") from None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:200] or type(exc).__name__


def to_document(session: Session, base: Path | None, packed: bool = False) -> dict[str, Any]:
    """The JSON document of ``session``; paths relative to ``base`` (absolute if None).

    ``packed`` stores the arrays as base64 (the recovery file: ~20x faster to write than
    decimal text); session files keep readable nested lists.
    """
    problem = session.validate()
    if problem:
        raise ValueError(problem)

    def array(a: np.ndarray | None):
        if a is None:
            return None
        return _packed(a) if packed else a.tolist()

    slice_doc = _slices_document(session.point_slices, packed)
    info = dict(session.info)
    info["saved"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return {
        "format": SESSION_FORMAT,
        "format_version": SESSION_FORMAT_VERSION,
        "image": _relative(session.image_path, base),
        "model": _relative(session.model_path, base),
        "image_absolute": _relative(session.image_path, None),
        "model_absolute": _relative(session.model_path, None),
        "points": array(session.points),
        "normals": array(session.normals),
        "point_slices": slice_doc,
        "coef": array(session.coef),
        "pose": array(session.pose),
        "fit": session.fit,
        "window": None if session.window is None else list(session.window),
        "crosshair": array(session.crosshair),
        **({"structures": [_structure_document(st, base, array, packed) for st in session.structures],
            "active_structure": session.active_structure} if session.structures else {}),
        "info": info,
    }


def from_document(doc: Any, source: Path, base: Path | None) -> Session:
    """The session a parsed JSON document holds; relative paths resolved against ``base``
    (None: stored absolute, as in recovery files). Raises DataFileError naming ``source``."""
    if not isinstance(doc, dict):
        raise DataFileError(source, "not an SSM Studio session (the JSON is not an object)")
    if doc.get("format") != SESSION_FORMAT:
        raise DataFileError(source, f"not an SSM Studio session (format {doc.get('format')!r}, "
                                    f"expected '{SESSION_FORMAT}')")
    version = doc.get("format_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise DataFileError(source, f"session has no valid format_version (got {version!r})")
    if version > SESSION_FORMAT_VERSION:
        raise DataFileError(source, f"session format version {version} is newer than this SSM "
                                    f"Studio reads (version {SESSION_FORMAT_VERSION}); "
                                    "update SSM Studio")
    if version < 1:
        raise DataFileError(source, f"session format version {version} is not supported")
    for key in ("fit", "info"):
        if not isinstance(doc.get(key) or {}, dict):
            raise DataFileError(source, f"'{key}' must be a JSON object")
    try:
        slices = _slices_from(doc.get("point_slices"))
        points = _unpacked(doc.get("points"), "points")
        return Session(
            image_path=_located(doc, "image", base, source),
            model_path=_located(doc, "model", base, source),
            points=points if points is not None else np.zeros((0, 3)),
            normals=_unpacked(doc.get("normals"), "normals"), point_slices=slices,
            coef=_unpacked(doc.get("coef"), "coef"), pose=_unpacked(doc.get("pose"), "pose"),
            fit=doc.get("fit") or {}, window=doc.get("window"),
            crosshair=_unpacked(doc.get("crosshair"), "crosshair"), info=doc.get("info") or {},
            structures=_structures_from(doc.get("structures"), base, source),
            active_structure=_active_index(doc.get("active_structure", 0)),
        )
    except DataFileError:
        raise  # names the file already
    except (ValueError, TypeError, OverflowError) as exc:
        raise DataFileError(source, f"invalid session: {exc}") from None


def save_session(path: str | os.PathLike, session: Session) -> None:
    """Write ``session`` as JSON at ``path`` (atomically), paths relative to its folder."""
    path = Path(path)
    try:
        doc = to_document(session, path.parent)
    except ValueError as exc:
        raise DataFileError(path, f"cannot save an invalid session: {exc}") from None
    with atomic_path(path) as tmp:
        tmp.write_text(_readable_json(doc), encoding="utf-8")


def _readable_json(doc: dict[str, Any]) -> str:
    """One key per line; tables (lists of lists, e.g. points) one row per line."""
    lines = []
    for key, value in doc.items():
        if isinstance(value, list) and value and all(isinstance(row, list) for row in value):
            text = "[\n    " + ",\n    ".join(json.dumps(row) for row in value) + "\n  ]"
        else:
            text = json.dumps(value)
        lines.append(f"  {json.dumps(key)}: {text}")
    return "{\n" + ",\n".join(lines) + "\n}\n"


def read_document(path: Path) -> Any:
    """The parsed JSON of a session (or recovery) file; DataFileError naming it if unreadable."""
    if not path.exists():
        raise DataFileError(path, "file not found")
    if path.is_dir():
        raise DataFileError(path, "is a folder, not a file")
    if not path.is_file():
        require_file(path)  # a FIFO or a device: say which
    raw = path.read_bytes()
    if not raw.strip():
        raise DataFileError(path, "file is empty")
    try:
        return json.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise DataFileError(path, "not a session file (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise DataFileError(path, f"not valid JSON (line {exc.lineno}, column {exc.colno}: "
                                  f"{exc.msg}); truncated?") from None
    except RecursionError:
        raise DataFileError(path, "not a session file (JSON nested too deeply to be read)") \
            from None


def load_session(path: str | os.PathLike) -> Session:
    """Read a session file; relative image/model paths are resolved against its folder.

    Raises
    ------
    DataFileError
        Not found, empty, not JSON, not a session, a newer format version, wrong array
        shapes or NaN values; the message names the file.
    """
    path = Path(path)
    return from_document(read_document(path), path, Path(os.path.abspath(path)).parent)
