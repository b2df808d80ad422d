"""The one adapter from core's numpy arrays to ``pyvista.PolyData`` for the 3D view."""

from __future__ import annotations

import math

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


def face_camera_to(plotter, vertices: np.ndarray, faces: np.ndarray, vertex: int) -> None:
    """Turn ``plotter``'s camera about its focal point to look at ``vertex`` from outside.

    The camera keeps its distance and moves onto the surface normal at ``vertex``, so the
    region around it (e.g. the support of a local deformation factor) is in view.
    """
    from core.geometry.toolkit import vertex_normals

    camera = plotter.camera
    focal = np.asarray(camera.focal_point)
    distance = math.dist(camera.position, camera.focal_point)
    direction = vertex_normals(np.asarray(vertices, dtype=np.float64), np.asarray(faces))[vertex]
    if not np.all(np.isfinite(direction)) or not np.any(direction):
        return                       # unit normals, or zero for a degenerate neighbourhood
    up = np.asarray(camera.up)
    if abs(float(np.dot(up, direction))) > 0.95:
        up = np.eye(3)[int(np.argmin(np.abs(direction)))]
    camera.position = tuple(focal + distance * direction)
    camera.up = tuple(up)
