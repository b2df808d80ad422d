"""Every file SSM Studio reads or writes: volumes, meshes, point sets and shape models.

One place for I/O so that coordinates and errors are handled the same way everywhere:

- volumes: NIfTI-1/2 (.nii, .nii.gz) through nibabel, kept with nibabel's best voxel->world
  affine (sform if set, else qform; RAS, mm), oblique affines included;
- meshes: .vtk .vtp .stl .ply .obj through pyvista/VTK, GIfTI surfaces (.gii) through nibabel,
  always triangulated on load, as :class:`TriMesh` (vertices/faces numpy arrays);
- point sets: CSV (header line, ``x,y,z`` or ``x,y,z,nx,ny,nz``, world RAS mm) and 3D Slicer
  markups JSON (.mrk.json; LPS or RAS on read, LPS on write as Slicer does);
- shape models: the versioned ``.npz`` format documented in :func:`save_model`.

Every save is atomic (written to a temporary file in the target folder, then renamed).
Every load error is a :class:`DataFileError` naming the file and the problem.
"""

from __future__ import annotations

import contextlib
import csv
import gzip
import json
import os
import tempfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.shape_model import ShapeModel

MODEL_FORMAT = "ssm-studio-model"
MODEL_FORMAT_VERSION = 1

MESH_SUFFIXES = (".vtk", ".vtp", ".stl", ".ply", ".obj", ".gii")
VOLUME_SUFFIXES = (".nii", ".nii.gz")
POINT_SUFFIXES = (".csv", ".mrk.json", ".json")


class DataFileError(ValueError):
    """A file could not be read or written; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for double in (".nii.gz", ".mrk.json"):
        if name.endswith(double):
            return double
    return path.suffix.lower()


def _require_file(path: str | os.PathLike) -> Path:
    path = Path(path)
    if not path.exists():
        raise DataFileError(path, "file not found")
    if path.is_dir():
        raise DataFileError(path, "is a folder, not a file")
    if path.stat().st_size == 0:
        raise DataFileError(path, "file is empty (0 bytes)")
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary name keeps the target's suffix so that writers choosing a format by
    extension (VTK, nibabel) pick the right one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{_suffix(path)}",
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def atomic_write_json(path: str | os.PathLike, obj: object) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def _json_default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


# --------------------------------------------------------------------------------------
# Volumes
# --------------------------------------------------------------------------------------


@dataclass
class Volume:
    """A 3D image with its voxel -> world (RAS, mm) affine.

    Attributes
    ----------
    data : (I, J, K) ndarray
        Voxel values, indexed [i, j, k].
    affine : (4, 4) float ndarray
        Maps homogeneous voxel indices (i, j, k, 1) to world RAS mm (column vectors).
    path : Path or None
        Where it was read from.
    """

    data: np.ndarray
    affine: np.ndarray
    path: Path | None = None

    def __post_init__(self) -> None:
        self.affine = np.asarray(self.affine, dtype=np.float64)
        if self.data.ndim != 3:
            raise ValueError(f"a volume must be 3D, got shape {self.data.shape}")
        if self.affine.shape != (4, 4) or abs(np.linalg.det(self.affine[:3, :3])) < 1e-12:
            raise ValueError("the affine must be an invertible 4x4 matrix")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.data.shape)  # type: ignore[return-value]

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along i, j, k in mm (column norms of the affine), (3,)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def is_oblique(self) -> bool:
        """True when the voxel axes are not aligned with the world axes."""
        direction = self.affine[:3, :3] / self.spacing
        return bool(np.any(np.abs(np.abs(direction).max(axis=0) - 1.0) > 1e-6))

    def voxel_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """Map voxel indices (..., 3) (fractional allowed) to world RAS mm (..., 3)."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def world_to_voxel(self, xyz: np.ndarray) -> np.ndarray:
        """Map world RAS mm (..., 3) to fractional voxel indices (..., 3)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        inv = np.linalg.inv(self.affine)
        return xyz @ inv[:3, :3].T + inv[:3, 3]

    def contains_voxel(self, ijk: np.ndarray) -> np.ndarray:
        """Whether rounded voxel indices (..., 3) fall inside the grid, (...,) bool."""
        idx = np.rint(np.asarray(ijk)).astype(np.int64)
        return np.all((idx >= 0) & (idx < np.array(self.shape)), axis=-1)

    def value_at(self, xyz: np.ndarray) -> float | None:
        """Intensity of the voxel nearest to world point ``xyz`` (3,), None if outside."""
        ijk = np.rint(self.world_to_voxel(xyz)).astype(np.int64)
        if not self.contains_voxel(ijk):
            return None
        return float(self.data[tuple(ijk)])

    def world_bounds(self) -> np.ndarray:
        """Axis-aligned world bounding box of the voxel centres, (2, 3): min and max."""
        corners = np.array(np.meshgrid(*[[0, s - 1] for s in self.shape], indexing="ij"))
        pts = self.voxel_to_world(corners.reshape(3, -1).T)
        return np.stack([pts.min(axis=0), pts.max(axis=0)])

    def axis_codes(self) -> tuple[str, str, str]:
        """nibabel-style orientation codes of the voxel axes, e.g. ('R', 'A', 'S')."""
        import nibabel as nib

        return tuple(nib.aff2axcodes(self.affine))  # type: ignore[return-value]


def load_volume(path: str | os.PathLike) -> Volume:
    """Read a 3D NIfTI image (.nii or .nii.gz).

    The affine is nibabel's best affine (sform when its code is set, else qform), so oblique
    acquisitions keep their orientation. A 4D image with a single volume is squeezed to 3D;
    other 4D or 2D images are refused.

    Raises
    ------
    DataFileError
        Not found, empty, truncated or corrupt gzip, not a NIfTI file, wrong dimensionality,
        non-finite or singular affine.
    """
    import nibabel as nib

    path = _require_file(path)
    if _suffix(path) not in VOLUME_SUFFIXES:
        raise DataFileError(path, f"not a NIfTI file name (expected .nii or .nii.gz, got "
                                  f"'{_suffix(path) or path.name}')")
    try:
        img = nib.load(str(path))
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip data ({exc})") from None
    except nib.filebasedimages.ImageFileError as exc:
        raise DataFileError(path, f"not a NIfTI image ({exc})") from None
    except Exception as exc:  # nibabel raises many types for bad headers
        raise DataFileError(path, f"could not read NIfTI header ({type(exc).__name__}: {exc})") from None
    if not isinstance(img, (nib.Nifti1Image, nib.Nifti2Image)):
        raise DataFileError(path, f"not a NIfTI image (nibabel read it as {type(img).__name__})")
    shape = img.shape
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    if len(shape) != 3:
        raise DataFileError(path, f"a 3D image is needed, this one is {len(img.shape)}D with shape "
                                  f"{tuple(img.shape)}")
    if min(shape) < 1:
        raise DataFileError(path, f"image has an empty dimension, shape {tuple(img.shape)}")
    affine = np.asarray(img.affine, dtype=np.float64)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise DataFileError(path, "the voxel-to-world affine is singular or not finite")
    try:
        data = np.asarray(img.dataobj)
        if data.dtype.kind not in "iuf" or (img.dataobj.slope not in (None, 1.0)):
            data = img.get_fdata(dtype=np.float32)
    except (EOFError, zlib.error, gzip.BadGzipFile, OSError, ValueError) as exc:
        raise DataFileError(path, f"image data are truncated or corrupt ({exc})") from None
    data = data.reshape(shape)
    if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
        data = np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0)
    return Volume(data=data, affine=affine, path=path)


def save_volume(path: str | os.PathLike, data: np.ndarray, affine: np.ndarray) -> None:
    """Write a 3D array as NIfTI-1 with ``affine`` as both sform and qform (code 1, scanner)."""
    import nibabel as nib

    path = Path(path)
    if _suffix(path) not in VOLUME_SUFFIXES:
        raise DataFileError(path, "volumes are written as .nii or .nii.gz")
    data = np.asarray(data)
    if data.ndim != 3:
        raise DataFileError(path, f"a 3D array is needed, got shape {data.shape}")
    if data.dtype == bool:
        data = data.astype(np.uint8)
    img = nib.Nifti1Image(data, np.asarray(affine, dtype=np.float64))
    img.set_sform(img.affine, code=1)
    img.set_qform(img.affine, code=1)
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))


# --------------------------------------------------------------------------------------
# Meshes
# --------------------------------------------------------------------------------------


@dataclass
class TriMesh:
    """A triangle surface as numpy arrays.

    Attributes
    ----------
    vertices : (N, 3) float64 ndarray
        Vertex positions (world mm unless stated otherwise).
    faces : (F, 3) int64 ndarray
        Triangles as vertex indices.
    name : str
        Usually the file name it came from.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = ""

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64)

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def to_polydata(self):  # -> pyvista.PolyData
        """The mesh as a ``pyvista.PolyData`` (for VTK filters and rendering)."""
        import pyvista as pv

        cells = np.hstack([np.full((len(self.faces), 1), 3, np.int64), self.faces]).ravel()
        return pv.PolyData(self.vertices.copy(), cells)

    @classmethod
    def from_polydata(cls, poly, name: str = "") -> TriMesh:
        """Build from a triangulated ``pyvista.PolyData``."""
        faces = _triangles_of(poly)
        return cls(np.asarray(poly.points, dtype=np.float64), faces, name)

    def check(self, source: str | os.PathLike | None = None) -> TriMesh:
        """Raise :class:`DataFileError` (naming ``source``) if the mesh is unusable."""
        src = source if source is not None else (self.name or "<mesh>")
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise DataFileError(src, f"vertices must be (N, 3), got {self.vertices.shape}")
        if self.n_vertices == 0:
            raise DataFileError(src, "empty mesh (no vertices)")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3 or len(self.faces) == 0:
            raise DataFileError(src, "mesh has no triangles (points or lines only?)")
        bad = ~np.all(np.isfinite(self.vertices), axis=1)
        if bad.any():
            raise DataFileError(src, f"{int(bad.sum())} vertices have NaN or infinite coordinates")
        if self.faces.min() < 0 or self.faces.max() >= self.n_vertices:
            raise DataFileError(src, "faces index vertices that do not exist")
        return self


def _triangles_of(poly) -> np.ndarray:
    if poly.n_cells == 0 or poly.faces.size == 0:
        return np.zeros((0, 3), np.int64)
    if not poly.is_all_triangles:
        poly = poly.triangulate()
    faces = np.asarray(poly.faces).reshape(-1, 4)
    return faces[:, 1:].astype(np.int64)


def load_mesh(path: str | os.PathLike) -> TriMesh:
    """Read a surface mesh and triangulate it.

    Formats: .vtk (legacy polydata or unstructured grid surface), .vtp, .stl, .ply, .obj via
    pyvista, and GIfTI (.gii, pointset + triangle arrays) via nibabel. Unused points are kept
    (vertex indices stay those of the file).

    Raises
    ------
    DataFileError
        Not found, empty, unreadable, no triangles, NaN vertices, faces out of range.
    """
    path = _require_file(path)
    suffix = _suffix(path)
    if suffix not in MESH_SUFFIXES:
        raise DataFileError(path, f"unsupported mesh format '{suffix}' (use one of "
                                  f"{', '.join(MESH_SUFFIXES)})")
    if suffix == ".gii":
        mesh = _load_gifti(path)
    else:
        mesh = _load_vtk_family(path)
    return mesh.check(path)


def _load_vtk_family(path: Path) -> TriMesh:
    import pyvista as pv
    import vtk

    # VTK readers report problems on their own error stream instead of raising: capture it.
    errors = vtk.vtkStringOutputWindow()
    previous = vtk.vtkOutputWindow.GetInstance()
    vtk.vtkOutputWindow.SetInstance(errors)
    try:
        data = pv.read(str(path))
    except Exception as exc:
        raise DataFileError(path, f"could not read mesh ({type(exc).__name__}: {exc})") from None
    finally:
        vtk.vtkOutputWindow.SetInstance(previous)
    if isinstance(data, pv.MultiBlock):
        data = data.combine()
    if data is None or data.n_points == 0:
        detail = errors.GetOutput().strip().splitlines()
        why = f" ({detail[-1][:200]})" if detail else ""
        raise DataFileError(path, f"empty mesh or unreadable file{why}")
    if not isinstance(data, pv.PolyData):
        data = data.extract_surface()
    if np.any(~np.isfinite(np.asarray(data.points))):
        n_bad = int(np.sum(~np.all(np.isfinite(np.asarray(data.points)), axis=1)))
        raise DataFileError(path, f"{n_bad} vertices have NaN or infinite coordinates")
    faces = _triangles_of(data)
    if len(faces) == 0:
        raise DataFileError(path, "mesh has no polygons that can be triangulated "
                                  "(points or lines only)")
    return TriMesh(np.asarray(data.points, dtype=np.float64), faces, path.name)


def _load_gifti(path: Path) -> TriMesh:
    import nibabel as nib

    try:
        img = nib.load(str(path))
    except Exception as exc:
        raise DataFileError(path, f"not a readable GIfTI file ({type(exc).__name__}: {exc})") from None
    if not isinstance(img, nib.gifti.GiftiImage):
        raise DataFileError(path, "not a GIfTI image")
    points = img.get_arrays_from_intent("NIFTI_INTENT_POINTSET")
    tris = img.get_arrays_from_intent("NIFTI_INTENT_TRIANGLE")
    if not points or not tris:
        raise DataFileError(path, "GIfTI file has no surface (needs POINTSET and TRIANGLE arrays)")
    return TriMesh(points[0].data, tris[0].data, path.name)


def save_mesh(path: str | os.PathLike, mesh: TriMesh, point_data: dict | None = None) -> None:
    """Write a triangle mesh; format chosen by extension (see :data:`MESH_SUFFIXES`).

    ``point_data`` (name -> (N,) or (N, k) array) is stored as VTK point arrays where the format
    supports it (.vtk, .vtp, .ply).
    """
    path = Path(path)
    suffix = _suffix(path)
    if suffix not in MESH_SUFFIXES:
        raise DataFileError(path, f"unsupported mesh format '{suffix}'")
    mesh.check(path)
    if suffix == ".gii":
        import nibabel as nib

        img = nib.gifti.GiftiImage(darrays=[
            nib.gifti.GiftiDataArray(mesh.vertices.astype(np.float32), intent="NIFTI_INTENT_POINTSET"),
            nib.gifti.GiftiDataArray(mesh.faces.astype(np.int32), intent="NIFTI_INTENT_TRIANGLE"),
        ])
        with atomic_path(path) as tmp:
            nib.save(img, str(tmp))
        return
    poly = mesh.to_polydata()
    for name, values in (point_data or {}).items():
        poly.point_data[name] = np.asarray(values)
    with atomic_path(path) as tmp:
        poly.save(str(tmp), binary=suffix != ".obj") if suffix != ".obj" else poly.save(str(tmp))


# --------------------------------------------------------------------------------------
# Point sets
# --------------------------------------------------------------------------------------


@dataclass
class PointSet:
    """Points in world RAS mm with optional unit normals.

    Attributes
    ----------
    points : (P, 3) float ndarray
    normals : (P, 3) float ndarray or None
    """

    points: np.ndarray
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=np.float64).reshape(-1, 3)
            if self.normals.shape != self.points.shape:
                raise ValueError("normals must have the same shape as points")

    def __len__(self) -> int:
        return int(self.points.shape[0])


def load_points(path: str | os.PathLike) -> PointSet:
    """Read a point set from CSV (``x,y,z[,nx,ny,nz]`` with header) or Slicer .mrk.json.

    Raises
    ------
    DataFileError
        Not found, unknown format, bad header, non-numeric or NaN values, no points.
    """
    path = _require_file(path)
    suffix = _suffix(path)
    if suffix == ".csv":
        pts = _load_points_csv(path)
    elif suffix in (".mrk.json", ".json"):
        pts = _load_points_markups(path)
    else:
        raise DataFileError(path, f"unsupported point-set format '{suffix}' (use .csv or .mrk.json)")
    if len(pts) == 0:
        raise DataFileError(path, "no points in file")
    if not np.all(np.isfinite(pts.points)):
        raise DataFileError(path, "points contain NaN or infinite coordinates")
    if pts.normals is not None and not np.all(np.isfinite(pts.normals)):
        raise DataFileError(path, "normals contain NaN or infinite values")
    return pts


def _load_points_csv(path: Path) -> PointSet:
    with open(path, newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.reader(fh) if r and any(c.strip() for c in r)]
    if not rows:
        raise DataFileError(path, "no header line")
    header = [c.strip().lower() for c in rows[0]]
    if header[:3] != ["x", "y", "z"]:
        raise DataFileError(path, f"header must start with x,y,z (got {','.join(rows[0])})")
    has_normals = header[3:6] == ["nx", "ny", "nz"]
    ncol = 6 if has_normals else 3
    try:
        values = np.array([[float(c) for c in r[:ncol]] for r in rows[1:]], dtype=np.float64)
    except ValueError as exc:
        raise DataFileError(path, f"non-numeric value ({exc})") from None
    if any(len(r) < ncol for r in rows[1:]):
        raise DataFileError(path, f"every row needs {ncol} values")
    values = values.reshape(-1, ncol)
    return PointSet(values[:, :3], values[:, 3:6] if has_normals else None)


_LPS_FLIP = np.array([-1.0, -1.0, 1.0])


def _load_points_markups(path: Path) -> PointSet:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFileError(path, f"not valid JSON ({exc})") from None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not markups:
        raise DataFileError(path, "not a Slicer markups file (no 'markups' list)")
    points, normals = [], []
    for markup in markups:
        system = str(markup.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise DataFileError(path, f"unknown coordinateSystem '{system}'")
        flip = _LPS_FLIP if system == "LPS" else np.ones(3)
        for cp in markup.get("controlPoints", []):
            pos = cp.get("position")
            if pos is None or len(pos) != 3:
                raise DataFileError(path, f"control point {cp.get('label', '?')} has no 3D position")
            try:
                points.append(np.asarray(pos, dtype=np.float64) * flip)
            except (TypeError, ValueError):
                raise DataFileError(path, f"control point {cp.get('label', '?')} has a "
                                          "non-numeric position") from None
            orient = cp.get("orientation")
            if orient is not None and len(orient) == 9:
                # Slicer's orientation is a row-major 3x3 of axis vectors; the 3rd column is the
                # point's normal direction (that is how save_points writes it).
                normals.append(np.asarray(orient, dtype=np.float64).reshape(3, 3)[:, 2] * flip)
            else:
                normals.append(None)
    has_normals = bool(points) and all(n is not None for n in normals) and \
        doc.get("ssmStudioNormals", False) is not False
    return PointSet(np.array(points).reshape(-1, 3),
                    np.array(normals) if has_normals else None)


def save_points(path: str | os.PathLike, points: PointSet | np.ndarray,
                normals: np.ndarray | None = None) -> None:
    """Write points (world RAS mm) as CSV or Slicer markups JSON (LPS, as Slicer writes)."""
    path = Path(path)
    pts = points if isinstance(points, PointSet) else PointSet(points, normals)
    suffix = _suffix(path)
    if suffix == ".csv":
        lines = ["x,y,z,nx,ny,nz" if pts.normals is not None else "x,y,z"]
        data = pts.points if pts.normals is None else np.hstack([pts.points, pts.normals])
        lines += [",".join(f"{v:.6f}" for v in row) for row in data]
        atomic_write_text(path, "\n".join(lines) + "\n")
    elif suffix in (".mrk.json", ".json"):
        cps = []
        for i, p in enumerate(pts.points):
            cp = {"id": str(i + 1), "label": f"P-{i + 1}",
                  "position": (p * _LPS_FLIP).tolist(), "selected": True, "locked": False,
                  "visibility": True, "positionStatus": "defined"}
            if pts.normals is not None:
                n = pts.normals[i] * _LPS_FLIP
                cp["orientation"] = _frame_with_z(n).ravel().tolist()
            cps.append(cp)
        doc = {
            "@schema": "https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/"
                       "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
            "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                         "controlPoints": cps}],
        }
        if pts.normals is not None:
            doc["ssmStudioNormals"] = "orientation column 3 holds each point's surface normal"
        atomic_write_json(path, doc)
    else:
        raise DataFileError(path, f"unsupported point-set format '{suffix}' (use .csv or .mrk.json)")


def _frame_with_z(n: np.ndarray) -> np.ndarray:
    """A rotation matrix (3, 3) whose third column is the unit vector along ``n``."""
    z = n / (np.linalg.norm(n) or 1.0)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


# --------------------------------------------------------------------------------------
# Shape models
# --------------------------------------------------------------------------------------


def save_model(path: str | os.PathLike, model: ShapeModel) -> None:
    """Write a shape model as ``.npz`` (format ``ssm-studio-model``, version 1).

    File layout (all arrays float64 unless stated):

    ============== ============ =====================================================
    key            shape        meaning
    ============== ============ =====================================================
    header         () str       JSON: format, format_version, units ("mm"), method,
                                params, source_meshes, n_vertices, n_factors, info
                                (free-form metadata: timings, evaluation, ...)
    mean           (N, 3)       mean shape, model frame, mm
    factors        (M, N, 3)    deformation factors
    coef_var       (M,)         prior variance of each coefficient
    faces          (F, 3) int64 triangles
    world_transform (4, 4)      model frame -> world RAS mm
    ============== ============ =====================================================
    """
    path = Path(path)
    header = {
        "format": MODEL_FORMAT,
        "format_version": MODEL_FORMAT_VERSION,
        "units": "mm",
        "method": model.method,
        "params": model.params,
        "source_meshes": list(model.source_meshes),
        "n_vertices": model.n_vertices,
        "n_factors": model.n_factors,
        "info": model.info,
    }
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                header=np.array(json.dumps(header, default=_json_default)),
                mean=model.mean, factors=model.factors, coef_var=model.coef_var,
                faces=model.faces, world_transform=model.world_transform,
            )


def load_model(path: str | os.PathLike) -> ShapeModel:
    """Read a model written by :func:`save_model`, checking format, version and shapes.

    Raises
    ------
    DataFileError
        Not found, not an npz, missing header or arrays, unknown format or version,
        inconsistent shapes, non-finite values.
    """
    path = _require_file(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except Exception as exc:
        raise DataFileError(path, f"not a shape model file (could not read as .npz: "
                                  f"{type(exc).__name__})") from None
    if "header" not in arrays:
        raise DataFileError(path, "not a shape model file (no header)")
    try:
        header = json.loads(str(arrays["header"]))
    except json.JSONDecodeError:
        raise DataFileError(path, "model header is not valid JSON") from None
    if header.get("format") != MODEL_FORMAT:
        raise DataFileError(path, f"not an SSM Studio model (format '{header.get('format')}')")
    version = header.get("format_version")
    if version != MODEL_FORMAT_VERSION:
        raise DataFileError(path, f"model format version {version} is not supported "
                                  f"(this SSM Studio reads version {MODEL_FORMAT_VERSION})")
    missing = [k for k in ("mean", "factors", "coef_var", "faces", "world_transform")
               if k not in arrays]
    if missing:
        raise DataFileError(path, f"model file lacks arrays: {', '.join(missing)}")
    try:
        model = ShapeModel(
            mean=arrays["mean"], factors=arrays["factors"], coef_var=arrays["coef_var"],
            faces=arrays["faces"], world_transform=arrays["world_transform"],
            method=str(header.get("method", "unknown")), params=dict(header.get("params", {})),
            source_meshes=list(header.get("source_meshes", [])),
            info=dict(header.get("info", {})),
        )
    except ValueError as exc:
        raise DataFileError(path, f"inconsistent model: {exc}") from None
    return model
