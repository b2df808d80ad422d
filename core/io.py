"""Every file SSM Studio reads or writes: volumes, meshes, point sets and shape models.

One place for I/O so that coordinates and errors are handled the same way everywhere:

- volumes: NIfTI-1/2 (.nii, .nii.gz) through nibabel, kept with nibabel's best voxel->world
  affine (sform if set, else qform; RAS, mm), oblique affines included;
- meshes: .vtk .vtp .stl through VTK readers (their error output captured, never printed),
  .ply and .obj through numpy readers of our own, GIfTI surfaces (.gii) through nibabel;
  always triangulated on load, as :class:`TriMesh` (vertices/faces numpy arrays), written
  through pyvista;
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
import threading
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


def _why(exc: BaseException, path: Path | None = None) -> str:
    """A library's error text on one line, without the file name (the caller adds it)."""
    text = str(exc)
    if path is not None:
        text = text.replace(str(path), "the file")
    text = " ".join(text.split())
    return text[:300] if text else type(exc).__name__


def _require_file(path: str | os.PathLike) -> Path:
    path = Path(path)
    if not path.exists():
        raise DataFileError(path, "file not found")
    if path.is_dir():
        raise DataFileError(path, "is a folder, not a file")
    if path.stat().st_size == 0:
        raise DataFileError(path, "file is empty (0 bytes)")
    if not os.access(path, os.R_OK):
        raise DataFileError(path, "permission denied (the file is not readable)")
    return path


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, allow_empty: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary name keeps the target's suffix so that writers choosing a format by
    extension (VTK, nibabel) pick the right one. If the block raises (or, unless
    ``allow_empty``, leaves the temporary file empty, as a failing VTK writer does), the
    previous file at ``path`` is left untouched and the temporary file is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{_suffix(path)}",
                               dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if not tmp_path.exists() or (tmp_path.stat().st_size == 0 and not allow_empty):
            raise DataFileError(path, "nothing was written (the writer produced no data)")
        # mkstemp creates the file private (0600); give the result the permissions a plain
        # open() would (or keep those of the file being replaced).
        mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_UMASK
        os.chmod(tmp_path, mode)
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path, allow_empty=True) as tmp:
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


_NIFTI1_HEADER_SIZE = 348
_NIFTI2_HEADER_SIZE = 540


def _read_head(path: Path, n_bytes: int) -> bytes:
    """The first ``n_bytes`` of a file, decompressed when its name ends in .gz."""
    if path.name.lower().endswith(".gz"):
        try:
            with gzip.open(path, "rb") as fh:
                return fh.read(n_bytes)
        except gzip.BadGzipFile:
            raise DataFileError(path, "not gzip-compressed data although the name ends in "
                                      ".gz") from None
        except (EOFError, zlib.error) as exc:
            raise DataFileError(path, f"truncated or corrupt gzip data ({exc})") from None
    with open(path, "rb") as fh:
        return fh.read(n_bytes)


def _nifti_class(path: Path):
    """Which nibabel class reads ``path``: checks the header size field and the magic string.

    Deciding this ourselves (instead of ``nibabel.load`` guessing) gives precise errors for
    truncated, non-NIfTI, .hdr/.img pair and CIFTI files.
    """
    import nibabel as nib

    head = _read_head(path, _NIFTI2_HEADER_SIZE)
    if len(head) < 4:
        raise DataFileError(path, f"truncated NIfTI header ({len(head)} bytes)")
    sizes = {int(np.frombuffer(head[:4], dtype=order + "i4")[0]) for order in "<>"}
    if _NIFTI1_HEADER_SIZE in sizes:
        if len(head) < _NIFTI1_HEADER_SIZE:
            raise DataFileError(path, f"truncated NIfTI header ({len(head)} of "
                                      f"{_NIFTI1_HEADER_SIZE} bytes)")
        magic = head[344:348]
        if magic == b"ni1\x00":
            raise DataFileError(path, "header of a NIfTI .hdr/.img pair, not a single-file .nii")
        if magic != b"n+1\x00":
            raise DataFileError(path, "not a NIfTI file (an Analyze-style header without the "
                                      "NIfTI magic string)")
        return nib.Nifti1Image
    if _NIFTI2_HEADER_SIZE in sizes:
        if len(head) < _NIFTI2_HEADER_SIZE:
            raise DataFileError(path, f"truncated NIfTI header ({len(head)} of "
                                      f"{_NIFTI2_HEADER_SIZE} bytes)")
        if head[4:8] == b"ni2\x00":
            raise DataFileError(path, "header of a NIfTI .hdr/.img pair, not a single-file .nii")
        if head[4:8] != b"n+2\x00":
            raise DataFileError(path, "not a NIfTI file (NIfTI-2 header size but no magic string)")
        return nib.Nifti2Image
    size = int(np.frombuffer(head[:4], dtype="<i4")[0])
    raise DataFileError(path, f"not a NIfTI file (header size field is {size}, expected "
                              f"{_NIFTI1_HEADER_SIZE} for NIfTI-1 or {_NIFTI2_HEADER_SIZE} for "
                              "NIfTI-2)")


def load_volume(path: str | os.PathLike) -> Volume:
    """Read a 3D NIfTI-1 or NIfTI-2 image (.nii or .nii.gz).

    The affine is nibabel's best affine (sform when its code is set, else qform, else the
    voxel-size-only fallback), so oblique acquisitions keep their orientation. Trailing
    singleton dimensions (a 4D image with one volume) are dropped; any other 2D, 4D or
    higher-dimensional image is refused. Intensity scaling (scl_slope/scl_inter) is applied;
    the array is returned in native byte order; NaN/inf voxels are replaced by 0.

    Raises
    ------
    DataFileError
        Not found, empty, truncated or corrupt gzip, not a NIfTI file, .hdr/.img pair, CIFTI,
        wrong dimensionality, unsupported voxel type, non-finite or singular affine.
    """

    path = _require_file(path)
    if _suffix(path) not in VOLUME_SUFFIXES:
        raise DataFileError(path, f"not a NIfTI file name (expected .nii or .nii.gz, got "
                                  f"'{_suffix(path) or path.name}')")
    image_class = _nifti_class(path)
    try:
        img = image_class.from_filename(str(path))
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip data ({_why(exc, path)})") from None
    except Exception as exc:  # nibabel raises many types for bad headers
        raise DataFileError(path, f"invalid NIfTI header ({type(exc).__name__}: "
                                  f"{_why(exc, path)})") from None
    intent_code = int(img.header["intent_code"])
    if 3000 <= intent_code < 3100:  # NIFTI_INTENT_CONNECTIVITY_* codes, used by CIFTI-2
        raise DataFileError(path, f"a CIFTI file (intent {img.header.get_intent()[0]}), "
                                  "not a volume")
    full_shape = tuple(int(s) for s in img.shape)
    shape = full_shape
    while len(shape) > 3 and shape[-1] == 1:
        shape = shape[:-1]
    if len(shape) != 3:
        extra = f", {full_shape[3]} volumes" if len(full_shape) == 4 else ""
        raise DataFileError(path, f"a 3D image is needed, this one is {len(full_shape)}D with "
                                  f"shape {full_shape}{extra}")
    if min(shape) < 1:
        raise DataFileError(path, f"image has an empty dimension, shape {full_shape}")
    affine = np.asarray(img.affine, dtype=np.float64)
    if not np.all(np.isfinite(affine)):
        raise DataFileError(path, "the voxel-to-world affine (sform/qform) has NaN or infinite "
                                  "entries")
    if abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise DataFileError(path, "the voxel-to-world affine (sform/qform) is singular "
                                  "(zero voxel size?)")
    dtype = img.get_data_dtype()
    if dtype.kind not in "iufb":
        raise DataFileError(path, f"unsupported voxel type {dtype} (RGB or complex images "
                                  "cannot be segmented)")
    proxy = img.dataobj
    scaled = getattr(proxy, "slope", 1.0) != 1.0 or getattr(proxy, "inter", 0.0) != 0.0
    try:
        # scl_slope / scl_inter applied when set (as float32: half of nibabel's float64)
        data = img.get_fdata(dtype=np.float32) if scaled else np.asanyarray(proxy)
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip data ({_why(exc, path)})") from None
    except (OSError, ValueError) as exc:
        raise DataFileError(path, f"image data are truncated or corrupt ({_why(exc, path)})") \
            from None
    data = data.reshape(shape)
    if data.dtype.kind == "b":
        data = data.astype(np.uint8)
    if not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="))
    if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
        data = np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0)
    return Volume(data=data, affine=affine, path=path)


def save_volume(path: str | os.PathLike, data: np.ndarray, affine: np.ndarray) -> None:
    """Write a 3D array as NIfTI-1 with ``affine`` as sform and qform (code 1, scanner).

    The sform keeps the affine exactly (to float32 precision); the qform holds its nearest
    rotation (a qform cannot store shear). Booleans are written as uint8, 64-bit integers as
    int32 when their range allows it (many tools cannot read 64-bit NIfTI), else float64.
    """
    import nibabel as nib

    path = Path(path)
    if _suffix(path) not in VOLUME_SUFFIXES:
        raise DataFileError(path, "volumes are written as .nii or .nii.gz")
    data = np.asarray(data)
    if data.ndim != 3:
        raise DataFileError(path, f"a 3D array is needed, got shape {data.shape}")
    affine = np.asarray(affine, dtype=np.float64)
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)) or \
            abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise DataFileError(path, "the affine must be a finite, invertible 4x4 matrix")
    if data.dtype == bool:
        data = data.astype(np.uint8)
    elif data.dtype.kind in "iu" and data.dtype.itemsize == 8:
        info = np.iinfo(np.int32)
        fits = data.size == 0 or (data.min() >= info.min and data.max() <= info.max)
        data = data.astype(np.int32 if fits else np.float64)
    img = nib.Nifti1Image(data, affine)
    img.set_sform(affine, code=1)
    img.set_qform(affine, code=1)
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
    """Triangles (F, 3) of a vtkPolyData: polygons and triangle strips, triangulated by VTK.

    Vertex and line cells are ignored; polygons with more than 3 corners and strips go through
    ``vtkTriangleFilter``. Point ids are unchanged.
    """
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    if poly.GetNumberOfPolys() == 0 and poly.GetNumberOfStrips() == 0:
        return np.zeros((0, 3), np.int64)

    def polygons(p) -> tuple[np.ndarray, np.ndarray]:
        cells = p.GetPolys()
        offsets = vtk_to_numpy(cells.GetOffsetsArray()).astype(np.int64)
        connectivity = vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64)
        return offsets, connectivity

    offsets, connectivity = polygons(poly)
    if poly.GetNumberOfStrips() > 0 or np.any(np.diff(offsets) != 3):
        triangulate = vtk.vtkTriangleFilter()
        triangulate.PassVertsOff()
        triangulate.PassLinesOff()
        triangulate.SetInputData(poly)
        triangulate.Update()
        offsets, connectivity = polygons(triangulate.GetOutput())
    sizes = np.diff(offsets)
    starts = offsets[:-1][sizes == 3]
    return connectivity[starts[:, None] + np.arange(3)]


_VTK_LOCK = threading.Lock()


def _vtk_error_text(raw: object) -> list[str]:
    """Error messages in the text collected by a vtkStringOutputWindow.

    ERROR entries, and warnings that report an error: the legacy .vtk reader only warns
    "Error reading binary data!" when a binary file is cut short, then returns garbage.
    """
    text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw or "")
    messages = []
    for block in text.split("\n\n"):
        lines = [ln.strip() for ln in block.strip().splitlines() if ln.strip()]
        if len(lines) < 2:
            continue
        message = " ".join(lines[1:])
        if not (lines[0].startswith("ERROR") or "error" in message.lower()):
            continue
        if "): " in message and message.startswith("vtk"):
            message = message.split("): ", 1)[1]  # drop "vtkSTLReader (0x55...): "
        garbage = next((i for i, c in enumerate(message) if not c.isprintable()), None)
        if garbage is not None:  # e.g. "Unrecognized file type: <binary bytes>"
            message = message[:garbage].rstrip() + "..."
        messages.append(message)
    return messages


@contextlib.contextmanager
def _vtk_errors() -> Iterator[list[str]]:
    """Collect VTK's error messages in a list instead of letting VTK print them on stderr.

    VTK readers do not raise: they print errors (through the output window and the
    vtkLogger stderr sink) and return partial data. The list is filled when the block exits.
    """
    import vtk

    errors: list[str] = []
    with _VTK_LOCK:
        window = vtk.vtkStringOutputWindow()
        previous = vtk.vtkOutputWindow.GetInstance()
        verbosity = vtk.vtkLogger.GetCurrentVerbosityCutoff()
        vtk.vtkOutputWindow.SetInstance(window)
        vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
        try:
            yield errors
        finally:
            vtk.vtkLogger.SetStderrVerbosity(verbosity)
            vtk.vtkOutputWindow.SetInstance(previous)
            errors.extend(_vtk_error_text(window.GetOutput()))


def expand_mesh_paths(paths: list[str | os.PathLike]) -> list[Path]:
    """Files and folders -> the mesh files among them, in order, without repeats.

    A folder stands for the files in it whose names end in one of :data:`MESH_SUFFIXES`
    (sorted by name); a folder with none contributes nothing.
    """
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(f for f in p.iterdir()
                            if f.is_file() and any(f.name.lower().endswith(s) for s in MESH_SUFFIXES))
        else:
            files.append(p)
    seen: set[Path] = set()
    return [f for f in files if not (f in seen or seen.add(f))]


def load_meshes(paths: list[str | os.PathLike], progress=None
                ) -> tuple[list[tuple[Path, TriMesh]], dict[str, str]]:
    """Read several mesh files, going on past unreadable ones (a batch is not lost to one file).

    Returns the (path, mesh) pairs read, in input order, and the problem of each file that
    could not be read (path -> message). ``progress(fraction, message)`` as in core.progress.
    """
    loaded: list[tuple[Path, TriMesh]] = []
    failures: dict[str, str] = {}
    for i, path in enumerate(map(Path, paths)):
        if progress is not None:
            progress(i / max(len(paths), 1), f"reading {path.name}")
        try:
            loaded.append((path, load_mesh(path)))
        except DataFileError as exc:
            failures[str(path)] = exc.problem
        except (ValueError, OSError) as exc:  # should not happen: load_mesh wraps its errors
            failures[str(path)] = f"{type(exc).__name__}: {exc}"
    if progress is not None:
        progress(1.0, f"{len(loaded)} meshes read")
    return loaded, failures


def load_mesh(path: str | os.PathLike) -> TriMesh:
    """Read a surface mesh and triangulate it.

    Formats: .vtk (legacy polydata or unstructured grid, whose outer surface is taken),
    .vtp and .stl through VTK readers; .ply and .obj through numpy readers of our own (VTK's
    PLY reader crashes on truncated files, its OBJ reader renumbers vertices); GIfTI (.gii,
    pointset + triangle arrays) through nibabel. Polygons and triangle strips are triangulated; vertex
    and line cells are ignored. Unused points are kept, so vertex indices stay those of the
    file (STL has no shared vertices: VTK merges coincident corners).

    Raises
    ------
    DataFileError
        Not found, empty, unreadable or truncated (any error VTK reports while reading),
        no triangles, NaN vertices, faces out of range.
    """
    path = _require_file(path)
    suffix = _suffix(path)
    if suffix not in MESH_SUFFIXES:
        raise DataFileError(path, f"unsupported mesh format '{suffix or path.name}' (use one of "
                                  f"{', '.join(MESH_SUFFIXES)})")
    if suffix == ".gii":
        mesh = _load_gifti(path)
    elif suffix == ".ply":
        mesh = _load_ply(path)
    elif suffix == ".obj":
        mesh = _load_obj(path)
    else:
        mesh = _load_vtk_family(path)
    return mesh.check(path)


def _load_vtk_family(path: Path) -> TriMesh:
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    suffix = _suffix(path)
    if suffix == ".stl":
        _check_stl_length(path)
    reader = {".vtk": vtk.vtkDataSetReader, ".vtp": vtk.vtkXMLPolyDataReader,
              ".stl": vtk.vtkSTLReader}[suffix]()
    reader.SetFileName(str(path))
    with _vtk_errors() as errors:
        reader.Update()
        data = reader.GetOutputDataObject(0)
    if errors:
        detail = errors[0].replace(str(path), "the file")[:200]
        raise DataFileError(path, f"unreadable, truncated or corrupt {suffix} file "
                                  f"(VTK: {detail})")
    if data is None or not isinstance(data, vtk.vtkDataSet) or data.GetNumberOfPoints() == 0:
        raise DataFileError(path, f"empty mesh (no points; is this really a {suffix} file?)")
    n_points = data.GetNumberOfPoints()
    point_data = data.GetPointData()
    for i in range(point_data.GetNumberOfArrays()):
        array = point_data.GetAbstractArray(i)
        if array is not None and array.GetNumberOfTuples() != n_points:
            raise DataFileError(path, f"truncated or corrupt {suffix} file (point array "
                                      f"'{array.GetName()}' has {array.GetNumberOfTuples()} "
                                      f"values for {n_points} points)")
    if isinstance(data, vtk.vtkUnstructuredGrid):
        surface = vtk.vtkDataSetSurfaceFilter()  # outer faces of volume cells, 2D cells as is
        surface.SetInputData(data)
        surface.Update()
        data = surface.GetOutput()
    if not isinstance(data, vtk.vtkPolyData):
        kind = data.GetClassName().removeprefix("vtk")
        raise DataFileError(path, f"holds {kind} data, not a surface mesh")
    points = vtk_to_numpy(data.GetPoints().GetData()).astype(np.float64)
    bad = ~np.all(np.isfinite(points), axis=1)
    if bad.any():
        raise DataFileError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates")
    faces = _triangles_of(data)
    if len(faces) == 0:
        raise DataFileError(path, "mesh has no triangles and no polygons that can be "
                                  "triangulated (points or lines only)")
    return TriMesh(points, faces, path.name)


def _check_stl_length(path: Path) -> None:
    """Refuse cut-short STL files, which VTK's reader may read in part without complaint."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(84)
        if head[:5].lower() == b"solid":  # ASCII (a binary header may also start so)
            fh.seek(max(0, size - 512))
            tail = fh.read().rstrip().lower()
            last_line = tail.splitlines()[-1].strip() if tail else b""
            if last_line.startswith(b"endsolid") or b"endsolid" in tail[-300:]:
                return
            if size >= 84 and size == 84 + 50 * int(np.frombuffer(head[80:84], "<u4")[0]):
                return  # binary STL whose header text starts with "solid"
            raise DataFileError(path, "truncated ASCII STL file (no closing 'endsolid' line)")
    if len(head) < 84:
        raise DataFileError(path, f"truncated or corrupt .stl file ({size} bytes, shorter than "
                                  "a binary STL header)")
    n_triangles = int(np.frombuffer(head[80:84], "<u4")[0])
    if size < 84 + 50 * n_triangles:
        raise DataFileError(path, f"truncated or corrupt .stl file (header announces "
                                  f"{n_triangles} triangles, the file holds "
                                  f"{(size - 84) // 50})")


def _load_obj(path: Path) -> TriMesh:
    """Read the geometry of a Wavefront OBJ file: 'v' and 'f' records, in file order.

    A reader of our own because VTK's splits vertices whose faces use separate normal or
    texture indices (``f 1//1 2//1 3//1``), which changes the vertex numbering. Texture
    coordinates, normals, groups and materials are ignored; polygons are fan-triangulated;
    negative (relative) indices are resolved as the OBJ specification says.
    """
    try:
        lines = path.read_text(encoding="utf-8", errors="strict").splitlines()
    except UnicodeDecodeError:
        raise DataFileError(path, "not a text OBJ file (not UTF-8 text)") from None
    vertex_rows: list[list[str]] = []
    polygons: list[np.ndarray] = []
    for number, line in enumerate(lines, start=1):
        if line.startswith("v "):
            coords = line.split()[1:4]
            if len(coords) < 3:
                raise DataFileError(path, f"line {number}: a vertex needs 3 coordinates")
            vertex_rows.append(coords)
        elif line.startswith("f "):
            try:
                ids = np.array([int(tok.split("/")[0]) for tok in line.split()[1:]], np.int64)
            except ValueError:
                raise DataFileError(path, f"line {number}: bad face record "
                                          f"'{line.strip()[:60]}'") from None
            if np.any(ids == 0):
                raise DataFileError(path, f"line {number}: face index 0 (OBJ counts from 1)")
            polygons.append(np.where(ids > 0, ids - 1, len(vertex_rows) + ids))
    if not vertex_rows:
        raise DataFileError(path, "empty mesh (no 'v' records; is this really a .obj file?)")
    try:
        vertices = np.array(vertex_rows, dtype=np.float64)
    except ValueError:
        raise DataFileError(path, "non-numeric vertex coordinates") from None
    return TriMesh(vertices, _polygons_to_triangles(polygons), path.name)


# PLY scalar type names (both spellings of the PLY spec) -> numpy type codes.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
              "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
              "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]]  # (name, value type, list count type or None)


def _parse_ply_header(path: Path, raw: bytes) -> tuple[str, list[_PlyElement], int]:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        what = "no 'end_header' line" if raw.startswith(b"ply") else "does not start with 'ply'"
        raise DataFileError(path, f"not a PLY file or truncated header ({what})")
    body_start = raw.find(b"\n", end) + 1
    if body_start == 0:
        body_start = len(raw)
    try:
        lines = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise DataFileError(path, "PLY header is not ASCII text") from None
    fmt, elements = "", []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append(_PlyElement(words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1].properties.append((words[4], _PLY_TYPES[words[3]],
                                                _PLY_TYPES[words[2]]))
            elif words[0] == "property":
                elements[-1].properties.append((words[2], _PLY_TYPES[words[1]], None))
            else:
                raise ValueError(words[0])
        except (IndexError, KeyError, ValueError):
            raise DataFileError(path, f"bad PLY header line {number}: '{line[:80]}'") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataFileError(path, f"unknown PLY format '{fmt}'")
    if any(e.count < 0 for e in elements):
        raise DataFileError(path, "negative element count in PLY header")
    return fmt, elements, body_start


def _ply_binary_element(path: Path, body: memoryview, pos: int, element: _PlyElement,
                        order: str) -> tuple[dict[str, np.ndarray | list], int]:
    """Read one element's records from binary PLY data starting at byte ``pos``."""
    props = element.properties
    n = element.count
    truncated = DataFileError(path, f"truncated PLY file (element '{element.name}' needs more "
                                    "data than the file holds)")
    if all(count_type is None for _, _, count_type in props):
        dtype = np.dtype([(name, order + t) for name, t, _ in props])
        if pos + n * dtype.itemsize > len(body):
            raise truncated
        rec = np.frombuffer(body, dtype=dtype, count=n, offset=pos)
        return {name: rec[name] for name, _, _ in props}, pos + n * dtype.itemsize
    # Lists: first try "every list has the length of the first one" (all triangles),
    # checked afterwards; otherwise walk the records one by one.
    if n == 0:
        return {name: np.zeros((0, 3)) for name, _, _ in props}, pos
    fields, probe = [], pos
    for name, value_type, count_type in props:
        if count_type is None:
            fields.append((name, order + value_type))
            probe += np.dtype(value_type).itemsize
            continue
        if probe + np.dtype(count_type).itemsize > len(body):
            raise truncated
        length = int(np.frombuffer(body, dtype=order + count_type, count=1, offset=probe)[0])
        fields.append((name + "#n", order + count_type))
        fields.append((name, order + value_type, (length,)))
        probe += np.dtype(count_type).itemsize + length * np.dtype(value_type).itemsize
    dtype = np.dtype(fields)
    if pos + n * dtype.itemsize <= len(body):
        rec = np.frombuffer(body, dtype=dtype, count=n, offset=pos)
        uniform = all(np.all(rec[name + "#n"] == rec.dtype[name].shape[0])
                      for name, _, count_type in props if count_type is not None)
        if uniform:
            return {name: rec[name] for name, _, _ in props}, pos + n * dtype.itemsize
    out: dict[str, list] = {name: [] for name, _, _ in props}
    for _ in range(n):
        for name, value_type, count_type in props:
            if count_type is not None:
                size = np.dtype(count_type).itemsize
                if pos + size > len(body):
                    raise truncated
                length = int(np.frombuffer(body, dtype=order + count_type, count=1, offset=pos)[0])
                pos += size
            else:
                length = 1
            size = np.dtype(value_type).itemsize * length
            if pos + size > len(body):
                raise truncated
            values = np.frombuffer(body, dtype=order + value_type, count=length, offset=pos)
            out[name].append(values if count_type is not None else values[0])
            pos += size
    return out, pos


def _ply_ascii_element(path: Path, lines: list[bytes], start: int,
                       element: _PlyElement) -> tuple[dict[str, np.ndarray | list], int]:
    n = element.count
    rows = lines[start:start + n]
    if len(rows) < n:
        raise DataFileError(path, f"truncated PLY file (element '{element.name}' has "
                                  f"{len(rows)} of {n} lines)")
    try:
        tokens = [row.split() for row in rows]
        lengths = {len(t) for t in tokens}
        if len(lengths) <= 1:
            table = np.array(tokens, dtype=np.float64).reshape(n, -1)
            out, col = {}, 0
            for name, _, count_type in element.properties:
                if count_type is None:
                    out[name] = table[:, col]
                    col += 1
                else:
                    length = int(table[0, col]) if n else 0
                    out[name] = table[:, col + 1:col + 1 + length]
                    col += 1 + length
            if col == table.shape[1]:
                return out, start + n
        out = {name: [] for name, _, _ in element.properties}
        for row in tokens:
            values = [float(v) for v in row]
            col = 0
            for name, _, count_type in element.properties:
                if count_type is None:
                    out[name].append(values[col])
                    col += 1
                else:
                    length = int(values[col])
                    out[name].append(np.array(values[col + 1:col + 1 + length]))
                    col += 1 + length
            if col > len(values):
                raise ValueError("row too short")
    except (ValueError, IndexError):
        raise DataFileError(path, f"PLY element '{element.name}' has non-numeric or missing "
                                  "values") from None
    return out, start + n


def _polygons_to_triangles(polygons: np.ndarray | list) -> np.ndarray:
    """Fan-triangulate polygons, given as an (F, k) array or a list of index arrays."""
    if isinstance(polygons, np.ndarray) and polygons.ndim == 2:
        groups = [polygons]
    else:
        by_size: dict[int, list] = {}
        for poly in polygons:
            by_size.setdefault(len(poly), []).append(poly)
        groups = [np.array(g) for g in by_size.values()]
    tris = []
    for group in groups:
        if group.ndim != 2 or group.shape[1] < 3:
            continue
        for j in range(1, group.shape[1] - 1):  # fan: (0, j, j+1)
            tris.append(group[:, [0, j, j + 1]])
    if not tris:
        return np.zeros((0, 3), np.int64)
    return np.concatenate(tris).astype(np.int64)


def _load_ply(path: Path) -> TriMesh:
    """Read a PLY surface (ascii or binary): 'vertex' x, y, z and 'face' vertex_indices."""
    raw = path.read_bytes()
    fmt, elements, body_start = _parse_ply_header(path, raw)
    data: dict[str, dict] = {}
    if fmt == "ascii":
        lines = [ln for ln in raw[body_start:].splitlines() if ln.strip()]
        line = 0
        for element in elements:
            data[element.name], line = _ply_ascii_element(path, lines, line, element)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        body, pos = memoryview(raw)[body_start:], 0
        for element in elements:
            data[element.name], pos = _ply_binary_element(path, body, pos, element, order)
    vertex = data.get("vertex")
    if vertex is None or not all(k in vertex for k in "xyz"):
        raise DataFileError(path, "PLY file has no 'vertex' element with x, y, z")
    vertices = np.column_stack([np.asarray(vertex[k], dtype=np.float64) for k in "xyz"])
    if len(vertices) == 0:
        raise DataFileError(path, "empty mesh (no vertices)")
    face = data.get("face", {})
    key = next((k for k in ("vertex_indices", "vertex_index") if k in face), None)
    if key is None:
        raise DataFileError(path, "mesh has no triangles (no 'face' element: points only)")
    faces = _polygons_to_triangles(face[key])
    return TriMesh(vertices, faces, path.name)


def _load_gifti(path: Path) -> TriMesh:
    import nibabel as nib

    try:
        img = nib.load(str(path))
    except Exception as exc:
        raise DataFileError(path, f"not a readable GIfTI file ({type(exc).__name__}: "
                                  f"{_why(exc, path)})") from None
    if not isinstance(img, nib.gifti.GiftiImage):
        raise DataFileError(path, "not a GIfTI image")
    points = img.get_arrays_from_intent("NIFTI_INTENT_POINTSET")
    tris = img.get_arrays_from_intent("NIFTI_INTENT_TRIANGLE")
    if not points:
        raise DataFileError(path, "GIfTI file has no surface (no POINTSET array: labels, shape "
                                  "or time-series data only?)")
    if not tris:
        raise DataFileError(path, "mesh has no triangles (GIfTI file has a POINTSET but no "
                                  "TRIANGLE array)")
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
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: Excel's BOM
            rows = [(n, r) for n, r in enumerate(csv.reader(fh), start=1)
                    if r and any(c.strip() for c in r)]
    except UnicodeDecodeError:
        raise DataFileError(path, "not a text CSV file (not UTF-8 text)") from None
    except csv.Error as exc:
        raise DataFileError(path, f"malformed CSV ({exc})") from None
    if not rows:
        raise DataFileError(path, "no header line")
    header = [c.strip().lower() for c in rows[0][1]]
    if header[:3] != ["x", "y", "z"]:
        got = ",".join(rows[0][1])[:80]
        raise DataFileError(path, f"header must start with x,y,z (got '{got}')")
    has_normals = header[3:6] == ["nx", "ny", "nz"]
    ncol = 6 if has_normals else 3
    values = np.empty((len(rows) - 1, ncol), dtype=np.float64)
    for i, (line, row) in enumerate(rows[1:]):
        if len(row) < ncol:
            raise DataFileError(path, f"line {line} has {len(row)} values, every row needs "
                                      f"{ncol} ({','.join(header[:ncol])})")
        try:
            values[i] = [float(c) for c in row[:ncol]]
        except ValueError:
            bad = next(c for c in row[:ncol] if not _is_float(c))
            raise DataFileError(path, f"non-numeric value '{bad.strip()[:40]}' on line "
                                      f"{line}") from None
    return PointSet(values[:, :3], values[:, 3:6] if has_normals else None)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


_LPS_FLIP = np.array([-1.0, -1.0, 1.0])


def _load_points_markups(path: Path) -> PointSet:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFileError(path, f"not valid JSON ({_why(exc)})") from None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not markups:
        raise DataFileError(path, "not a Slicer markups file (no 'markups' list)")
    points, normals = [], []
    for markup in markups:
        if not isinstance(markup, dict):
            raise DataFileError(path, "not a Slicer markups file (a markup is not an object)")
        system = str(markup.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise DataFileError(path, f"unknown coordinateSystem '{system}' (LPS or RAS)")
        flip = _LPS_FLIP if system == "LPS" else np.ones(3)
        control_points = markup.get("controlPoints", [])
        if not isinstance(control_points, list):
            raise DataFileError(path, "'controlPoints' is not a list")
        for number, cp in enumerate(control_points, start=1):
            if not isinstance(cp, dict):
                raise DataFileError(path, f"control point {number} is not an object")
            label = cp.get("label", number)
            if cp.get("positionStatus") in ("undefined", "missing"):
                continue  # a placeholder Slicer keeps for points not placed yet
            try:
                pos = np.asarray(cp.get("position"), dtype=np.float64)
            except (TypeError, ValueError):
                raise DataFileError(path, f"control point {label} has a non-numeric "
                                          "position") from None
            if pos.shape != (3,):
                raise DataFileError(path, f"control point {label} has no 3D position")
            points.append(pos * flip)
            orient = cp.get("orientation")
            try:
                orient = np.asarray(orient, dtype=np.float64) if orient is not None else None
            except (TypeError, ValueError):
                raise DataFileError(path, f"control point {label} has a non-numeric "
                                          "orientation") from None
            if orient is not None and orient.size == 9:
                # Slicer's orientation is a row-major 3x3 matrix whose columns are the point's
                # axes; the 3rd column is the normal direction (that is how save_points writes it).
                normals.append(orient.reshape(3, 3)[:, 2] * flip)
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
    if not np.all(np.isfinite(pts.points)) or \
            (pts.normals is not None and not np.all(np.isfinite(pts.normals))):
        raise DataFileError(path, "cannot save points or normals with NaN or infinite values")
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
    import zipfile

    path = _require_file(path)
    with open(path, "rb") as fh:
        if fh.read(4) != b"PK\x03\x04":
            raise DataFileError(path, "not a shape model file (not an .npz archive)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, EOFError, zlib.error, OSError) as exc:
        raise DataFileError(path, f"not a shape model file: truncated or corrupt .npz archive "
                                  f"({_why(exc, path)})") from None
    except ValueError as exc:  # object arrays (pickles) are refused, or a malformed array
        raise DataFileError(path, f"not a shape model file ({_why(exc, path)})") from None
    if "header" not in arrays:
        raise DataFileError(path, "not a shape model file (no header)")
    try:
        header = json.loads(str(arrays["header"]))
    except json.JSONDecodeError:
        raise DataFileError(path, "model header is not valid JSON") from None
    if not isinstance(header, dict):
        raise DataFileError(path, "model header is not a JSON object")
    if header.get("format") != MODEL_FORMAT:
        raise DataFileError(path, f"not an SSM Studio model (format '{header.get('format')}')")
    version = header.get("format_version")
    if version is None:
        raise DataFileError(path, "model header has no format_version")
    if version != MODEL_FORMAT_VERSION:
        raise DataFileError(path, f"model format version {version} is not supported "
                                  f"(this SSM Studio reads version {MODEL_FORMAT_VERSION})")
    missing = [k for k in ("mean", "factors", "coef_var", "faces", "world_transform")
               if k not in arrays]
    if missing:
        raise DataFileError(path, f"model file lacks arrays: {', '.join(missing)}")
    for key in ("params", "info"):
        if not isinstance(header.get(key, {}), dict):
            raise DataFileError(path, f"model header field '{key}' is not a JSON object")
    if not isinstance(header.get("source_meshes", []), list):
        raise DataFileError(path, "model header field 'source_meshes' is not a list")
    if header.get("units", "mm") != "mm":
        raise DataFileError(path, f"model units are '{header.get('units')}', only mm is supported")
    if arrays["faces"].dtype.kind not in "iu":
        raise DataFileError(path, f"model faces must be integers, got {arrays['faces'].dtype}")
    try:
        model = ShapeModel(
            mean=arrays["mean"], factors=arrays["factors"], coef_var=arrays["coef_var"],
            faces=arrays["faces"], world_transform=arrays["world_transform"],
            method=str(header.get("method", "unknown")), params=dict(header.get("params", {})),
            source_meshes=[str(m) for m in header.get("source_meshes", [])],
            info=dict(header.get("info", {})),
        )
    except (ValueError, TypeError) as exc:
        raise DataFileError(path, f"inconsistent model: {exc}") from None
    for key, expected in (("n_vertices", model.n_vertices), ("n_factors", model.n_factors)):
        if key in header and header[key] != expected:
            raise DataFileError(path, f"inconsistent model: header says {key}={header[key]} but "
                                      f"the arrays hold {expected}")
    return model
