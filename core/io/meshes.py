"""Surface meshes: the suffix dispatch for every mesh format, and batch reading.

The format modules (:mod:`core.io.vtk_meshes` for .vtk/.vtp/.stl, :mod:`core.io.ply`,
:mod:`core.io.obj`, :mod:`core.io.gifti`) are registered here in the dispatch table of
:mod:`core.io.registry`; :func:`load_mesh` and :func:`save_mesh` look the suffix up there.
Meshes are always triangulated on load, as :class:`TriMesh` (vertices/faces numpy arrays).

World coordinates: SSM Studio works in RAS mm. 3D Slicer writes its models in LPS with a
``SPACE=LPS`` tag (legacy VTK and STL header, PLY and OBJ comment, a ``SPACE`` field array in
.vtp/.vtu); every reader reports the tag it finds and :func:`load_mesh` converts LPS to RAS
(x, y negated). Files without a tag are taken as RAS, as before. :func:`save_mesh` writes
``SPACE=RAS`` (or ``space="LPS"``, coordinates converted) in every format that carries it.

Vertex order: STL stores each triangle's corners apart, so a mesh read back from STL is not
numbered as it was written. Corresponded shapes (vertex i homologous across files) must not
go through STL: ``save_mesh(..., vertex_order=True)`` and ``load_meshes(..., vertex_order=
True)`` refuse it by name.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import cast

import numpy as np

from core.errors import DataFileError, DataFileWarning, require_file, warnings_as_notes
from core.io.atomic import is_temporary_name
from core.io.gifti import load_gifti, save_gifti
from core.io.limits import coordinate_problem
from core.io.obj import load_obj, save_obj
from core.io.ply import load_ply, save_ply
from core.io.registry import FileFormat, lookup, register
from core.io.vtk_meshes import load_vtk_family, save_legacy_vtk, save_stl, save_xml_vtk
from core.types.trimesh import TriMesh

for _fmt in (
    FileFormat(".vtk", "mesh", "legacy VTK", read=load_vtk_family, write=save_legacy_vtk),
    FileFormat(".vtp", "mesh", "VTK XML polydata", read=load_vtk_family, write=save_xml_vtk),
    # STL stores each triangle's corners apart: vertex numbering is lost on re-read
    FileFormat(".stl", "mesh", "STL", read=load_vtk_family, write=save_stl,
               keeps_vertex_order=False),
    FileFormat(".ply", "mesh", "PLY", read=load_ply, write=save_ply),
    FileFormat(".obj", "mesh", "Wavefront OBJ", read=load_obj, write=save_obj),
    FileFormat(".gii", "mesh", "GIfTI surface", read=load_gifti, write=save_gifti),
    FileFormat(".gii.gz", "mesh", "gzipped GIfTI surface", read=load_gifti),
    FileFormat(".vtu", "mesh", "VTK XML unstructured grid", read=load_vtk_family),
):
    register(_fmt)

MESH_SUFFIXES = (".vtk", ".vtp", ".stl", ".ply", ".obj", ".gii", ".gii.gz", ".vtu")
SPACES = ("RAS", "LPS")
_LPS_FLIP = np.array([-1.0, -1.0, 1.0])


def order_keeping_suffixes() -> tuple[str, ...]:
    """Mesh suffixes that can be written and keep vertex numbering (corresponded shapes)."""
    fmts = [lookup(Path("x" + s), "mesh") for s in MESH_SUFFIXES]
    return tuple(f.suffix for f in fmts if f is not None and f.write and f.keeps_vertex_order)


def vertex_order_problem(path: str | os.PathLike) -> str | None:
    """Why ``path``'s format cannot hold corresponded shapes, or None if it can."""
    fmt = lookup(path, "mesh")
    if fmt is None or fmt.keeps_vertex_order:
        return None
    return (f"{fmt.description} files do not keep vertex order (each triangle stores its own "
            "corners), so they cannot hold corresponded shapes; use "
            f"{', '.join(order_keeping_suffixes())}")


def expand_mesh_paths(paths: list[str | os.PathLike]) -> list[Path]:
    """Files and folders -> the mesh files among them, in order, without repeats.

    A folder stands for the files in it whose names end in one of :data:`MESH_SUFFIXES`
    (sorted by name); hidden files (name starting with a dot, e.g. the temporary files of
    an interrupted save) and editor backups (ending in ``~``) are not part of it. A folder
    with none contributes nothing. Files named explicitly are always kept.
    """
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(f for f in p.iterdir()
                            if f.is_file() and not _hidden_or_temporary(f.name)
                            and any(f.name.lower().endswith(s) for s in MESH_SUFFIXES))
        else:
            files.append(p)
    return list(dict.fromkeys(files))  # duplicates dropped, first occurrence kept


def _hidden_or_temporary(name: str) -> bool:
    return name.startswith(".") or name.endswith("~") or is_temporary_name(name)


def load_meshes(paths: Sequence[str | os.PathLike], progress: Callable | None = None, *,
                isolate: bool = False, vertex_order: bool = False,
                ) -> tuple[list[tuple[Path, TriMesh]], dict[str, str]]:
    """Read several mesh files, going on past unreadable ones (a batch is not lost to one file).

    Returns the (path, mesh) pairs read, in input order, and the problem of each file that
    could not be read (path -> message). ``progress(fraction, message)`` as in core.runtime.progress.

    ``isolate``: read in a child process (POSIX fork), so that a native crash of a VTK
    reader on a damaged file is reported for that file instead of ending this process; the
    batch goes on with the next file in a new child. ``vertex_order``: the meshes must keep
    their vertex numbering (corresponded shapes), so formats that cannot (STL) are refused.
    """
    inputs = [Path(p) for p in paths]
    failures: dict[str, str] = {}
    todo = []
    for path in inputs:
        problem = vertex_order_problem(path) if vertex_order else None
        if problem:
            failures[str(path)] = problem
        else:
            todo.append(path)
    if isolate and _can_fork():
        results = _load_in_children(todo, progress, len(inputs))
    else:
        results = {}
        for i, path in enumerate(todo):
            if progress is not None:
                progress(i / max(len(inputs), 1), f"reading {path.name}")
            results[path] = _load_one(path)
    loaded: list[tuple[Path, TriMesh]] = []
    for path in todo:
        outcome = results[path]
        if isinstance(outcome, TriMesh):
            loaded.append((path, outcome))
        else:
            failures[str(path)] = outcome
    if progress is not None:
        progress(1.0, f"{len(loaded)} meshes read")
    failures = {str(p): failures[str(p)] for p in inputs if str(p) in failures}  # input order
    return loaded, failures


def _load_one(path: Path) -> TriMesh | str:
    """The mesh, or the problem (one line, without the file name)."""
    try:
        return load_mesh(path)
    except DataFileError as exc:
        return exc.problem
    except (ValueError, OSError, MemoryError) as exc:  # should not happen: load_mesh wraps them
        return f"{type(exc).__name__}: {' '.join(str(exc).split())[:200]}"


def _can_fork() -> bool:
    return sys.platform != "win32" and hasattr(os, "fork")


def _child_reader(paths: list[Path], conn, parent: int) -> None:  # runs in the forked child
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the parent's: it kills us
    # ... and so does the parent's death (a pool worker terminated mid-read): an orphan
    # would block forever writing a mesh into the pipe, holding the command's stderr open
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    from core.runtime.parallel import die_with_parent

    die_with_parent()
    if os.getppid() != parent:  # the parent died before the request took effect
        os._exit(1)
    for index, path in enumerate(paths):
        conn.send(("start", index))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            outcome = _load_one(path)
        notes = [str(w.message) for w in caught]
        if isinstance(outcome, TriMesh):
            conn.send(("mesh", index, outcome.vertices, outcome.faces, outcome.name, notes))
        else:
            conn.send(("error", index, outcome, notes))
    conn.send(("done", len(paths)))
    conn.close()


def _load_in_children(paths: list[Path], progress: Callable | None,
                      n_total: int) -> dict[Path, TriMesh | str]:
    """Read ``paths`` in forked children; a child killed by a signal costs one file."""
    import multiprocessing

    context = multiprocessing.get_context("fork")
    results: dict[Path, TriMesh | str] = {}
    start = 0
    while start < len(paths):
        receiver, sender = context.Pipe(duplex=False)
        child = context.Process(target=_child_reader, args=(paths[start:], sender, os.getpid()),
                                daemon=True)
        with _children_allowed():
            child.start()
        sender.close()
        current, finished = None, False
        try:
            while True:
                message = receiver.recv()
                if message[0] == "start":
                    current = start + message[1]
                    if progress is not None:
                        progress(current / max(n_total, 1), f"reading {paths[current].name}")
                elif message[0] == "mesh":
                    _, index, vertices, faces, name, notes = message
                    results[paths[start + index]] = TriMesh(vertices, faces, name)
                    _reissue(notes)
                elif message[0] == "error":
                    _, index, problem, notes = message
                    results[paths[start + index]] = problem
                    _reissue(notes)
                else:
                    finished = True
                    break
        except (EOFError, OSError):
            pass
        except BaseException:  # SIGINT/SIGTERM: the reader (maybe blocked on a full pipe) goes too
            child.kill()
            raise
        finally:
            receiver.close()
            child.join()
        if finished:
            break
        crashed = start if current is None else current
        results[paths[crashed]] = _crash_text(child.exitcode)
        start = crashed + 1
    return results


@contextlib.contextmanager
def _children_allowed() -> Iterator[None]:
    """Let a daemonic process (a Dask or pool worker) start the reader's child:
    multiprocessing refuses children there because a daemon's children would be orphaned at
    its exit, but the reader's child is waited for, or killed, before the read returns (and
    dies with its parent, :func:`core.runtime.parallel.die_with_parent`)."""
    import multiprocessing

    config = getattr(multiprocessing.current_process(), "_config", {})
    daemon = config.get("daemon")
    if daemon:
        config["daemon"] = False
    try:
        yield
    finally:
        if daemon:
            config["daemon"] = daemon


def _reissue(notes: list[str]) -> None:
    for note in notes:
        warnings.warn(DataFileWarning(note), stacklevel=4)


def _crash_text(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        how = f"was killed by {name}"
    else:
        how = f"exited with code {exitcode}"
    return (f"the reader crashed on this file (the reading process {how}): the file is "
            "damaged or uses a variant this reader cannot handle")


def load_mesh(path: str | os.PathLike) -> TriMesh:
    """Read a surface mesh and triangulate it; coordinates returned in RAS mm.

    Formats: .vtk (legacy polydata or unstructured grid, whose outer surface is taken), .vtu,
    .vtp and .stl through VTK readers, after checking the sizes their headers declare and
    every cell's point ids (a damaged file would crash VTK's filters); .ply and .obj through
    numpy readers of our own (VTK's PLY reader crashes on truncated files, its OBJ reader
    renumbers vertices); GIfTI (.gii, .gii.gz: pointset + triangle arrays) through nibabel.
    Polygons and triangle strips are triangulated; vertex and line cells are ignored. Unused
    points are kept, so vertex indices stay those of the file, unstructured grids included
    (STL has no shared vertices: VTK merges coincident corners). A ``SPACE=LPS`` tag (3D
    Slicer) converts the coordinates from LPS to RAS.

    Raises
    ------
    DataFileError
        Not found, empty, unreadable or truncated (any error VTK reports while reading),
        sizes the file cannot hold, no triangles, NaN vertices, faces out of range.
    """
    path = require_file(path)
    fmt = lookup(path, "mesh")
    if fmt is None or fmt.read is None:
        suffix = path.suffix.lower()
        raise DataFileError(path, f"unsupported mesh format '{suffix or path.name}' (use one of "
                                  f"{', '.join(MESH_SUFFIXES)})")
    try:
        with warnings_as_notes(path):
            mesh, space = cast(tuple[TriMesh, str], fmt.read(path))
    except (MemoryError, RecursionError) as exc:
        raise DataFileError(path, f"cannot be read ({type(exc).__name__}: the file declares "
                                  "more data than can be held)") from None
    if space == "LPS":
        mesh = TriMesh(mesh.vertices * _LPS_FLIP, mesh.faces, mesh.name)
    mesh.check(path)
    _check_geometry(path, mesh)
    return mesh


def _check_geometry(path: Path, mesh: TriMesh) -> None:
    """Refuse coordinates no scan has (beyond 1 km: they overflow every later squared
    distance) and a mesh without extent (all vertices at one point, or every triangle of
    zero area): no shape can be measured, aligned or modelled from it."""
    problem = coordinate_problem(mesh.vertices, "vertices")
    if problem:
        raise DataFileError(path, problem)
    used = mesh.vertices[np.unique(mesh.faces)]
    if np.ptp(used, axis=0).max() == 0:
        raise DataFileError(path, f"degenerate mesh: all {len(used)} vertices of its triangles "
                                  f"lie at one point ({', '.join(f'{c:g}' for c in used[0])})")
    corners = mesh.vertices[mesh.faces]
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                   corners[:, 2] - corners[:, 0]), axis=1)
    if not np.any(area > 0):
        raise DataFileError(path, f"degenerate mesh: all {len(mesh.faces)} triangles have zero "
                                  "area (the vertices lie on a line)")


def save_mesh(path: str | os.PathLike, mesh: TriMesh, point_data: dict | None = None, *,
              space: str = "RAS", vertex_order: bool = False) -> None:
    """Write a triangle mesh; format chosen by extension (see :data:`MESH_SUFFIXES`).

    ``point_data`` (name -> (N,) or (N, k) array) is stored as point arrays where the format
    supports it (.vtk, .vtp, .ply). ``space``: the coordinate system written ("RAS", the
    default, or "LPS" for tools that expect it: coordinates converted); the tag ``SPACE=...``
    goes into the header or a comment of every format that has one (.vtk written as legacy
    version 4.2, readable by older VTK and 3D Slicer). ``vertex_order``: the mesh is a
    corresponded shape, so formats that lose vertex numbering (STL) are refused.
    """
    path = Path(path)
    fmt = lookup(path, "mesh")
    if fmt is None or fmt.write is None:
        raise DataFileError(path, f"unsupported mesh format '{path.suffix.lower()}'")
    space = str(space).upper()
    if space not in SPACES:
        raise DataFileError(path, f"unknown coordinate system '{space}' (RAS or LPS)")
    if vertex_order and not fmt.keeps_vertex_order:
        raise DataFileError(path, f"not written: {vertex_order_problem(path)}")
    mesh.check(path)
    if space == "LPS":
        mesh = TriMesh(mesh.vertices * _LPS_FLIP, mesh.faces, mesh.name)
    fmt.write(path, mesh, point_data, space=space)
