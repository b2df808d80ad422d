"""Analytic test shapes shared by the test modules (plain functions, not fixtures)."""

from __future__ import annotations

import numpy as np
import pyvista as pv


def sphere(radius: float, center, nsub: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Outward-oriented icosphere (vertices on the sphere): (vertices (N, 3), faces (F, 3))."""
    s = pv.Icosphere(radius=radius, center=center, nsub=nsub)
    return np.asarray(s.points, dtype=np.float64), s.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
