"""The point-set type: points in world RAS mm with optional unit normals.

Read and written by :mod:`core.io.points`; the fitters take it as their data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PointSet:
    """Points in world RAS mm with optional unit normals.

    Attributes
    ----------
    points : (P, 3) float ndarray
    normals : (P, 3) float ndarray or None
    """

    points: np.ndarray
    normals: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=np.float64).reshape(-1, 3)
            if self.normals.shape != self.points.shape:
                raise ValueError("normals must have the same shape as points")

    def __len__(self) -> int:
        return int(self.points.shape[0])
