"""Surface meshes: the suffix dispatch for every mesh format, and batch reading.

The format modules (:mod:`core.io.vtk_meshes` for .vtk/.vtp/.stl, :mod:`core.io.ply`,
:mod:`core.io.obj`, :mod:`core.io.gifti`) are registered here in the dispatch table of
:mod:`core.io.registry`; :func:`load_mesh` and :func:`save_mesh` look the suffix up there.
Meshes are always triangulated on load, as :class:`TriMesh` (vertices/faces numpy arrays).
"""

from __future__ import annotations

import os
from pathlib import Path

from core.io.errors import DataFileError, require_file
from core.io.gifti import load_gifti, save_gifti
from core.io.obj import load_obj
from core.io.ply import load_ply
from core.io.registry import FileFormat, lookup, register
from core.io.vtk_meshes import load_vtk_family, save_with_pyvista
from core.types.trimesh import TriMesh

for _fmt in (
    FileFormat(".vtk", "mesh", "legacy VTK", read=load_vtk_family, write=save_with_pyvista),
    FileFormat(".vtp", "mesh", "VTK XML polydata", read=load_vtk_family, write=save_with_pyvista),
    # STL stores each triangle's corners apart: vertex numbering is lost on re-read
    FileFormat(".stl", "mesh", "STL", read=load_vtk_family, write=save_with_pyvista,
               keeps_vertex_order=False),
    FileFormat(".ply", "mesh", "PLY", read=load_ply, write=save_with_pyvista),
    FileFormat(".obj", "mesh", "Wavefront OBJ", read=load_obj, write=save_with_pyvista),
    FileFormat(".gii", "mesh", "GIfTI surface", read=load_gifti, write=save_gifti),
):
    register(_fmt)

MESH_SUFFIXES = (".vtk", ".vtp", ".stl", ".ply", ".obj", ".gii")


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
    path = require_file(path)
    fmt = lookup(path, "mesh")
    if fmt is None or fmt.read is None:
        suffix = path.suffix.lower()
        raise DataFileError(path, f"unsupported mesh format '{suffix or path.name}' (use one of "
                                  f"{', '.join(MESH_SUFFIXES)})")
    return fmt.read(path).check(path)


def save_mesh(path: str | os.PathLike, mesh: TriMesh, point_data: dict | None = None) -> None:
    """Write a triangle mesh; format chosen by extension (see :data:`MESH_SUFFIXES`).

    ``point_data`` (name -> (N,) or (N, k) array) is stored as VTK point arrays where the format
    supports it (.vtk, .vtp, .ply).
    """
    path = Path(path)
    fmt = lookup(path, "mesh")
    if fmt is None or fmt.write is None:
        raise DataFileError(path, f"unsupported mesh format '{path.suffix.lower()}'")
    mesh.check(path)
    fmt.write(path, mesh, point_data)
