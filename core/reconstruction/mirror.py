"""The mirror ambiguity of one contour, or of parallel slices of one view.

Points in one plane cannot tell on which side of it a shape's centre lies: a section at
height h from the centre and one at -h look alike (a ring, an ellipsoid, a tube cut once);
nor can parallel slices of one view, about their middle plane. The other candidate, the
*mirror mode*, is the fitted shape moved by -2 h along the planes' normal (h: the centre's
height above the middle plane).

Two users of it (issue 27, items 5 and 7): the fit (``core.reconstruction.fit``) restarts
once from the mirror mode on parallel slices and keeps the fit with the lower objective, and
the posterior (``core.reconstruction.uncertainty``) counts the mirror mode as a second
component of the pose's uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Parallel slices of one view: at most this many distinct depths along a world axis.
MAX_PARALLEL_SLICES = 3


@dataclass(frozen=True)
class SliceStack:
    """Points lying in one plane (``n_planes`` 1, any orientation) or in up to
    :data:`MAX_PARALLEL_SLICES` slices of one view (a world axis): the planes' unit
    ``normal`` and their depths' extent along it."""

    normal: np.ndarray
    n_planes: int
    low: float
    high: float
    depths: tuple[float, ...] = ()  # the slices' depths along the normal (parallel slices)
    n_points: int = 0

    @property
    def middle(self) -> float:
        return 0.5 * (self.low + self.high)

    @property
    def key(self) -> tuple:
        """The slices (axis and depths, to 0.01 mm) and the points' count to a power of 2: a
        warm-started fit with the same key need not look at the mirror mode again, and one
        drawn on looks again each time its points have doubled (the first points of a new
        slice say little about which side is right)."""
        return (tuple(np.round(self.normal, 3)), tuple(np.round(self.depths, 2)),
                int(np.log2(max(self.n_points, 1))))


def slice_stack(points: np.ndarray, parallel: bool = True) -> SliceStack | None:
    """The plane, or the parallel slices of one view, that hold all ``points`` (P, 3); None
    when they span three dimensions otherwise (or ``parallel`` is False and they are not
    coplanar)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 3:
        return None
    centred = points - points.mean(axis=0)
    _, sv, vt = np.linalg.svd(centred, full_matrices=False)
    depths: tuple[float, ...] = ()
    normal, n_planes = (vt[2], 1) if sv[2] <= 1e-3 * sv[0] else (None, 0)
    if normal is None and parallel:
        for axis in range(3):  # few distinct depths along a view's axis
            found = np.unique(np.round(points[:, axis], 3))
            if len(found) <= MAX_PARALLEL_SLICES and len(found) * 4 < len(points):
                normal, n_planes, depths = np.eye(3)[axis], len(found), tuple(map(float, found))
                break
    if normal is None:
        return None
    along = points @ normal
    return SliceStack(normal, n_planes, float(along.min()), float(along.max()), depths,
                      len(points))


def mirror_shift(vertices: np.ndarray, stack: SliceStack) -> np.ndarray:
    """(3,) the move from a fitted surface ``vertices`` (N, 3) to its mirror mode about the
    middle plane of ``stack``: -2 h along the normal, h the centre's height above it."""
    h = float(np.asarray(vertices, dtype=np.float64).mean(axis=0) @ stack.normal - stack.middle)
    return -2.0 * h * stack.normal
