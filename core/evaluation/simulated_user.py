"""A simulated clinician for evaluating the reconstruction: contour points in a few slices.

The user of SSM Studio draws contour points in 2D slice views. To evaluate the fit without a
person, we intersect a held-out true surface with k slice planes (axial, coronal, sagittal or a
mix; see :func:`slice_planes`), sample points at a fixed spacing along each contour
(:func:`core.geometry.slicing.polylines`, :func:`core.geometry.slicing.sample_polyline`), add
in-plane Gaussian noise (the user clicks in the slice, so the points stay in it), and estimate
each point's normal as a user's drawing would give it: the contour tangent (central difference
of the noisy neighbours along the contour) crossed with the slice normal, pointing outwards (the
slicing orients contours counter-clockwise around the plane normal).

Also here, for tests and benchmarks without the demo data: :func:`synthetic_shapes` (a family
of deformed, bean-like ellipsoids on one icosphere topology, sizes of a deep grey-matter
nucleus) and :func:`pca_model` (a plain PCA :class:`ShapeModel` of corresponded shapes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.geometry.planes import PLANE_AXIS
from core.geometry.slicing import polylines, sample_polyline
from core.models.shape_model import ShapeModel

AXES = {name: np.eye(3)[axis] for name, axis in PLANE_AXIS.items()}  # slice normals


@dataclass
class UserPoints:
    """Contour points as a simulated user placed them.

    Attributes
    ----------
    points : (P, 3) float ndarray
        World coordinates (mm).
    normals : (P, 3) float ndarray
        Outward unit normals from the contour tangent and the slice normal (in the slice).
    contour : (P,) int ndarray
        Index of the slice plane each point was drawn in.
    planes : list of (origin (3,), normal (3,))
        The slice planes.
    loop : (P,) int ndarray
        Index of the closed contour (loop) each point belongs to; the points of one loop are
        consecutive and in drawing order.
    """

    points: np.ndarray
    normals: np.ndarray
    contour: np.ndarray
    planes: list[tuple[np.ndarray, np.ndarray]]
    loop: np.ndarray | None = None


def slice_planes(vertices: np.ndarray, k: int, orientations: str = "mixed",
                 margin: float = 0.15, rng: np.random.Generator | None = None,
                 jitter: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """k slice planes through a shape, spread over its extent.

    ``orientations``: "axial", "coronal", "sagittal" (parallel slices) or "mixed" (cycling
    axial, coronal, sagittal). The planes of one orientation sit at equal steps between
    ``margin`` and ``1 - margin`` of the shape's extent along that axis (the user avoids the
    tips); ``jitter`` (fraction of a step) moves them randomly.
    """
    if k < 1:
        raise ValueError("need at least one slice plane")
    if orientations == "mixed":
        names = [("axial", "coronal", "sagittal")[i % 3] for i in range(k)]
    elif orientations in AXES:
        names = [orientations] * k
    else:
        raise ValueError(f"unknown orientations {orientations!r}")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre = 0.5 * (lo + hi)
    planes = []
    for name in AXES:
        count = names.count(name)
        if count == 0:
            continue
        axis = AXES[name]
        a = int(np.argmax(axis))
        frac = margin + (1 - 2 * margin) * (np.arange(count) + 0.5) / count
        if rng is not None and jitter > 0:
            frac = frac + jitter * (1 - 2 * margin) / count * rng.uniform(-0.5, 0.5, count)
        for f in frac:
            origin = centre.copy()
            origin[a] = lo[a] + f * (hi[a] - lo[a])
            planes.append((origin, axis.copy()))
    return planes


def simulate_user(vertices: np.ndarray, faces: np.ndarray, k: int, *, orientations: str = "mixed",
                  spacing: float = 2.0, noise: float = 0.3, margin: float = 0.15,
                  rng: np.random.Generator | None = None,
                  planes: list[tuple[np.ndarray, np.ndarray]] | None = None) -> UserPoints:
    """Contour points of the true surface (vertices (N, 3), faces (F, 3)) in k slices.

    ``spacing``: mm between points along a contour; ``noise``: in-plane Gaussian standard
    deviation (mm) per coordinate; ``planes``: explicit (origin, normal) slice planes instead
    of :func:`slice_planes` (``k`` and ``orientations`` are then ignored).
    Returns :class:`UserPoints`.
    """
    rng = np.random.default_rng() if rng is None else rng
    if planes is None:
        planes = slice_planes(vertices, k, orientations, margin=margin, rng=rng)
    all_pts: list[np.ndarray] = []
    all_nrm: list[np.ndarray] = []
    all_id: list[np.ndarray] = []
    all_loop: list[np.ndarray] = []
    for plane_id, (origin, normal) in enumerate(planes):
        for line in polylines(vertices, faces, origin, normal):
            if not line.closed or line.length < 2 * spacing:
                continue
            count = max(3, int(round(line.length / spacing)))
            pts, _ = sample_polyline(line, count=count, offset=rng.uniform())
            jitter = rng.normal(scale=noise, size=pts.shape)
            jitter -= np.outer(jitter @ normal, normal)  # stay in the slice
            pts = pts + jitter
            tangent = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)  # closed contour
            nrm = np.cross(tangent, normal)
            nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
            all_pts.append(pts)
            all_nrm.append(nrm)
            all_id.append(np.full(len(pts), plane_id))
            all_loop.append(np.full(len(pts), len(all_loop)))
    if not all_pts:
        return UserPoints(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), planes,
                          np.zeros(0, np.int64))
    return UserPoints(np.vstack(all_pts), np.vstack(all_nrm), np.concatenate(all_id), planes,
                      np.concatenate(all_loop))


# --------------------------------------------------------------------------------------
# Synthetic shape families (tests, benchmarks without demo data)
# --------------------------------------------------------------------------------------


def synthetic_shapes(n_shapes: int, subdivisions: int = 3, seed: int = 0,
                     size: tuple[float, float, float] = (5.0, 4.0, 9.0)) -> tuple[np.ndarray, np.ndarray]:
    """Corresponded bean-like shapes (K, N, 3) in mm on one icosphere topology, and faces.

    Each shape is an ellipsoid with random semi-axes (about ``size``, +-15 %), bent along its
    long axis, with a random bulge and a slight twist: smooth, non-linear variation that PCA
    captures in a handful of modes.
    """
    import pyvista as pv

    sphere = pv.Icosphere(radius=1.0, nsub=subdivisions)
    base = np.asarray(sphere.points, dtype=np.float64)
    faces = sphere.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    rng = np.random.default_rng(seed)
    shapes = []
    for _ in range(n_shapes):
        axes = np.asarray(size) * (1 + 0.15 * rng.standard_normal(3))
        p = base * axes
        z = base[:, 2]
        bend = 0.25 * rng.standard_normal() * axes[0]
        p[:, 0] += bend * (z**2 - 0.5)  # banana bend along x
        bulge = 0.15 * rng.standard_normal()
        p[:, :2] *= (1 + bulge * np.exp(-((z - 0.4) ** 2) / 0.1))[:, None]
        twist = 0.2 * rng.standard_normal() * z
        c, s = np.cos(twist), np.sin(twist)
        p[:, 0], p[:, 1] = c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]
        shapes.append(p)
    return np.stack(shapes), faces


def pca_model(shapes: np.ndarray, faces: np.ndarray, n_factors: int | None = None,
              variance_floor: float = 1e-6) -> ShapeModel:
    """Plain PCA model of corresponded shapes (K, N, 3): ``core.models.PCA`` (unit factors,
    coef_var = eigenvalues), modes with variance below ``variance_floor`` x the largest dropped."""
    from core.models import PCA

    est = PCA(n_factors=n_factors, connectivity=faces).fit(shapes)
    var = est.coef_var_
    keep = max(1, int(np.sum(var > variance_floor * max(float(var[0]), 1e-300))))
    return ShapeModel(mean=est.mean_, factors=est.factors_[:keep], coef_var=var[:keep],
                      faces=faces, method="pca")
