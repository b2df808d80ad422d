"""A template fitted to a surface by an affine pose and smooth offsets along its normals.

The deformation of the groupwise refinement passes (:mod:`core.correspondence.batch`): the
population's mean shape, posed on a shape by the affine fit over the shape's current
correspondence, is moved onto the shape's surface by

    P = A (X + (B a) * N) + t

with X the posed template's vertices, N their unit normals, ``B a`` a scalar offset field
and (A, t) an affine map (or a similarity, A = s R). The affine map takes up the anisotropic
scalings between subjects, which offsets along the normals cannot express where the surface
runs along the stretch (a tube's length, a bean's long side): with a similarity the rest
of such a stretch was left to slide (README, Measured). The offsets have a Gaussian-process
prior (squared-exponential kernel of width ``width``, standard deviation ``sd``:
``a ~ N(0, I)`` with ``B B^T`` the kernel, low rank by the Nystrom method), as Gaussian
process morphable models do (Luthi et al., IEEE TPAMI 2018), restricted here to
displacements along the template's normals: the template's points may not slide along the
surface, so each shape's local features and bumps are taken up by offsets and not by a
drift of the points. The data term
is the symmetric point-to-plane distance (Chen & Medioni 1992 for point-to-plane; both
directions as in Rusinkiewicz's symmetric ICP, SIGGRAPH 2019): template points to the
surface and surface points to the moved template, so that a tube cannot slide along its own
axis with offsets lengthening one end. Solved by Gauss-Newton (closest points recomputed
every iteration).

Nonrigid CPD, the first pass's deformation, matches point densities: where a shape's
feature is higher than the template's, its larger area draws template points in, a
tangential error of the order of the feature's size. On the known-homology benchmark
(``benchmarks/bench_correspondence.py --only spread``) this fit in the refinement pass
lowered the spread below CPD's (README, Measured).

Where it hurts (issue 27, ``benchmarks/bench_safeguard.py``, 6 shapes, true spread mean mm,
reference-based then after one pass of this fit / of nonrigid CPD): the "global" family
(bending, tapering, twisting) 2.06 -> 2.66 / 1.26, "concave" 0.55 -> 1.19 / 0.56; where it
helps: uneven beans 1.82 -> 0.79 / 1.89, uneven tubes 2.54 -> 0.66 / 2.33, label maps at 1 mm
0.78 -> 0.54 / 0.79. Not yet shown which part is the cause; what is known: the offsets move
the template only along its normals, so a tangential error of the template (the mean of the
reference-based pass, blurred where that pass is inconsistent) is carried to every shape,
and a global bend or twist, mostly tangential at a shape's ends, is left to the affine map,
which cannot bend. The safeguard (:mod:`core.correspondence.safeguard`) rolls such a pass
back and tries CPD instead.

All lengths are in the units of the points given (:func:`core.correspondence.pair`
normalises each target to unit RMS radius).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits

from core.geometry.toolkit import (
    SurfaceProjector,
    barycentric,
    face_normals,
    farthest_point_indices,
    rodrigues,
    vertex_normals,
)

NYSTROM_POINTS = 400  # landmarks of the low-rank kernel (the kernel is broad: ~0.5 of the size)
BASIS_ENERGY = 0.995  # share of the kernel's trace the offset basis keeps


@dataclass
class NormalOffsetFit:
    """``points`` (M, 3): the moved template (near the surface, not on it); ``offsets`` (M,)
    along the posed template's normals; ``pose`` (4, 4) the affine map (or similarity)
    applied after them; ``residual2`` the mean squared point-to-plane distance at the end;
    ``objective`` the fit's objective there (twice the negative log posterior up to a
    constant: data term plus prior), by which fits from different starts compare;
    ``n_iter``."""

    points: np.ndarray
    offsets: np.ndarray
    pose: np.ndarray
    residual2: float
    n_iter: int
    objective: float


def offset_basis(points: np.ndarray, width: float, sd: float, *,
                 landmarks: int = NYSTROM_POINTS, energy: float = BASIS_ENERGY) -> np.ndarray:
    """B (M, r) with ``B B^T`` ~ sd^2 exp(-|x_i - x_j|^2 / (2 width^2)) (Nystrom on
    ``landmarks`` points spread by farthest-point order, then the leading ``energy`` share).
    """
    points = np.asarray(points, dtype=np.float64)
    pick = farthest_point_indices(points, min(int(landmarks), len(points)))

    def kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d2 = (a ** 2).sum(1)[:, None] + (b ** 2).sum(1)[None] - 2.0 * a @ b.T
        return np.exp(-np.maximum(d2, 0.0) / (2.0 * width ** 2))
    cross = kernel(points, points[pick])                     # (M, m)
    lam, vec = np.linalg.eigh(kernel(points[pick], points[pick]))
    keep = lam > 1e-10 * lam.max()
    factor = cross @ (vec[:, keep] / np.sqrt(lam[keep]))     # K ~ factor factor^T
    u, s, _ = np.linalg.svd(factor, full_matrices=False)
    cum = np.cumsum(s ** 2) / (s ** 2).sum()
    r = int(np.searchsorted(cum, energy) + 1)
    return u[:, :r] * s[:r] * sd


def fit_normal_offsets(template: np.ndarray, faces: np.ndarray, target_vertices: np.ndarray,
                       target_faces: np.ndarray, *, width: float = 0.5, sd: float = 0.1,
                       noise: float = 0.02, iterations: int = 15, pose_iterations: int = 0,
                       pose: str = "affine", tolerance: float = 1e-6) -> NormalOffsetFit:
    """Fit the posed ``template`` (M, 3) with ``faces`` to the target surface (module
    docstring): ``width`` and ``sd`` of the offsets' prior, ``noise`` the point-to-plane
    residual's standard deviation, all in the points' units; ``pose`` the map fitted with
    the offsets, ``"affine"`` or ``"similarity"``. ``pose_iterations`` of the pose alone
    (the offsets held at zero) may come first, then ``iterations`` of both. A pose-first
    stage is off by default: a ring's turn about its own axis is barely constrained by the
    pose alone (README, Measured).

    Runs on one BLAS thread: a pool's workers have one, and the round-off of a threaded
    product differs, which the closest points amplify (0.01 mm on a tube); the outputs of
    the process pool, of Dask and of a run in this process stay byte-identical.
    """
    if pose not in ("affine", "similarity"):
        raise ValueError(f"pose must be 'affine' or 'similarity', got {pose!r}")
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit(np.asarray(template, dtype=np.float64), np.asarray(faces),
                    np.asarray(target_vertices, dtype=np.float64), np.asarray(target_faces),
                    width, sd, noise, (int(pose_iterations), int(iterations)), tolerance,
                    pose == "affine")


def _fit(x0: np.ndarray, faces: np.ndarray, tv: np.ndarray, tf: np.ndarray, width: float,
         sd: float, noise: float, stages: tuple[int, int], tolerance: float,
         affine: bool) -> NormalOffsetFit:
    normals = vertex_normals(x0, faces)
    basis = offset_basis(x0, width, sd)
    # The approximate projector (nearest triangle centroids) inside the loop, as the fairing
    # does: chosen when the exact search was the slower numpy one, and what the protocol's
    # numbers were measured with (the exact one, libigl's, would now cost about the same).
    target = SurfaceProjector(tv, tf, k=8, exact=False, candidates="centroids")
    target_normals = face_normals(tv, tf)
    alpha = np.zeros(basis.shape[1])
    pose = np.eye(4)
    npose = 12 if affine else 7
    residual2, objective, n_iter = 0.0, 0.0, 0
    for stage, count in enumerate(stages):
        active = basis if stage == 1 else basis[:, :0]  # the pose-only stage: no offsets
        for _ in range(count):
            n_iter += 1
            points = _moved(x0, normals, basis, alpha, pose)
            linear = normals @ pose[:3, :3].T  # d points / d offset, per vertex
            centre = points.mean(axis=0)
            e1, j1 = _to_surface(points, centre, linear, active, target, target_normals, affine)
            e2, j2 = _to_template(points, faces, centre, linear, active, tv, affine)
            balance = np.sqrt(len(points) / len(tv))  # both directions weigh the same
            jac = np.vstack([j1, balance * j2]) / noise
            hessian = jac.T @ jac
            hessian[npose:, npose:] += np.eye(active.shape[1])
            hessian[:npose, :npose] += (1e-6 * np.trace(hessian[:npose, :npose])
                                        * np.eye(npose))  # a tiny damping
            gradient = jac.T @ (np.concatenate([e1, balance * e2]) / noise)
            gradient[npose:] += alpha[:active.shape[1]]
            objective = float(np.sum((np.concatenate([e1, balance * e2]) / noise) ** 2)
                           + alpha @ alpha)
            step = -np.linalg.solve(hessian, gradient)
            pose = _pose_step(step[:npose], centre) @ pose
            alpha[:active.shape[1]] += step[npose:]
            residual2 = float(np.mean(e1 ** 2))
            offsets_step = np.abs(step[npose:]).max(initial=0.0) * sd  # alpha is in prior sds
            if np.abs(step[:npose]).max() < tolerance and offsets_step < tolerance:
                break
    points = _moved(x0, normals, basis, alpha, pose)
    return NormalOffsetFit(points, basis @ alpha, pose, residual2, n_iter, objective)


def _to_surface(points: np.ndarray, centre: np.ndarray, linear: np.ndarray, basis: np.ndarray,
                target: SurfaceProjector, target_normals: np.ndarray, affine: bool
                ) -> tuple[np.ndarray, np.ndarray]:
    """Template -> surface: point-to-plane residuals (M,) and their Jacobian (M, 7 + r; 12 + r
    for an affine pose)."""
    closest, _, tri = target.project(points)
    normals = target_normals[tri]
    residual = np.einsum("ij,ij->i", normals, points - closest)
    jac = np.hstack([_pose_rows(points - centre, normals, affine),
                     np.einsum("ij,ij->i", normals, linear)[:, None] * basis])
    return residual, jac


def _to_template(points: np.ndarray, faces: np.ndarray, centre: np.ndarray, linear: np.ndarray,
                 basis: np.ndarray, surface_points: np.ndarray, affine: bool
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Surface -> moved template: residuals (N,) and Jacobian (N, 7 + r; 12 + r for an affine
    pose), each row the barycentric mix of the closest template triangle's vertex rows."""
    back, _, tri = SurfaceProjector(points, faces, k=8, exact=False,
                                    candidates="centroids").project(surface_points)
    corners = faces[tri]
    bary = barycentric(points[corners], back)
    normals = face_normals(points, faces)[tri]
    residual = np.einsum("ij,ij->i", normals, back - surface_points)
    weights = np.einsum("ij,ikj->ik", normals, linear[corners]) * bary
    jac = np.hstack([_pose_rows(back - centre, normals, affine),
                     np.einsum("ik,ikr->ir", weights, basis[corners])])
    return residual, jac


def _moved(x0: np.ndarray, normals: np.ndarray, basis: np.ndarray, alpha: np.ndarray,
           pose: np.ndarray) -> np.ndarray:
    return (x0 + (basis @ alpha)[:, None] * normals) @ pose[:3, :3].T + pose[:3, 3]


def _pose_rows(arm: np.ndarray, normals: np.ndarray, affine: bool) -> np.ndarray:
    """Point-to-plane Jacobian rows of a small pose step about the centre: (P, 7) for a
    similarity (rotation vector, relative scale, translation), (P, 12) for an affine map
    (the 3 x 3 increment row by row, translation)."""
    if affine:
        return np.column_stack([(normals[:, :, None] * arm[:, None, :]).reshape(-1, 9), normals])
    return np.column_stack([np.cross(arm, normals), np.einsum("ij,ij->i", normals, arm), normals])


def _pose_step(step: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The similarity or affine map (4, 4) of one Gauss-Newton step, about ``centre``."""
    out = np.eye(4)
    if len(step) == 12:
        out[:3, :3] += step[:9].reshape(3, 3)
        out[:3, 3] = centre - out[:3, :3] @ centre + step[9:]
        return out
    out[:3, :3] = (1.0 + step[3]) * rodrigues(step[:3])
    out[:3, 3] = centre - out[:3, :3] @ centre + step[4:7]
    return out
