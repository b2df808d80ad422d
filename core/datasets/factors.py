"""Shapes with planted local-support deformation factors: ground truth for tests and benchmarks.

A closed base surface (an ellipsoid from a UV grid, or a torus grid with an exact vertex count)
is deformed by M smooth bumps with disjoint supports: factor m moves the vertices within
geodesic-like (Euclidean on the base) distance r of its centre c_m along the surface normal by
(1 - (d / r)^2)^2. Shape k = base + sum_m a_km factor_m + Gaussian noise, a_km ~ N(0, 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.geometry import mesh as meshops
from core.geometry import toolkit as geometry


@dataclass
class PlantedShapes:
    """Synthetic training set with known factors.

    shapes (K, N, 3); faces (F, 3); factors (M, N, 3) planted; coefficients (K, M);
    supports (M, N) bool (vertices each planted factor moves); base (N, 3).
    """

    shapes: np.ndarray
    faces: np.ndarray
    factors: np.ndarray
    coefficients: np.ndarray
    supports: np.ndarray
    base: np.ndarray


def grid_surface(n_u: int, n_v: int, kind: str = "torus",
                 radii=(30.0, 12.0)) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated torus (n_u * n_v vertices) in mm; returns (vertices, faces)."""
    if kind != "torus":
        raise ValueError("only kind='torus' is supported")
    big, small = radii
    u = np.linspace(0, 2 * np.pi, n_u, endpoint=False)
    v = np.linspace(0, 2 * np.pi, n_v, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    verts = np.stack([(big + small * np.cos(vv)) * np.cos(uu),
                      (big + small * np.cos(vv)) * np.sin(uu),
                      small * np.sin(vv)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    a = (i * n_v + j).ravel()
    b = (((i + 1) % n_u) * n_v + j).ravel()
    c = (((i + 1) % n_u) * n_v + (j + 1) % n_v).ravel()
    d = (i * n_v + (j + 1) % n_v).ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return verts, faces.astype(np.int64)


def ellipsoid_surface(n_sub: int = 3, radii=(20.0, 14.0, 10.0)) -> tuple[np.ndarray, np.ndarray]:
    """A closed ellipsoid from a subdivided icosahedron (10 * 4^n_sub + 2 vertices), mm."""
    t = (1 + 5 ** 0.5) / 2
    verts = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                      [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]],
                     dtype=np.float64)
    faces = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9],
                      [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2],
                      [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
                      [8, 6, 7], [9, 8, 1]])
    for _ in range(n_sub):
        uniq, _, face_edges = meshops.edge_table(faces)
        mid = len(verts) + face_edges  # midpoints of edges (01, 12, 20) per face
        verts = np.vstack([verts, 0.5 * (verts[uniq[:, 0]] + verts[uniq[:, 1]])])
        a, b, c = faces.T
        ab, bc, ca = mid.T
        faces = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1),
                                np.stack([ca, bc, c], 1), np.stack([ab, bc, ca], 1)])
    verts /= np.linalg.norm(verts, axis=1, keepdims=True)
    return verts * np.asarray(radii), faces.astype(np.int64)


def farthest_points(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``count`` points chosen by farthest-point sampling from a random start."""
    return geometry.farthest_point_indices(points, count, start=int(rng.integers(len(points))))


def planted_shapes(base: np.ndarray, faces: np.ndarray, *, n_shapes: int = 30, n_factors: int = 6,
                   radius: float | None = None, radius_spread: float = 0.0,
                   amplitude: float = 3.0, noise: float = 0.05,
                   random_state: int = 0) -> PlantedShapes:
    """Training shapes from planted bump factors with disjoint supports (see module doc).

    radius defaults to 0.45 x the smallest distance between two bump centres, so supports are
    disjoint; with ``radius_spread`` s in [0, 1) the factors' radii are spread evenly over
    [(1 - s) radius, radius] (regions of different sizes); amplitude (mm) is the peak
    displacement of a factor; noise is the per-coordinate standard deviation (mm).
    """
    rng = np.random.default_rng(random_state)
    centres = farthest_points(base, n_factors, rng)
    cd = np.linalg.norm(base[centres][:, None] - base[centres][None], axis=-1)
    min_sep = cd[~np.eye(n_factors, dtype=bool)].min() if n_factors > 1 else np.ptp(base, 0).max()
    r = 0.45 * min_sep if radius is None else float(radius)
    normals = geometry.vertex_normals(base, faces)
    r = r * rng.permutation(np.linspace(1.0 - radius_spread, 1.0, n_factors))[:, None]
    d = np.linalg.norm(base[None] - base[centres][:, None], axis=-1)  # (M, N)
    bump = np.where(d < r, (1 - (d / r) ** 2) ** 2, 0.0)
    factors = amplitude * bump[:, :, None] * normals[None]
    coef = rng.standard_normal((n_shapes, n_factors))
    shapes = base + np.tensordot(coef, factors, axes=1)
    shapes = shapes + noise * rng.standard_normal(shapes.shape)
    return PlantedShapes(shapes=shapes, faces=faces, factors=factors, coefficients=coef,
                         supports=bump > 0, base=base)


def _supports(factors: np.ndarray, threshold: float) -> np.ndarray:
    mag = np.linalg.norm(factors, axis=2)
    return mag > threshold * mag.max(axis=1, keepdims=True)


def support_iou(planted: np.ndarray, recovered: np.ndarray, threshold: float = 0.1) -> np.ndarray:
    """For each planted factor, the best support IoU with any recovered factor.

    planted : (M, N, 3) and recovered : (M', N, 3) factors; a factor's support is the set of
    vertices moving more than ``threshold`` times its maximum displacement (the same rule for
    both). Returns (M,) IoU values in [0, 1].
    """
    p = _supports(planted, threshold).astype(np.int64)
    r = _supports(recovered, threshold).astype(np.int64)
    inter = p @ r.T
    union = p.sum(1)[:, None] + r.sum(1)[None] - inter
    return (inter / np.maximum(union, 1)).max(axis=1)


def mixed_shapes(base: np.ndarray, faces: np.ndarray, *, n_shapes: int = 30, n_local: int = 4,
                 n_global: int = 2, overlap: float = 1.2, amplitude: float = 3.0,
                 noise: float = 0.05, random_state: int = 0) -> PlantedShapes:
    """Training shapes from overlapping local bumps plus global modes (harder than disjoint
    bumps: no factor's support is cleanly separable from the others).

    The ``n_local`` bumps have radius ``overlap`` x the smallest distance between two centres
    (> 0.5: neighbouring supports overlap); the ``n_global`` modes move every vertex along
    its normal by a smooth function of its position (the first a linear ramp along the longest
    axis, then products of the centred coordinates), scaled to peak ``amplitude``. Supports are
    the vertices moving more than 10% of each factor's maximum. Coefficients ~ N(0, 1).
    """
    rng = np.random.default_rng(random_state)
    centres = farthest_points(base, n_local, rng)
    cd = np.linalg.norm(base[centres][:, None] - base[centres][None], axis=-1)
    min_sep = cd[~np.eye(n_local, dtype=bool)].min() if n_local > 1 else np.ptp(base, 0).max()
    d = np.linalg.norm(base[None] - base[centres][:, None], axis=-1)  # (M_local, N)
    r = overlap * min_sep
    bumps = np.where(d < r, (1 - (d / r) ** 2) ** 2, 0.0)
    c = (base - base.mean(0)) / np.ptp(base, axis=0).max()
    axes = np.argsort(-np.ptp(base, axis=0))
    fields = [c[:, axes[0]], c[:, axes[0]] * c[:, axes[1]], c[:, axes[1]] * c[:, axes[2]],
              c[:, axes[0]] ** 2 - c[:, axes[2]] ** 2]
    glob = np.array([f / np.abs(f).max() for f in fields[:n_global]]).reshape(-1, len(base))
    normals = meshops.vertex_normals(base, faces)
    factors = amplitude * np.concatenate([bumps, glob])[:, :, None] * normals[None]
    coef = rng.standard_normal((n_shapes, len(factors)))
    shapes = base + np.tensordot(coef, factors, axes=1)
    shapes = shapes + noise * rng.standard_normal(shapes.shape)
    return PlantedShapes(shapes=shapes, faces=faces, factors=factors, coefficients=coef,
                         supports=_supports(factors, 0.1), base=base)
