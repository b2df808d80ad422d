"""Meshes read through VTK's readers: legacy .vtk (polydata or unstructured grid), .vtp, .stl.

VTK readers do not raise: they print errors and return partial data. Their messages are
captured (never printed) and turned into a :class:`DataFileError`; cut-short STL files are
refused before VTK sees them. Also the polydata -> triangles conversion used by
:meth:`TriMesh.from_polydata`.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.io.atomic import atomic_path
from core.io.errors import DataFileError
from core.io.registry import file_suffix
from core.types.trimesh import TriMesh


def triangles_of(poly) -> np.ndarray:
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
def vtk_errors() -> Iterator[list[str]]:
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


def load_vtk_family(path: Path) -> TriMesh:
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    suffix = file_suffix(path)
    if suffix == ".stl":
        _check_stl_length(path)
    reader = {".vtk": vtk.vtkDataSetReader, ".vtp": vtk.vtkXMLPolyDataReader,
              ".stl": vtk.vtkSTLReader}[suffix]()
    reader.SetFileName(str(path))
    with vtk_errors() as errors:
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
    faces = triangles_of(data)
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


def save_with_pyvista(path: Path, mesh: TriMesh, point_data: dict | None = None) -> None:
    """Write through pyvista (VTK writers), format by suffix; binary except for OBJ.

    ``point_data`` (name -> (N,) or (N, k) array) is stored as point arrays where the format
    supports it (.vtk, .vtp, .ply).
    """
    suffix = file_suffix(path)
    poly = mesh.to_polydata()
    for name, values in (point_data or {}).items():
        poly.point_data[name] = np.asarray(values)
    with atomic_path(path) as tmp:
        poly.save(str(tmp), binary=suffix != ".obj") if suffix != ".obj" else poly.save(str(tmp))
