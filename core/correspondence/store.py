"""Where a correspondence batch keeps its per-shape meshes between passes.

A batch (:mod:`core.correspondence.batch`) passes over the training set several times
(grooming, the reference-based pass, the outlier and mirror checks, the groupwise refinement
passes), and every pass needs every shape. Held by the client, that is ~0.4 MB per
2,500-vertex shape (input, groomed input, corresponded vertices): 20 GB for a 50,000-shape
cohort. So the per-shape data can live in two places:

- **in memory** (library calls: the GUI builder, tests): the groomed meshes and the
  corresponded vertices are held by this process and travel with each job, as before;
- **in a scratch directory** every worker can read and write (the command line: a folder
  inside the output folder, removed at the end): the workers read their input file by path
  (:class:`InputFile`), write the groomed mesh (:class:`ScratchMesh`), and read the current
  correspondence of their shape (:class:`Row` of a :class:`VertexRows` file); the client
  keeps per-shape scalars only, and streams the GPA mean over the rows
  (:func:`core.alignment.transforms.procrustes_mean`). Its memory stays flat in the number of
  shapes (measured in ``benchmarks/bench_cluster.py --part C``).

Jobs receive *handles* -- a :class:`~core.types.TriMesh` or array (in memory), or one of the
small path records below -- and open them with :func:`open_mesh` / :func:`open_rows`, so one
job function serves both places. The streamed GPA, :func:`core.alignment.transforms.procrustes_mean`,
runs the iterations of :func:`core.alignment.transforms.generalized_procrustes` (Gower 1975) one shape at
a time: its results are bit-identical (tested).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import warnings
from collections.abc import Iterable, Iterator, MutableMapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.runtime.parallel import preload_in_workers
from core.types import TriMesh

# the workers read input meshes (VTK readers, each file in a forked child): the fork server
# imports the VTK libraries of the .vtk/.vtp readers once, so that neither each worker nor
# each reading child imports them again (see also _import_readers)
for _library in ("vtkCommonCore", "vtkCommonDataModel", "vtkFiltersCore", "vtkFiltersGeometry",
                 "vtkIOLegacy", "vtkIOXML", "util.numpy_support"):
    preload_in_workers(f"vtkmodules.{_library}")

SCRATCH_NAME = ".correspond-scratch"


@dataclass(frozen=True)
class InputFile:
    """An input mesh file, read by the worker that needs it (a shared filesystem); ``name``
    names it in the results (default: the path)."""

    path: str
    name: str = ""


@dataclass(frozen=True)
class ScratchMesh:
    """A mesh a worker wrote into the scratch directory (``.npz``: exact arrays)."""

    path: str
    name: str = ""


@dataclass(frozen=True)
class Row:
    """Shape ``index``'s corresponded vertices in a :class:`VertexRows` file."""

    path: str
    index: int
    n_vertices: int


MeshHandle = TriMesh | InputFile | ScratchMesh


def read_input(path: str | os.PathLike) -> tuple[TriMesh | None, str | None, list[str]]:
    """Read one input mesh in a child process (a reader crash on a damaged file costs that
    file only, as :func:`core.io.load_meshes` with ``isolate``): (mesh or None, problem or
    None, the reader's warnings as text, for the client to show)."""
    from core.io import load_meshes

    _import_readers()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        loaded, failures = load_meshes([path], isolate=True)
    notes = [str(w.message) for w in caught]
    if failures:
        return None, failures[str(path)], notes
    mesh = loaded[0][1]
    mesh.name = str(path)
    return mesh, None, notes


_READERS_IMPORTED = False


def _import_readers() -> None:
    """Import the mesh readers' VTK classes here once, before the readers' children are forked
    from this process: each child would import them again (0.4 s a file instead of 20 ms)."""
    global _READERS_IMPORTED
    if not _READERS_IMPORTED:
        _READERS_IMPORTED = True
        with contextlib.suppress(ImportError, AttributeError):
            from vtkmodules.util import numpy_support  # noqa: F401

            from core.io.vtk_meshes import import_classes

            import_classes()


def open_mesh(handle: MeshHandle) -> TriMesh:
    """The mesh behind a handle (read from disk for the path records)."""
    if isinstance(handle, TriMesh):
        return handle
    if isinstance(handle, ScratchMesh):
        with np.load(handle.path) as data:
            return TriMesh(data["vertices"], data["faces"], handle.name)
    if isinstance(handle, InputFile):
        mesh, problem, _ = read_input(handle.path)
        if mesh is None:
            from core.io import DataFileError

            raise DataFileError(handle.path, problem or "cannot be read")
        return mesh
    raise TypeError(f"not a mesh handle: {type(handle).__name__}")


def write_scratch_mesh(mesh: TriMesh, directory: str | os.PathLike, index: int) -> ScratchMesh:
    """Write ``mesh`` into ``directory`` as shape ``index`` (atomically: a reader never sees
    half a file) and return its handle."""
    from core.io import atomic_path

    target = Path(directory) / f"{int(index)}.npz"
    with atomic_path(target) as tmp:  # its name keeps the .npz suffix: savez adds none
        np.savez(tmp, vertices=mesh.vertices, faces=mesh.faces)
    return ScratchMesh(str(target), mesh.name)


def open_rows(handle: np.ndarray | Row) -> np.ndarray:
    """The (N, 3) vertices behind a handle (an array in memory, or a :class:`Row`)."""
    if isinstance(handle, Row):
        fd = os.open(handle.path, os.O_RDONLY)
        try:
            return _read_row(fd, handle.index, handle.n_vertices)
        finally:
            os.close(fd)
    return np.asarray(handle, dtype=np.float64)


def _read_row(fd: int, index: int, n_vertices: int) -> np.ndarray:
    size = n_vertices * 3 * 8
    data = os.pread(fd, size, index * size)
    if len(data) != size:
        raise OSError(f"row {index} of the vertex store is incomplete")
    return np.frombuffer(data, dtype=np.float64).reshape(n_vertices, 3).copy()


class VertexRows(MutableMapping):
    """Corresponded vertices of shape i -> (N, 3) float64, kept in one file of fixed-size rows
    (row i at offset i * N * 24 bytes) rather than in memory; only the set of keys is held.

    Written by the client as results arrive (``rows[i] = v``), read by workers through
    :meth:`handle` and by the client one row at a time.
    """

    def __init__(self, path: str | os.PathLike, n_vertices: int, keys: Iterable[int] = ()):
        self.path = str(path)
        self.n_vertices = int(n_vertices)
        self._keys: set[int] = set(int(k) for k in keys)
        if not os.path.exists(self.path):
            open(self.path, "wb").close()
        self._fd = os.open(self.path, os.O_RDWR)

    def __getitem__(self, key: int) -> np.ndarray:
        if key not in self._keys:
            raise KeyError(key)
        return _read_row(self._fd, int(key), self.n_vertices)

    def __setitem__(self, key: int, vertices: np.ndarray) -> None:
        v = np.ascontiguousarray(vertices, dtype=np.float64)
        if v.shape != (self.n_vertices, 3):
            raise ValueError(f"expected ({self.n_vertices}, 3) vertices, got {v.shape}")
        os.pwrite(self._fd, v.tobytes(), int(key) * self.n_vertices * 24)
        self._keys.add(int(key))

    def __delitem__(self, key: int) -> None:
        self._keys.remove(key)

    def __iter__(self) -> Iterator[int]:
        return iter(sorted(self._keys))

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, key: object) -> bool:
        return key in self._keys

    def handle(self, key: int) -> Row:
        """What a worker needs to read row ``key`` itself (the client's writes are in the
        file before the pass that reads them is submitted)."""
        return Row(self.path, int(key), self.n_vertices)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


class Scratch:
    """A batch's scratch directory: the inputs as read (``raw/``, until groomed), the groomed
    meshes (``groomed/``) and vertex row files.

    Every worker must see it at the same path (a shared filesystem for a cluster, as for
    the inputs). :meth:`remove` deletes it (the batch does so at the end, also when stopped).
    A folder that exists already is replaced only if it carries this class's marker file (a
    stale scratch folder of a killed run): any other folder given by mistake is refused, never
    deleted.
    """

    MARKER = ".ssm-studio-scratch"

    def __init__(self, root: str | os.PathLike | None = None):
        if root is None:
            self.root = Path(tempfile.mkdtemp(prefix="ssm-correspond-"))
        else:
            self.root = Path(root)
            if self.root.exists():
                if not (self.root / self.MARKER).is_file():
                    raise ValueError(f"{self.root}: exists and is not a scratch folder of SSM "
                                     "Studio (it would be deleted at the end); give a new path")
                shutil.rmtree(self.root, ignore_errors=True)  # a stale one from a killed run
            self.root.mkdir(parents=True)
        (self.root / self.MARKER).touch()
        self.raw = self.root / "raw"        # the inputs as the workers read them
        self.groomed = self.root / "groomed"
        self.raw.mkdir()
        self.groomed.mkdir()
        self._rows: list[VertexRows] = []

    def drop_raw(self) -> None:
        """Remove the inputs as read (once every one is groomed)."""
        shutil.rmtree(self.raw, ignore_errors=True)

    def rows(self, name: str, n_vertices: int) -> VertexRows:
        rows = VertexRows(self.root / f"{name}.f64", n_vertices)
        self._rows.append(rows)
        return rows

    def remove(self) -> None:
        for rows in self._rows:
            rows.close()
        shutil.rmtree(self.root, ignore_errors=True)
