"""Polygon lists -> triangles, shared by the PLY and OBJ readers."""

from __future__ import annotations

import numpy as np


def polygons_to_triangles(polygons: np.ndarray | list) -> np.ndarray:
    """Fan-triangulate polygons, given as an (F, k) array or a list of index arrays."""
    if isinstance(polygons, np.ndarray) and polygons.ndim == 2:
        groups = [polygons]
    else:
        by_size: dict[int, list] = {}
        for poly in polygons:
            by_size.setdefault(len(poly), []).append(poly)
        groups = [np.array(g) for g in by_size.values()]
    tris = []
    for group in groups:
        if group.ndim != 2 or group.shape[1] < 3:
            continue
        for j in range(1, group.shape[1] - 1):  # fan: (0, j, j+1)
            tris.append(group[:, [0, j, j + 1]])
    if not tris:
        return np.zeros((0, 3), np.int64)
    return np.concatenate(tris).astype(np.int64)
