"""Meshes read and written through VTK: legacy .vtk (polydata or unstructured grid), .vtp,
.vtu and .stl.

VTK readers do not raise: they print errors and return partial data, and VTK's filters
trust every point id they are given (an id past the end segfaults the process). So before
VTK reads, the sizes the header declares are checked against the file size and the memory
(a .vtp claiming 2e9 points made VTK abort with ``std::bad_alloc``); after it reads, and
before any filter runs, every cell array is validated in numpy (offsets, ids in range, cell
sizes, cell types) and compared with the counts of the legacy header. VTK's messages are
captured (never printed) and turned into a :class:`DataFileError`; cut-short STL files are
refused before VTK sees them. Unstructured grids keep the file's point numbering (their outer
surface is mapped back to the original point ids).

Coordinate system: the ``SPACE=RAS``/``SPACE=LPS`` tag 3D Slicer writes (legacy VTK and STL
header, a ``SPACE`` string field array in .vtp/.vtu) is returned with the mesh; the writers
put ``SPACE=<space>`` in the same places and write legacy VTK as version 4.2, as Slicer does.

"""

from __future__ import annotations

import contextlib
import importlib
import os
import re
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.errors import DataFileError, without_path
from core.io.atomic import atomic_path
from core.io.limits import DEFLATE_MAX_RATIO, check_declared_size
from core.io.registry import file_suffix
from core.types.trimesh import TriMesh, cell_arrays, triangles_of


class _VTKClasses:
    """The VTK classes the readers and writers use, each imported from its own ``vtkmodules``
    library on first use: ``import vtk`` loads every VTK library, about half a second of each
    command's start-up."""

    _LIBRARY = {
        "vtkLogger": "vtkCommonCore", "vtkOutputWindow": "vtkCommonCore",
        "vtkStringOutputWindow": "vtkCommonCore", "vtkStringArray": "vtkCommonCore",
        "vtkDataSet": "vtkCommonDataModel", "vtkPolyData": "vtkCommonDataModel",
        "vtkUnstructuredGrid": "vtkCommonDataModel", "vtkTriangleFilter": "vtkFiltersCore",
        "vtkDataSetSurfaceFilter": "vtkFiltersGeometry", "vtkDataSetReader": "vtkIOLegacy",
        "vtkPolyDataWriter": "vtkIOLegacy", "vtkXMLPolyDataReader": "vtkIOXML",
        "vtkXMLPolyDataWriter": "vtkIOXML", "vtkXMLUnstructuredGridReader": "vtkIOXML",
        "vtkSTLReader": "vtkIOGeometry", "vtkSTLWriter": "vtkIOGeometry",
        "vtkPLYWriter": "vtkIOPLY",
    }

    def __getattr__(self, name: str):
        value = getattr(importlib.import_module(f"vtkmodules.{self._LIBRARY[name]}"), name)
        setattr(self, name, value)
        return value


vtk = _VTKClasses()


def import_classes() -> None:
    """Import every VTK class the readers and writers use now (e.g. before forking reader
    children, which would each import them again)."""
    for name in _VTKClasses._LIBRARY:
        getattr(vtk, name)


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
def vtk_errors() -> Iterator[list[str]]:
    """Collect VTK's error messages in a list instead of letting VTK print them on stderr.

    VTK readers do not raise: they print errors (through the output window and the
    vtkLogger stderr sink) and return partial data. The list is filled when the block exits.
    """
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



_SPACE_TAG = re.compile(rb"SPACE\s*=\s*(RAS|LPS)", re.IGNORECASE)


def space_in_text(text: bytes | str | None) -> str | None:
    """"RAS" or "LPS" when ``text`` holds a ``SPACE=...`` tag (3D Slicer's convention)."""
    if not text:
        return None
    raw = text.encode("utf-8", "replace") if isinstance(text, str) else text
    match = _SPACE_TAG.search(raw)
    return match.group(1).decode("ascii").upper() if match else None


@contextlib.contextmanager
def vtk_file_name(path: Path) -> Iterator[str]:
    """A name of ``path`` that VTK can open: itself, or a link with an ASCII name.

    VTK's Python wrapping encodes file names as UTF-8; a name holding bytes that are not
    (lone surrogates, PEP 383) makes it raise a codec error that names no file.
    """
    name = str(path)
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        with tempfile.TemporaryDirectory(prefix="ssm-studio-") as folder:
            alias = os.path.join(folder, "file" + file_suffix(path))
            os.symlink(os.path.abspath(path), alias)
            yield alias
        return
    yield name


# VTK cell types a surface can be taken from, with their number of points (None: any >= 1,
# a negative number -n: at least n)
_CELL_POINTS = {1: 1, 2: None, 3: 2, 4: -2, 5: 3, 6: -3, 7: -3, 8: 4, 9: 4, 10: 4, 11: 8,
                12: 8, 13: 6, 14: 5, 15: 10, 16: 12, 21: 3, 22: 6, 23: 8, 24: 10, 25: 20,
                26: 15, 27: 13}
_CELL_SECTIONS = ("VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS")
_LEGACY_VALUE_BYTES = {"bit": 1, "unsigned_char": 1, "char": 1, "short": 2,
                       "unsigned_short": 2, "int": 4, "unsigned_int": 4, "long": 4,
                       "unsigned_long": 4, "vtktypeint64": 8, "vtktypeuint64": 8,
                       "float": 4, "double": 8}


def _legacy_header(path: Path, raw: bytes) -> dict:
    """What a legacy .vtk header declares: title, encoding, dataset, points, cell sections.

    Checked against the file size here (VTK would allocate what the header claims first).
    """
    lines = raw[:4096].split(b"\n", 4)
    if len(lines) < 4 or not lines[0].startswith(b"# vtk DataFile Version"):
        return {}  # not legacy VTK: VTK's reader says what it is not
    version = lines[0].split(b"Version")[-1].strip()
    binary = lines[2].strip().upper() == b"BINARY"
    declared: dict = {"title": lines[1], "binary": binary, "version": version, "cells": {}}
    value_bytes = 2 if not binary else None  # an ASCII value takes at least 2 bytes ("0 ")
    total = 0
    points = re.search(rb"^POINTS[ \t]+(-?\d+)[ \t]+(\w+)", raw, re.MULTILINE)
    if points:
        n, kind = int(points.group(1)), points.group(2).decode("ascii", "replace").lower()
        if n < 0:
            raise DataFileError(path, f"the header declares a negative number of points ({n})")
        declared["points"] = n
        total += 3 * n * (value_bytes or _LEGACY_VALUE_BYTES.get(kind, 4))
    new_style = version.startswith(b"5")
    for match in re.finditer(rb"^(VERTICES|LINES|POLYGONS|TRIANGLE_STRIPS|CELLS)[ \t]+(-?\d+)"
                             rb"[ \t]+(-?\d+)", raw, re.MULTILINE):
        section = match.group(1).decode("ascii")
        n, size = int(match.group(2)), int(match.group(3))
        if n < 0 or size < 0:
            raise DataFileError(path, f"the header declares a negative size in {section} "
                                      f"({n} {size})")
        declared["cells"][section] = (n, size)
        ints = n + size if new_style else size  # 5.1: n offsets + size ids; 4.x: size all
        total += ints * (value_bytes or (8 if new_style else 4))
    types = re.search(rb"^CELL_TYPES[ \t]+(-?\d+)", raw, re.MULTILINE)
    if types:
        declared["cell_types"] = int(types.group(1))
        total += max(0, declared["cell_types"]) * (value_bytes or 4)
    what = f"{declared.get('points', 0)} points and " \
           f"{sum(n for n, _ in declared['cells'].values())} cells"
    check_declared_size(path, total, what, truncated="truncated or corrupt .vtk file")
    return declared


_PIECE = re.compile(rb"<Piece\b([^>]*)>")
_ATTRIBUTE = re.compile(rb'(\w+)\s*=\s*"(-?\d+)"')


def _check_xml_sizes(path: Path) -> None:
    """.vtp/.vtu: the counts in each <Piece> against the file size and the memory."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    if b"<VTKFile" not in head:
        raise DataFileError(path, "not a VTK XML file (no <VTKFile> element)")
    points = cells = 0
    for piece in _PIECE.finditer(head):
        attributes = {k.decode(): int(v) for k, v in _ATTRIBUTE.findall(piece.group(1))}
        if any(v < 0 for v in attributes.values()):
            raise DataFileError(path, "a <Piece> declares a negative number of points or cells")
        points += attributes.get("NumberOfPoints", 0)
        cells += sum(v for k, v in attributes.items()
                     if k in ("NumberOfVerts", "NumberOfLines", "NumberOfStrips",
                              "NumberOfPolys", "NumberOfCells"))
    compressor = re.search(rb'compressor\s*=\s*"(\w+)"', head)
    if compressor and b"LZMA" in compressor.group(1):
        ratio = float("inf")  # LZMA can exceed any fixed ratio: the memory check decides
    elif compressor:
        ratio = DEFLATE_MAX_RATIO
    else:
        ratio = 2.0  # ASCII: >= 2 characters per 4-byte value; base64 and raw: <= 1
    # a point is 3 values (>= 4 bytes each); a cell at least one id and one offset
    check_declared_size(path, points * 12 + cells * 8, f"{points} points and {cells} cells",
                        max_ratio=ratio)


def _validate_cell_array(path: Path, cells, n_points: int, what: str, min_size: int = 1
                         ) -> np.ndarray:
    """Check one vtkCellArray before any filter sees it; returns the cell sizes."""
    offsets, connectivity = cell_arrays(cells)
    if len(offsets) == 0:
        return np.zeros(0, np.int64)
    sizes = np.diff(offsets)
    if offsets[0] != 0 or np.any(sizes < 0) or offsets[-1] != len(connectivity):
        raise DataFileError(path, f"corrupt {what} (cell offsets are not consistent)")
    if len(connectivity) and (connectivity.min() < 0 or connectivity.max() >= n_points):
        bad = int(connectivity[(connectivity < 0) | (connectivity >= n_points)][0])
        raise DataFileError(path, f"{what} refer to point {bad}, the file has {n_points} points "
                                  f"(0 to {n_points - 1})")
    if np.any(sizes < min_size):
        raise DataFileError(path, f"corrupt {what} (a cell has {int(sizes.min())} points, "
                                  f"at least {min_size} are needed)")
    return sizes


def _validate_polydata(path: Path, data, declared: dict | None) -> None:
    n_points = data.GetNumberOfPoints()
    getters = {"VERTICES": (data.GetVerts, 1), "LINES": (data.GetLines, 2),
               "POLYGONS": (data.GetPolys, 3), "TRIANGLE_STRIPS": (data.GetStrips, 3)}
    for section, (get, min_size) in getters.items():
        cells = get()
        if cells is None:
            continue
        sizes = _validate_cell_array(path, cells, n_points, section.lower().replace("_", " "),
                                     min_size)
        if declared and section in declared["cells"]:
            _compare_declared(path, section, declared, len(sizes), int(sizes.sum()))


def _compare_declared(path: Path, section: str, declared: dict, n_cells: int,
                      n_ids: int) -> None:
    """The legacy header's counts for ``section`` against what VTK read (VTK does not
    complain when a cell list is shorter than its header says, or counts run over)."""
    n, size = declared["cells"][section]
    expected_ids = size if declared["version"].startswith(b"5") else size - n
    if n_cells != (max(n - 1, 0) if declared["version"].startswith(b"5") else n) \
            or n_ids != expected_ids:
        raise DataFileError(path, f"corrupt {section} section (the header declares {n} cells "
                                  f"and {size} values, the data do not match)")


def _validate_unstructured(path: Path, data, declared: dict | None) -> None:
    from vtkmodules.util.numpy_support import vtk_to_numpy

    n_points = data.GetNumberOfPoints()
    sizes = _validate_cell_array(path, data.GetCells(), n_points, "cells")
    if declared and "CELLS" in declared["cells"]:
        _compare_declared(path, "CELLS", declared, len(sizes), int(sizes.sum()))
    type_array = data.GetCellTypes()
    types = np.zeros(0, np.int64) if type_array is None else \
        vtk_to_numpy(type_array).astype(np.int64)
    if declared and declared.get("cell_types", len(sizes)) != len(sizes):
        raise DataFileError(path, f"corrupt file: CELL_TYPES declares {declared['cell_types']} "
                                  f"types for {len(sizes)} cells")
    if len(types) != len(sizes):
        raise DataFileError(path, f"corrupt file: {len(types)} cell types for {len(sizes)} cells")
    for cell_type in np.unique(types):
        expected = _CELL_POINTS.get(int(cell_type))
        if int(cell_type) not in _CELL_POINTS:
            raise DataFileError(path, f"unsupported or invalid cell type {int(cell_type)}")
        these = sizes[types == cell_type]
        if expected is not None and expected > 0 and np.any(these != expected):
            raise DataFileError(path, f"corrupt cells: a cell of type {int(cell_type)} has "
                                      f"{int(these[these != expected][0])} points, not {expected}")
        if expected is not None and expected < 0 and np.any(these < -expected):
            raise DataFileError(path, f"corrupt cells: a cell of type {int(cell_type)} has "
                                      f"{int(these.min())} points, at least {-expected} needed")


def _read_space_tag(path: Path, suffix: str, data, raw_head: bytes) -> str | None:
    if suffix == ".vtk":
        return space_in_text(raw_head.split(b"\n", 2)[1] if raw_head.count(b"\n") >= 1 else b"")
    if suffix == ".stl":
        if raw_head[:5].lower() == b"solid":
            return space_in_text(raw_head.split(b"\n", 1)[0])
        return space_in_text(raw_head[:80])
    field = data.GetFieldData()
    array = field.GetAbstractArray("SPACE") if field is not None else None
    if array is not None and array.GetNumberOfValues() > 0:
        try:
            return space_in_text("SPACE=" + str(array.GetValue(0)))
        except (TypeError, ValueError):
            return None
    return None


def load_vtk_family(path: Path) -> tuple[TriMesh, str | None]:
    """Read .vtk, .vtp, .vtu or .stl; returns the mesh (file coordinates) and its SPACE tag."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    suffix = file_suffix(path)
    declared = None
    with open(path, "rb") as fh:
        raw_head = fh.read(4096)
    if suffix == ".stl":
        _check_stl_length(path)
    elif suffix == ".vtk":
        declared = _legacy_header(path, path.read_bytes()) or None
    else:
        _check_xml_sizes(path)
    reader = {".vtk": vtk.vtkDataSetReader, ".vtp": vtk.vtkXMLPolyDataReader,
              ".vtu": vtk.vtkXMLUnstructuredGridReader, ".stl": vtk.vtkSTLReader}[suffix]()
    with vtk_file_name(path) as name, vtk_errors() as errors:
        reader.SetFileName(name)
        reader.Update()
        data = reader.GetOutputDataObject(0)
    if errors:
        detail = without_path(without_path(errors[0], path), name)[:200]
        raise DataFileError(path, f"unreadable, truncated or corrupt {suffix} file "
                                  f"(VTK: {detail})")
    if data is None or not isinstance(data, vtk.vtkDataSet) or data.GetNumberOfPoints() == 0:
        raise DataFileError(path, f"empty mesh (no points; is this really a {suffix} file?)")
    n_points = data.GetNumberOfPoints()
    if declared is not None and declared.get("points", n_points) != n_points:
        raise DataFileError(path, f"corrupt file: the header declares {declared['points']} "
                                  f"points, {n_points} were read")
    point_data = data.GetPointData()
    for i in range(point_data.GetNumberOfArrays()):
        array = point_data.GetAbstractArray(i)
        if array is not None and array.GetNumberOfTuples() != n_points:
            raise DataFileError(path, f"truncated or corrupt {suffix} file (point array "
                                      f"'{array.GetName()}' has {array.GetNumberOfTuples()} "
                                      f"values for {n_points} points)")
    space = _read_space_tag(path, suffix, data, raw_head)
    points = vtk_to_numpy(data.GetPoints().GetData()).astype(np.float64)
    bad = ~np.all(np.isfinite(points), axis=1)
    if bad.any():
        raise DataFileError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates")
    if isinstance(data, vtk.vtkUnstructuredGrid):
        _validate_unstructured(path, data, declared)
        faces = _unstructured_surface(data)
    elif isinstance(data, vtk.vtkPolyData):
        _validate_polydata(path, data, declared)
        faces = triangles_of(data)
    else:
        kind = data.GetClassName().removeprefix("vtk")
        raise DataFileError(path, f"holds {kind} data, not a surface mesh")
    if len(faces) == 0:
        raise DataFileError(path, "mesh has no triangles and no polygons that can be "
                                  "triangulated (points or lines only)")
    return TriMesh(points, faces, path.name), space


def _unstructured_surface(grid) -> np.ndarray:
    """Triangles of the outer surface of a (validated) unstructured grid, in the grid's own
    point ids (vtkDataSetSurfaceFilter renumbers; its OriginalPointIds map back)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    surface = vtk.vtkDataSetSurfaceFilter()  # outer faces of volume cells, 2D cells as is
    surface.SetInputData(grid)
    surface.PassThroughPointIdsOn()
    surface.SetNonlinearSubdivisionLevel(0)  # no new points for quadratic cells
    surface.Update()
    poly = surface.GetOutput()
    faces = triangles_of(poly)
    ids = poly.GetPointData().GetArray(surface.GetOriginalPointIdsName())
    if ids is None or len(faces) == 0:
        return faces
    original = vtk_to_numpy(ids).astype(np.int64)
    return original[faces]


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


def _polydata_with(mesh: TriMesh, point_data: dict | None):
    poly = mesh.to_polydata()
    for name, values in (point_data or {}).items():
        poly.point_data[name] = np.asarray(values)
    return poly


def _write_with(path: Path, writer, poly) -> None:
    """Run a VTK writer into an atomic temporary file, VTK errors raised as DataFileError."""
    with atomic_path(path) as tmp:
        writer.SetFileName(str(tmp))
        writer.SetInputData(poly)
        with vtk_errors() as errors:
            ok = writer.Write()
        if errors or not ok:
            detail = errors[0] if errors else "the writer failed"
            raise DataFileError(path, f"could not be written (VTK: {detail[:200]})")


def save_legacy_vtk(path: Path, mesh: TriMesh, point_data: dict | None = None, *,
                    space: str = "RAS") -> None:
    """Binary legacy VTK, file version 4.2 (read by VTK < 9 and 3D Slicer), with
    ``SPACE=<space>`` in the header line as Slicer writes it."""
    writer = vtk.vtkPolyDataWriter()
    writer.SetFileVersion(42)
    writer.SetFileTypeToBinary()
    writer.SetHeader(f"SSM Studio output. SPACE={space}")
    _write_with(path, writer, _polydata_with(mesh, point_data))


def save_xml_vtk(path: Path, mesh: TriMesh, point_data: dict | None = None, *,
                 space: str = "RAS") -> None:
    """VTK XML polydata (.vtp, binary), with the ``SPACE`` string field array Slicer reads."""
    poly = _polydata_with(mesh, point_data)
    tag = vtk.vtkStringArray()
    tag.SetName("SPACE")
    tag.InsertNextValue(space)
    poly.GetFieldData().AddArray(tag)
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetDataModeToBinary()
    _write_with(path, writer, poly)


def save_stl(path: Path, mesh: TriMesh, point_data: dict | None = None, *,
             space: str = "RAS") -> None:
    """Binary STL with ``SPACE=<space>`` in the 80-byte header (point data cannot be kept)."""
    writer = vtk.vtkSTLWriter()
    writer.SetFileTypeToBinary()
    writer.SetHeader(f"SSM Studio output. SPACE={space}")
    _write_with(path, writer, _polydata_with(mesh, None))
