"""Wavefront OBJ meshes (.obj): a numpy reader of our own (VTK's renumbers vertices)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.io.errors import DataFileError
from core.io.polygons import polygons_to_triangles
from core.types.trimesh import TriMesh


def load_obj(path: Path) -> TriMesh:
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
    return TriMesh(vertices, polygons_to_triangles(polygons), path.name)
