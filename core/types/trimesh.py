"""The triangle-surface type: vertices and faces as numpy arrays.

Read and written by :mod:`core.io.meshes`; the algorithms (correspondence, models,
reconstruction, slicing) work on it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np


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
        from core.io.vtk_meshes import triangles_of  # io imports this module: import late

        faces = triangles_of(poly)
        return cls(np.asarray(poly.points, dtype=np.float64), faces, name)

    def check(self, source: str | os.PathLike | None = None) -> TriMesh:
        """Raise :class:`DataFileError` (naming ``source``) if the mesh is unusable."""
        from core.errors import DataFileError  # io imports this module: import late

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
