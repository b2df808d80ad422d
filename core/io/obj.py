"""Wavefront OBJ meshes (.obj): a numpy reader and writer of our own.

VTK's reader splits vertices whose faces use separate normal or texture indices, which
changes the vertex numbering, so the geometry is read here: ``v`` and ``f`` records in file
order, as the OBJ specification and other readers accept them (leading spaces or tabs, tabs
between fields, ``\\`` line continuations, comments after data, comment text in any
encoding). A ``SPACE=RAS``/``SPACE=LPS`` tag in a comment (3D Slicer) is reported.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.errors import DataFileError
from core.io.atomic import atomic_path
from core.io.polygons import polygons_to_triangles
from core.io.vtk_meshes import space_in_text
from core.types.trimesh import TriMesh

_MAX_INDEX = 1 << 40  # far beyond any mesh; keeps int64 arithmetic exact


def _logical_lines(raw: bytes) -> list[tuple[int, bytes]]:
    """(first line number, text) with ``\\`` continuations joined."""
    out: list[tuple[int, bytes]] = []
    pending: list[bytes] = []
    first = 1
    for number, line in enumerate(raw.splitlines(), start=1):
        if not pending:
            first = number
        stripped = line.rstrip()
        if stripped.endswith(b"\\"):
            pending.append(stripped[:-1] + b" ")
            continue
        pending.append(line)
        out.append((first, b"".join(pending)))
        pending = []
    if pending:
        out.append((first, b"".join(pending)))
    return out


def load_obj(path: Path) -> tuple[TriMesh, str | None]:
    """Read the geometry of a Wavefront OBJ file: 'v' and 'f' records, in file order.

    Texture coordinates, normals, groups and materials are ignored; polygons are
    fan-triangulated; negative (relative) indices are resolved as the OBJ specification
    says. Returns the mesh and the SPACE tag of its comments (or None).
    """
    raw = path.read_bytes()
    if b"\x00" in raw[:4096]:
        raise DataFileError(path, "not a text OBJ file (binary data)")
    vertex_rows: list[list[bytes]] = []
    polygons: list[np.ndarray] = []
    space = None
    for number, line in _logical_lines(raw):
        data, _, comment = line.partition(b"#")
        if comment and space is None and not vertex_rows:
            space = space_in_text(comment)
        try:
            data.decode("utf-8")  # comments may be in any encoding, records are text
        except UnicodeDecodeError:
            raise DataFileError(path, f"line {number}: not text (binary data in an OBJ "
                                      "record)") from None
        words = data.split()  # any whitespace: spaces, tabs, indentation
        if not words:
            continue
        if words[0] == b"v":
            if len(words) < 4:
                raise DataFileError(path, f"line {number}: a vertex needs 3 coordinates")
            vertex_rows.append(words[1:4])
        elif words[0] == b"f":
            try:
                ids = [int(tok.split(b"/")[0]) for tok in words[1:]]
            except ValueError:
                text = data.strip()[:60].decode("utf-8", "replace")
                raise DataFileError(path, f"line {number}: bad face record '{text}'") from None
            if len(ids) < 3:
                raise DataFileError(path, f"line {number}: a face needs at least 3 vertices")
            if any(abs(i) > _MAX_INDEX for i in ids):
                raise DataFileError(path, f"line {number}: face index out of range "
                                          f"({max(ids, key=abs)})")
            ids_array = np.array(ids, np.int64)
            if np.any(ids_array == 0):
                raise DataFileError(path, f"line {number}: face index 0 (OBJ counts from 1)")
            polygons.append(np.where(ids_array > 0, ids_array - 1, len(vertex_rows) + ids_array))
    if not vertex_rows:
        raise DataFileError(path, "empty mesh (no 'v' records; is this really a .obj file?)")
    try:
        vertices = np.array([[float(c) for c in row] for row in vertex_rows], dtype=np.float64)
    except ValueError:
        raise DataFileError(path, "non-numeric vertex coordinates") from None
    return TriMesh(vertices, polygons_to_triangles(polygons), path.name), space


def save_obj(path: Path, mesh: TriMesh, point_data: dict | None = None, *,
             space: str = "RAS") -> None:
    """Write ``v`` and ``f`` records (17 significant digits) with a ``SPACE=`` comment."""
    lines = [f"# SSM Studio output. SPACE={space}"]
    lines += [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in mesh.vertices.tolist()]
    lines += [f"f {a} {b} {c}" for a, b, c in (mesh.faces + 1).tolist()]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="ascii")
