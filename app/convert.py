"""The one adapter from core's numpy arrays to ``pyvista.PolyData`` for the 3D view."""

from __future__ import annotations

import numpy as np
import pyvista as pv


def surface_polydata(vertices: np.ndarray, faces: np.ndarray) -> pv.PolyData:
    """Triangle mesh (N, 3) vertices, (F, 3) faces -> PolyData with point normals."""
    faces = np.asarray(faces, dtype=np.int64)
    cells = np.column_stack([np.full(len(faces), 3, dtype=np.int64), faces]).ravel()
    mesh = pv.PolyData(np.asarray(vertices, dtype=np.float64), faces=cells)
    mesh.compute_normals(inplace=True, cell_normals=False, split_vertices=False)
    return mesh


def points_polydata(points: np.ndarray) -> pv.PolyData:
    """Point cloud (P, 3) -> PolyData of vertices."""
    return pv.PolyData(np.asarray(points, dtype=np.float64).reshape(-1, 3))
