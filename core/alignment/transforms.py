"""Pose removal for corresponded shapes: Procrustes, GPA and transformation synchronisation.

Three ways to bring K shapes with N homologous vertices each into one common frame:

- :func:`procrustes` / :func:`fit_transform`: the closed-form least-squares transform between
  two corresponded point sets (Umeyama, "Least-squares estimation of transformation parameters
  between two point patterns", TPAMI 1991), for every transformation class below;
- :func:`generalized_procrustes`: iterative generalised Procrustes analysis (GPA, Gower 1975):
  align every shape to the current mean, recompute the mean, repeat;
- :func:`synchronize_transforms`: the spectral transformation synchronisation of Bernard et al.,
  "A Solution for Multi-Alignment by Transformation Synchronisation", CVPR 2015, with the
  translation handling of the numerically stable variant ("Transitively consistent and unbiased
  multi-image registration using numerically stable transformation synchronisation", MICCAI
  workshop on spectral analysis in medical imaging, 2015). All K(K-1) pairwise transforms are
  made transitively consistent at once, so no shape serves as reference (reference-free GPA);
- :func:`synchronize_sparse` / :func:`align_shapes_sparse`: the same synchronisation at cohort
  scale, on a sparse graph of pairs (each shape with its K nearest) with sparse eigensolvers.

Conventions (all functions):

- homogeneous 4x4 matrices act on column vectors, ``x' = T @ [x, 1]``; for (N, 3) row arrays
  that is ``x' = x @ T[:3, :3].T + T[:3, 3]`` (:func:`apply_transform`);
- ``pairwise[i, j]`` maps shape j onto shape i: ``X_i ~ pairwise[i, j] (X_j)``;
- an :class:`AlignmentResult`'s ``transforms[k]`` maps input shape k into the common frame:
  ``aligned[k] = apply_transform(transforms[k], shapes[k])``.

Transformation classes (``transform=``):

=============  ==============================================================================
``rigid``      rotation + translation, ``det R = +1`` (a proper rotation, no reflection)
``euclidean``  orthogonal matrix + translation, ``det Q = +-1``: isometries, reflections allowed
               (the "euclidean" class of the CVPR 2015 paper)
``similarity`` ``s R`` + translation with s > 0 and ``det R = +1``
``affine``     any invertible 3x3 matrix + translation
=============  ==============================================================================
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from core.geometry.toolkit import umeyama
from core.runtime.progress import ProgressCallback, report

TRANSFORMS = ("similarity", "euclidean", "rigid", "affine")
METHODS = ("sync", "sync-sparse", "gpa")


@dataclass
class AlignmentResult:
    """Shapes brought into a common frame.

    Attributes
    ----------
    aligned : (K, N, 3) float
        The shapes in the common frame.
    transforms : (K, 4, 4) float
        ``transforms[k]`` maps input shape k into the common frame (column vectors).
    mean : (N, 3) float
        Mean of the aligned shapes.
    method, transform : str
        How they were aligned.
    n_iter_ : int
        GPA iterations (0 for synchronisation, which is not iterative).
    converged_ : bool
        Whether GPA met its tolerance (always True for synchronisation).
    rmsd_ : (K,) float
        Root mean square distance of each aligned shape to the mean.
    """

    aligned: np.ndarray
    transforms: np.ndarray
    mean: np.ndarray
    method: str
    transform: str
    n_iter_: int = 0
    converged_: bool = True
    rmsd_: np.ndarray = field(default_factory=lambda: np.zeros(0))


# ----------------------------------------------------------------------------- helpers

def _check_transform(transform: str) -> str:
    if transform not in TRANSFORMS:
        raise ValueError(f"transform must be one of {', '.join(TRANSFORMS)}; got {transform!r}")
    return transform


def _check_points(points, name: str = "points") -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contain NaN or infinite coordinates")
    return arr


def _check_shapes(shapes) -> np.ndarray:
    arr = np.asarray(shapes, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"shapes must be (K, N, 3), got shape {arr.shape}")
    if arr.shape[0] < 2:
        raise ValueError(f"at least 2 shapes are needed to align, got {arr.shape[0]}")
    if arr.shape[1] < 4:
        raise ValueError(f"each shape needs at least 4 points, got {arr.shape[1]}")
    if not np.all(np.isfinite(arr)):
        raise ValueError("shapes contain NaN or infinite coordinates")
    return arr


def homogeneous(linear: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 matrix [[A, t], [0, 1]] from a 3x3 ``linear`` part and a 3-vector ``translation``."""
    t = np.eye(4)
    t[:3, :3] = linear
    t[:3, 3] = translation
    return t


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 column-vector transform to (N, 3) points (or (..., N, 3) with (..., 4, 4))."""
    transform = np.asarray(transform, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    return points @ np.swapaxes(transform[..., :3, :3], -1, -2) + transform[..., None, :3, 3]


def project_linear(matrix: np.ndarray, transform: str) -> np.ndarray:
    """Nearest member of a transformation class for 3x3 linear part(s) (..., 3, 3).

    rigid: nearest rotation (SVD, det +1); euclidean: nearest orthogonal matrix (polar factor);
    similarity: nearest scaled rotation, scale = mean singular value with the sign correction;
    affine: unchanged.
    """
    _check_transform(transform)
    matrix = np.asarray(matrix, dtype=np.float64)
    if transform == "affine":
        return matrix.copy()
    u, s, vt = np.linalg.svd(matrix)
    if transform == "euclidean":
        return u @ vt
    d = np.ones(s.shape)
    d[..., -1] = np.sign(np.linalg.det(u @ vt))
    rotation = (u * d[..., None, :]) @ vt
    if transform == "rigid":
        return rotation
    scale = np.maximum((s * d).sum(axis=-1) / 3.0, 1e-12)
    return rotation * scale[..., None, None]


# ----------------------------------------------------------------------------- Procrustes

def fit_transform(source, target, transform: str = "similarity", *, weights=None) -> np.ndarray:
    """Least-squares transform (4, 4) of the given class mapping ``source`` onto ``target``.

    Minimises ``sum_i w_i ||T(source_i) - target_i||^2`` in closed form (Umeyama 1991 for the
    orthogonal classes; weighted linear least squares for affine).

    Parameters
    ----------
    source, target : (N, 3) float
        Corresponded points.
    transform : {"similarity", "euclidean", "rigid", "affine"}
    weights : (N,) float, optional
        Non-negative point weights.
    """
    _check_transform(transform)
    src = _check_points(source, "source")
    dst = _check_points(target, "target")
    if src.shape != dst.shape:
        raise ValueError(f"source and target must have the same shape, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    if w.shape != (len(src),) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be N non-negative numbers with a positive sum")
    w = w / w.sum()
    mu_s = w @ src
    mu_t = w @ dst
    s0 = src - mu_s
    t0 = dst - mu_t
    if transform == "affine":
        # Weighted normal equations A (S^T W S) = T^T W S
        cov_ss = (s0 * w[:, None]).T @ s0
        cov_ts = (t0 * w[:, None]).T @ s0
        linear = np.linalg.lstsq(cov_ss.T, cov_ts.T, rcond=None)[0].T
    else:
        scale, rotation, _ = umeyama(src, dst, w, scaling=transform == "similarity",
                                     reflection=transform == "euclidean")
        linear = scale * rotation
    return homogeneous(linear, mu_t - linear @ mu_s)


def procrustes(source, target, *, scaling: bool = True, reflection: bool = False,
               weights=None) -> tuple[np.ndarray, np.ndarray, float]:
    """Orthogonal Procrustes (Umeyama) alignment of ``source`` onto ``target``.

    Parameters
    ----------
    source, target : (N, 3) float
        Corresponded points.
    scaling : bool
        Estimate an isotropic scale.
    reflection : bool
        Allow an improper orthogonal matrix (det -1) when it fits better.
    weights : (N,) float, optional

    Returns
    -------
    T : (4, 4) float
        Maps source onto target (column vectors).
    aligned : (N, 3) float
        The transformed source.
    rmsd : float
        Root mean square distance between ``aligned`` and ``target`` (weighted if weights given).
    """
    src = _check_points(source, "source")
    dst = _check_points(target, "target")
    if scaling:
        transform = "similarity"
    else:
        transform = "euclidean" if reflection else "rigid"
    if scaling and reflection:
        t_rot = fit_transform(src, dst, "euclidean", weights=weights)
        # Scale for the reflection-allowed rotation (Umeyama Eq. 42 with the plain SVD).
        w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
        w = w / w.sum()
        s0 = src - w @ src
        t0 = dst - w @ dst
        rot = t_rot[:3, :3]
        scale = float((w * np.einsum("ij,ij->i", t0, s0 @ rot.T)).sum()
                      / max((w * (s0 ** 2).sum(axis=1)).sum(), 1e-300))
        linear = scale * rot
        T = homogeneous(linear, w @ dst - linear @ (w @ src))
    else:
        T = fit_transform(src, dst, transform, weights=weights)
    aligned = apply_transform(T, src)
    sq = ((aligned - dst) ** 2).sum(axis=1)
    if weights is None:
        rmsd = float(np.sqrt(sq.mean()))
    else:
        w = np.asarray(weights, dtype=np.float64)
        rmsd = float(np.sqrt((w * sq).sum() / w.sum()))
    return T, aligned, rmsd


# ----------------------------------------------------------------------------- GPA

def _centroid_size(points: np.ndarray) -> float:
    return float(np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean()))


def _aligned_mean(each: Callable[[], Iterator[np.ndarray]], k: int, target: np.ndarray,
                  transform: str) -> np.ndarray:
    """Mean of the ``k`` shapes ``each()`` yields, each fitted to ``target`` (one at a time,
    summed in order: what ``aligned.mean(axis=0)`` of the stacked shapes computes)."""
    total = np.zeros_like(target, dtype=np.float64)     # 0 + a == a: the same sums
    for x in each():
        total = total + apply_transform(fit_transform(x, target, transform), x)
    return total / k


def _procrustes_iterations(each: Callable[[], Iterator[np.ndarray]], k: int, mean: np.ndarray,
                           transform: str, max_iter: int, tol: float,
                           progress: ProgressCallback | None) -> tuple[np.ndarray, int, bool]:
    """GPA's iterations from the start ``mean``: (mean to fit the shapes to, iterations,
    converged). The shapes come from ``each()``, stacked or read one at a time."""
    size = _centroid_size(mean)
    gauge_class = transform if transform in ("rigid", "euclidean") else "similarity"
    converged = False
    n_iter = 0
    for n_iter in range(1, max_iter + 1):
        new_mean = _aligned_mean(each, k, mean, transform)
        # Gauge: keep the mean at the previous mean's pose and size.
        gauge = fit_transform(new_mean, mean, gauge_class)
        new_mean = apply_transform(gauge, new_mean)
        change = float(np.sqrt(((new_mean - mean) ** 2).sum(axis=1).mean())) / max(size, 1e-300)
        mean = new_mean
        report(progress, n_iter / max_iter, f"GPA iteration {n_iter}: mean moved {change:.2e}")
        if change < tol:
            converged = True
            break
    return mean, n_iter, converged


def procrustes_mean(shapes: Mapping, keys: list, transform: str = "similarity", *,
                    max_iter: int = 100, tol: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """(mean, per-shape rmsd) of :func:`generalized_procrustes` on ``[shapes[k] for k in
    keys]``, reading one shape at a time (``shapes`` may be a file-backed mapping such as
    :class:`core.correspondence.store.VertexRows`): memory independent of the number of
    shapes. The same operations in the same order, so the results are bit-identical."""
    _check_transform(transform)
    k = len(keys)
    if k < 2:
        raise ValueError(f"at least 2 shapes are needed to align, got {k}")

    def each() -> Iterator[np.ndarray]:
        for key in keys:
            x = np.asarray(shapes[key], dtype=np.float64)
            if x.ndim != 2 or x.shape[1] != 3 or len(x) < 4 or not np.all(np.isfinite(x)):
                raise ValueError(f"shape {key}: not a finite (N >= 4, 3) array")
            yield x

    total: np.ndarray | None = None
    for x in each():
        c = x - x.mean(axis=0, keepdims=True)
        total = c.copy() if total is None else total + c
    assert total is not None                            # k >= 2 shapes were checked above
    centred_mean = total / k
    distances = [((x - x.mean(axis=0, keepdims=True) - centred_mean) ** 2).sum() for x in each()]
    x0 = np.asarray(shapes[keys[int(np.argmin(distances))]], dtype=np.float64)
    target, _, _ = _procrustes_iterations(each, k, x0 - x0.mean(axis=0), transform, max_iter,
                                          tol, None)
    mean = _aligned_mean(each, k, target, transform)
    rmsd = np.array([np.sqrt(((apply_transform(fit_transform(x, target, transform), x) - mean) ** 2)
                             .sum(axis=1).mean()) for x in each()])
    return mean, rmsd


def generalized_procrustes(shapes, transform: str = "similarity", *, max_iter: int = 100,
                           tol: float = 1e-7, initial: int | None = None,
                           progress: ProgressCallback | None = None) -> AlignmentResult:
    """Iterative generalised Procrustes analysis to an evolving mean.

    Start from shape ``initial`` (default: the shape closest to the centred, unscaled mean),
    then repeat: fit every shape to the mean with ``transform``, take the new mean, and
    normalise it back to the pose and size of the previous mean (a similarity fit, which removes
    the gauge drift of GPA, so the mean keeps the size of the start shape). Stops when the
    mean moves less than ``tol`` times its size.

    Parameters
    ----------
    shapes : (K, N, 3) float
    transform : {"similarity", "euclidean", "rigid", "affine"}

    Returns
    -------
    AlignmentResult
        With ``n_iter_`` and ``converged_``.
    """
    _check_transform(transform)
    x = _check_shapes(shapes)
    k = len(x)
    if initial is None:
        centred = x - x.mean(axis=1, keepdims=True)
        initial = int(np.argmin(((centred - centred.mean(axis=0)) ** 2).sum(axis=(1, 2))))
    mean, n_iter, converged = _procrustes_iterations(
        lambda: iter(x), k, x[initial] - x[initial].mean(axis=0), transform, max_iter, tol,
        progress)
    transforms = np.stack([fit_transform(x[i], mean, transform) for i in range(k)])
    aligned = apply_transform(transforms, x)
    mean = aligned.mean(axis=0)
    rmsd = np.sqrt(((aligned - mean) ** 2).sum(axis=2).mean(axis=1))
    report(progress, 1.0, "GPA done")
    return AlignmentResult(aligned, transforms, mean, "gpa", transform, n_iter, converged, rmsd)


# ----------------------------------------------------------------------------- synchronisation

def _spectral_linear(pairwise_linear: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Synchronise (K, K, d, d) linear maps L_ij ~ Z_i Z_j^-1; returns (K, d, d) Z_i (any gauge).

    CVPR 2015, Eq. 6-9: with W the block matrix of the L_ij (W_ii = I) and all pairs known,
    W U = K U for U = [Z_1; ...; Z_K]; U spans the null space of W - K I, found as the d right
    singular vectors of smallest singular value. With missing pairs the block row i is divided
    by its number of known pairs (degree), i.e. the null space of D^-1 W - I is used.
    """
    k, _, d, _ = pairwise_linear.shape
    w = np.where(mask[:, :, None, None], pairwise_linear, 0.0)
    w[np.arange(k), np.arange(k)] = np.eye(d)
    degree = mask.sum(axis=1) + 1.0 - mask[np.arange(k), np.arange(k)]
    big = w.transpose(0, 2, 1, 3).reshape(k * d, k * d)
    big = big / np.repeat(degree, d)[:, None]
    z = big - np.eye(k * d)  # Eq. 8: Z = W - K I (degree-normalised)
    _, _, vt = np.linalg.svd(z)
    u = vt[-d:].T  # (K d, d): null space basis
    return u.reshape(k, d, d)


def synchronize_transforms(pairwise, transform: str = "similarity", *, mask=None,
                           stable: bool = True) -> np.ndarray:
    """Transitively consistent absolute transforms from noisy pairwise ones (CVPR 2015).

    Parameters
    ----------
    pairwise : (K, K, 4, 4) or (K, K, 3, 3) float
        ``pairwise[i, j]`` maps shape j onto shape i (column vectors); 3x3 blocks mean linear
        maps without translation. Diagonal blocks are ignored.
    transform : {"similarity", "euclidean", "rigid", "affine"}
        Class the result is projected onto.
    mask : (K, K) bool, optional
        Which pairs are known (default: all). The pair graph must be connected.
    stable : bool
        Numerically stable variant (MICCAI-SASHIMI 2015): synchronise the linear parts
        spectrally, then the translations by linear least squares given them, so that large
        translations cannot swamp the rotations in the spectral problem. With ``False`` the
        full 4x4 homogeneous blocks go into one spectral problem (the CVPR 2015 formulation),
        after rescaling translations to unit size.

    Returns
    -------
    (K, 4, 4) float
        ``T[k]`` maps shape k into the common frame, so ``T[i]^-1 T[j] ~ pairwise[i, j]``.
        Gauge: the linear parts average to the identity (the common frame is the mean frame,
        not any one shape's) and the translations are the minimum-norm solution.
    """
    _check_transform(transform)
    p = np.asarray(pairwise, dtype=np.float64)
    if p.ndim != 4 or p.shape[0] != p.shape[1] or p.shape[2] != p.shape[3] or p.shape[2] not in (3, 4):
        raise ValueError(f"pairwise must be (K, K, 4, 4) or (K, K, 3, 3), got shape {p.shape}")
    k = p.shape[0]
    if k < 2:
        raise ValueError("at least 2 shapes are needed")
    known = np.ones((k, k), bool) if mask is None else np.asarray(mask, bool).copy()
    if known.shape != (k, k):  # checked before use: a wrong shape would fail in numpy
        raise ValueError(f"mask must be ({k}, {k}), got shape {known.shape}")
    known[np.arange(k), np.arange(k)] = False
    known &= np.all(np.isfinite(p.reshape(k, k, -1)), axis=2)
    if p.shape[2] == 3:
        full = np.tile(np.eye(4), (k, k, 1, 1))
        full[:, :, :3, :3] = p
        p = full
    p = np.where(known[:, :, None, None], p, 0.0)
    if stable:
        lin = _spectral_linear(p[:, :, :3, :3], known)
        lin = _gauge_and_project(lin, transform)
        # Translations: t_ij = a_i - L_ij a_j with Z_i = [A_i a_i], given synchronised A: a
        # sparse least-squares problem (4 non-zeros a row), solved by sparse normal equations
        # (a dense solve of the 3K^2 x 3K system took a minute, uninterruptible, at K = 200).
        ii, jj = np.nonzero(known)
        trans = _sparse_translations(k, ii, jj, lin, p[ii, jj, :3, 3], np.ones(len(ii)))
        # the minimum-norm solution: without the common shift a_i = A_i c (the null space)
        null = lin.reshape(3 * k, 3)
        trans = trans - (null @ np.linalg.lstsq(null, trans.reshape(-1), rcond=None)[0]).reshape(k, 3)
        z = np.tile(np.eye(4), (k, 1, 1))
        z[:, :3, :3] = lin
        z[:, :3, 3] = trans
    else:
        # Condition: N Z N^-1 with N = diag(1, 1, 1, s) divides translations by s and keeps
        # the pairwise maps consistent; undone below.
        scale = np.sqrt(np.mean(p[known][:, :3, 3] ** 2)) if known.any() else 1.0
        scale = max(float(scale), 1e-12)
        cond = np.diag([1.0, 1.0, 1.0, scale])
        cond_inv = np.diag([1.0, 1.0, 1.0, 1.0 / scale])
        u = _spectral_linear(cond @ p @ cond_inv, known)
        # Gauge: U_i = Z_i B for an unknown B; right-multiplying by (mean U)^-1 gives
        # Z_i (mean Z)^-1, whose last rows stay [0 0 0 1] and whose blocks average to I.
        z = u @ np.linalg.inv(u.mean(axis=0))
        z[:, 3, :] = [0.0, 0.0, 0.0, 1.0]
        z = cond_inv @ z @ cond
        z[:, :3, :3] = _gauge_and_project(z[:, :3, :3], transform)
    # Z_i maps the common frame into shape i; the result maps shape i into the common frame.
    return np.linalg.inv(z)


def _gauge_and_project(lin: np.ndarray, transform: str) -> np.ndarray:
    """Mean-frame gauge (right-multiply by the inverse mean block), then project each block.

    Right-multiplying every block by one matrix keeps them consistent, and the orthogonal
    polar factor of R_i M is R_i times that of M, so the projection stays consistent too.
    """
    lin = lin @ np.linalg.inv(np.mean(lin, axis=0))
    return project_linear(lin, transform)


def reference_transforms(pairwise, reference: int = 0) -> np.ndarray:
    """The reference-based baseline: shape k is mapped by ``pairwise[reference, k]`` only.

    Returns (K, 4, 4) transforms into the reference's frame (same convention as
    :func:`synchronize_transforms`); used to show what synchronisation gains.
    """
    p = np.asarray(pairwise, dtype=np.float64)
    if p.shape[2] == 3:
        full = np.tile(np.eye(4), (p.shape[0], 1, 1))
        full[:, :3, :3] = p[reference]
        out = full
    else:
        out = p[reference].copy()
    out[reference] = np.eye(4)
    return out


def pairwise_transforms(shapes, transform: str = "similarity") -> np.ndarray:
    """All (K, K, 4, 4) least-squares transforms, ``[i, j]`` mapping shape j onto shape i."""
    x = _check_shapes(shapes)
    k = len(x)
    out = np.tile(np.eye(4), (k, k, 1, 1))
    for i in range(k):
        for j in range(k):
            if i != j:
                out[i, j] = fit_transform(x[j], x[i], transform)
    return out


# ----------------------------------------------------------------------------- front end

def align_shapes(shapes, method: str = "sync", transform: str = "similarity", *,
                 progress: ProgressCallback | None = None, max_iter: int = 100,
                 tol: float = 1e-7) -> AlignmentResult:
    """Remove the pose of K corresponded shapes.

    Parameters
    ----------
    shapes : (K, N, 3) float
        Corresponded shapes (vertex i homologous across shapes).
    method : {"sync", "sync-sparse", "gpa"}
        ``sync``: pairwise least-squares transforms between all shapes, made consistent by
        :func:`synchronize_transforms` (reference-free, not iterative). ``sync-sparse``: the
        same on the graph of each shape's 10 nearest (:func:`align_shapes_sparse`, thousands
        of shapes). ``gpa``: iterative :func:`generalized_procrustes`.
    transform : {"similarity", "euclidean", "rigid", "affine"}

    Returns
    -------
    AlignmentResult
        ``transforms[k]`` maps shape k into the common frame. The common frame is centred on
        the mean's centroid; for ``sync`` its scale is the mean input size (similarity/affine).
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}; got {method!r}")
    if method == "sync-sparse":
        return align_shapes_sparse(shapes, transform, progress=progress)
    _check_transform(transform)
    x = _check_shapes(shapes)
    if method == "gpa":
        return generalized_procrustes(x, transform, max_iter=max_iter, tol=tol, progress=progress)
    k = len(x)
    report(progress, 0.0, "pairwise transforms")
    # Centre every shape first: the pairwise least-squares fits then have small translations
    # (exactly zero for the orthogonal classes), which keeps the spectral problem well posed.
    centroids = x.mean(axis=1)
    centring = np.tile(np.eye(4), (k, 1, 1))
    centring[:, :3, 3] = -centroids
    centred = x - centroids[:, None, :]
    pairwise = np.tile(np.eye(4), (k, k, 1, 1))
    for i in range(k):
        for j in range(k):
            if i != j:
                pairwise[i, j] = fit_transform(centred[j], centred[i], transform)
        report(progress, 0.9 * (i + 1) / k, "pairwise transforms")
    sync = synchronize_transforms(pairwise, transform)
    transforms = sync @ centring
    aligned = apply_transform(transforms, x)
    # Final gauge: centre the mean; for scaling classes give the mean the mean input size.
    mean = aligned.mean(axis=0)
    gauge = np.eye(4)
    gauge[:3, 3] = -mean.mean(axis=0)
    if transform in ("similarity", "affine"):
        target_size = np.mean([_centroid_size(s) for s in x])
        gauge[:3, :] *= target_size / max(_centroid_size(mean), 1e-300)
    transforms = gauge @ transforms
    aligned = apply_transform(transforms, x)
    mean = aligned.mean(axis=0)
    rmsd = np.sqrt(((aligned - mean) ** 2).sum(axis=2).mean(axis=1))
    report(progress, 1.0, "synchronised")
    return AlignmentResult(aligned, transforms, mean, "sync", transform, 0, True, rmsd)


# ----------------------------------------------------------------------------- cohort scale
# Sparse synchronisation (issue 15): the same problem as synchronize_transforms on a sparse
# graph of pairs (each shape with its K nearest), with a sparse eigensolver, so that thousands
# of shapes synchronise in seconds and in memory linear in the number of pairs.

def batched_fit_transforms(sources: np.ndarray, targets: np.ndarray,
                           transform: str = "similarity") -> np.ndarray:
    """Least-squares transforms (P, 4, 4) mapping ``sources[p]`` onto ``targets[p]``, (P, N, 3)
    each: :func:`fit_transform` for many pairs at once (vectorised Umeyama / least squares)."""
    _check_transform(transform)
    src = np.asarray(sources, dtype=np.float64)
    dst = np.asarray(targets, dtype=np.float64)
    mu_s = src.mean(axis=1)
    mu_t = dst.mean(axis=1)
    s0 = src - mu_s[:, None]
    t0 = dst - mu_t[:, None]
    cov = np.einsum("pni,pnj->pij", t0, s0) / src.shape[1]  # Umeyama Eq. 38
    if transform == "affine":
        cov_ss = np.einsum("pni,pnj->pij", s0, s0) / src.shape[1]
        linear = np.linalg.solve(cov_ss, np.swapaxes(cov, 1, 2)).transpose(0, 2, 1)
    else:
        u, sing, vt = np.linalg.svd(cov)
        d = np.ones(sing.shape)
        if transform != "euclidean":
            d[:, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt))  # Umeyama Eq. 39/43
        linear = (u * d[:, None, :]) @ vt
        if transform == "similarity":
            var_s = (s0 ** 2).sum(axis=(1, 2)) / src.shape[1]
            linear = linear * ((sing * d).sum(axis=1) / np.maximum(var_s, 1e-300))[:, None, None]
    out = np.tile(np.eye(4), (len(src), 1, 1))
    out[:, :3, :3] = linear
    out[:, :3, 3] = mu_t - np.einsum("pij,pj->pi", linear, mu_s)
    return out


def shape_neighbours(shapes: np.ndarray, n_neighbors: int = 10, *, n_components: int = 16,
                     random_state: int = 0) -> np.ndarray:
    """Pairs (E, 2), i < j, of each shape with its ``n_neighbors`` nearest, joined into one
    connected graph. Distance: a pose-invariant descriptor (every vertex's distance to the
    centroid over the centroid size), reduced to ``n_components`` by PCA."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    x = np.asarray(shapes, dtype=np.float64)
    k = len(x)
    radial = np.linalg.norm(x - x.mean(axis=1, keepdims=True), axis=2)
    radial /= np.sqrt((radial ** 2).mean(axis=1, keepdims=True))
    radial -= radial.mean(axis=0)
    m = max(1, min(int(n_components), k - 1, radial.shape[1]))
    rng = np.random.default_rng(random_state)
    # Randomised range finder (Halko et al. 2011) for the leading principal directions.
    q, _ = np.linalg.qr(radial.T @ (radial @ rng.normal(size=(radial.shape[1], m + 8))))
    _, _, vt = np.linalg.svd(radial @ q, full_matrices=False)
    desc = radial @ (q @ vt[:m].T)
    nn = max(1, min(int(n_neighbors), k - 1))
    _, idx = cKDTree(desc).query(desc, k=nn + 1)
    rows = np.repeat(np.arange(k), nn)
    cols = idx[:, 1:].ravel()
    keep = rows != cols
    a, b = np.minimum(rows[keep], cols[keep]), np.maximum(rows[keep], cols[keep])
    pairs = np.unique(np.column_stack([a, b]), axis=0)
    while True:
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(k, k))
        n_comp, labels = connected_components(graph, directed=False)
        if n_comp == 1:
            return pairs
        inside = np.flatnonzero(labels == 0)
        outside = np.flatnonzero(labels != 0)
        dist, near = cKDTree(desc[outside]).query(desc[inside])
        i, j = int(inside[np.argmin(dist)]), int(outside[near[np.argmin(dist)]])
        pairs = np.vstack([pairs, [min(i, j), max(i, j)]])


def synchronize_sparse(n: int, pairs: np.ndarray, transforms: np.ndarray,
                       transform: str = "similarity", *, weights=None) -> np.ndarray:
    """Transformation synchronisation on a sparse graph of pairs.

    Least-squares form of CVPR 2015's spectral relaxation: the linear parts Z (stacked, 3n x 3,
    orthonormal columns) minimise sum_e w_e ||Z_i - L_e Z_j||_F^2 over the measured pairs e =
    (i, j), i.e. they are the 3 eigenvectors of smallest eigenvalue of the sparse PSD matrix
    M = sum_e w_e E_e^T E_e (E_e = [.. I at block i, -L_e at block j ..]), found by
    shift-invert Lanczos (ARPACK). M has the sparsity of the pair graph, so memory and time
    grow with the number of pairs, not with n^2. Translations then follow by sparse least
    squares given the consistent linear parts (the numerically stable variant, MICCAI-SASHIMI
    2015). With every pair measured both ways this is the dense method's problem up to the
    degree weighting.

    Parameters
    ----------
    n : number of items.
    pairs : (E, 2) int, (i, j): ``transforms[e]`` maps item j onto item i (column vectors).
        A pair given in one direction only is used both ways (the reverse block its inverse).
    transforms : (E, 4, 4) float.
    transform : {"similarity", "euclidean", "rigid", "affine"}
    weights : (E,) non-negative pair weights (default 1).

    Returns
    -------
    (n, 4, 4) float
        ``T[k]`` maps item k into the common frame (the convention of
        :func:`synchronize_transforms`); the graph must be connected.
    """
    _check_transform(transform)
    pairs, t, w = _sparse_pairs_both_ways(n, pairs, transforms, weights)
    i, j = pairs[:, 0], pairs[:, 1]
    z = _gauge_and_project(_sparse_linear_parts(n, i, j, t[:, :3, :3], w), transform)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = z
    out[:, :3, 3] = _sparse_translations(n, i, j, z, t[:, :3, 3], w)
    return np.linalg.inv(out)


def _sparse_pairs_both_ways(n: int, pairs, transforms, weights
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked (pairs, transforms, weights) of :func:`synchronize_sparse`, with the reverse of
    every pair measured one way only added (its block the inverse)."""
    pairs = np.asarray(pairs, dtype=np.int64)
    t = np.asarray(transforms, dtype=np.float64)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or t.shape != (len(pairs), 4, 4):
        raise ValueError(f"pairs must be (E, 2) and transforms (E, 4, 4), got {pairs.shape} and {t.shape}")
    if pairs.min(initial=0) < 0 or pairs.max(initial=0) >= n or np.any(pairs[:, 0] == pairs[:, 1]):
        raise ValueError("pairs must index distinct items in range(n)")
    w = np.ones(len(pairs)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(pairs),) or np.any(w < 0):
        raise ValueError("weights must be one non-negative number per pair")
    code = pairs[:, 0] * n + pairs[:, 1]
    missing = ~np.isin(pairs[:, 1] * n + pairs[:, 0], code)
    if missing.any():
        pairs = np.vstack([pairs, pairs[missing][:, ::-1]])
        t = np.concatenate([t, np.linalg.inv(t[missing])])
        w = np.concatenate([w, w[missing]])
    return pairs, t, w


def _block_sparse(n: int, brow: np.ndarray, bcol: np.ndarray, blocks: np.ndarray, fmt: str):
    """The (3n, 3n) sparse matrix with the 3x3 ``blocks`` at block positions (brow, bcol)
    (repeated positions add up)."""
    import scipy.sparse as sp

    r3, c3 = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    rows = (3 * brow[:, None, None] + r3).ravel()
    cols = (3 * bcol[:, None, None] + c3).ravel()
    return sp.coo_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n)).asformat(fmt)


def _sparse_linear_parts(n: int, i: np.ndarray, j: np.ndarray, lin: np.ndarray, w: np.ndarray
                         ) -> np.ndarray:
    """(n, 3, 3) linear parts before the gauge: the 3 smallest eigenvectors of the edge
    least-squares matrix M (shift-invert Lanczos), refined by LOBPCG to the CVPR 2015
    objective (preconditioned by M^-1)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import LinearOperator, eigsh, lobpcg, splu

    eye = np.broadcast_to(np.eye(3), lin.shape)
    # Blocks of M: (i,i) += w I, (j,j) += w L^T L, (i,j) += -w L, (j,i) += -w L^T.
    blocks = np.concatenate([w[:, None, None] * eye,
                             w[:, None, None] * np.swapaxes(lin, 1, 2) @ lin,
                             -w[:, None, None] * lin,
                             -w[:, None, None] * np.swapaxes(lin, 1, 2)])
    m = _block_sparse(n, np.concatenate([i, j, i, j]), np.concatenate([i, j, j, i]), blocks,
                      "csc")
    scale = float(m.diagonal().mean())
    # Shift slightly below 0: M is PSD and (for exact data) singular.
    # Minimum-degree ordering on the symmetric pattern: a third of COLAMD's fill on kNN graphs.
    shifted = splu(m + 1e-6 * scale * sp.identity(3 * n, format="csc"),
                   permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
    # a seeded start vector: ARPACK's own random one made results vary run to run (~1e-5)
    vals, vecs = eigsh(m, k=3, sigma=-1e-6 * scale, which="LM",
                       v0=np.random.default_rng(0).standard_normal(3 * n),
                       OPinv=LinearOperator(m.shape, matvec=shifted.solve, dtype=np.float64))
    start = vecs[:, np.argsort(vals)]
    # Refine to the CVPR 2015 objective itself: the null space of Z = D^-1 W - I (each block
    # compared with the average of its neighbours' predictions), i.e. the smallest eigenvectors
    # of Z^T Z, applied as two sparse products (Z^T Z itself would have 2-hop fill). LOBPCG
    # from the edge solution, preconditioned by M^-1 (the same graph Laplacian structure).
    deg = np.bincount(i, weights=w, minlength=n)
    zmat = (_block_sparse(n, i, j, (w / deg[i])[:, None, None] * lin, "csr")  # D^-1 W
            - sp.identity(3 * n, format="csr"))
    zt = zmat.T.tocsr()
    op = LinearOperator(m.shape, matvec=lambda v: zt @ (zmat @ v),
                        matmat=lambda v: zt @ (zmat @ v), dtype=np.float64)
    pre = LinearOperator(m.shape, matvec=shifted.solve, matmat=shifted.solve, dtype=np.float64)
    vals, vecs = lobpcg(op, start, M=pre, largest=False, tol=1e-8, maxiter=200)
    return vecs[:, np.argsort(vals)].reshape(n, 3, 3)


def _sparse_translations(n: int, i: np.ndarray, j: np.ndarray, z: np.ndarray,
                         shifts: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(n, 3) translations a by weighted sparse least squares on a_i - L'_e a_j = t_e, with
    the consistent L'_e = Z_i Z_j^-1 (the numerically stable variant)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    rel = z[i] @ np.linalg.inv(z[j])
    e = len(i)
    _, c3 = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    er = (3 * np.arange(e)[:, None] + np.arange(3)).ravel()
    a_rows = np.concatenate([er, np.repeat(er, 3)])
    a_cols = np.concatenate([(3 * np.repeat(i, 3) + np.tile(np.arange(3), e)),
                             (3 * j[:, None, None] + c3[None]).ravel()])
    a_vals = np.concatenate([np.ones(3 * e), -rel.reshape(-1)])
    a = sp.csr_matrix((a_vals, (a_rows, a_cols)), shape=(3 * e, 3 * n))
    sw = np.repeat(w, 3)
    normal = (a.T @ sp.diags(sw) @ a).tocsc()
    # The translations are defined up to a common shift: a small ridge picks the small-norm one.
    ridge = 1e-10 * max(float(normal.diagonal().mean()), 1e-300)
    trans = splu(normal + ridge * sp.identity(3 * n, format="csc"), permc_spec="MMD_AT_PLUS_A",
                 options={"SymmetricMode": True}).solve(a.T @ (sw * shifts.reshape(-1)))
    return trans.reshape(n, 3)


def align_shapes_sparse(shapes, transform: str = "similarity", *, n_neighbors: int = 10,
                        chunk: int = 2048, progress: ProgressCallback | None = None) -> AlignmentResult:
    """:func:`align_shapes` with ``method="sync"`` at cohort scale.

    Pairwise least-squares transforms only between each shape and its ``n_neighbors`` nearest
    (:func:`shape_neighbours`), computed in vectorised chunks, then :func:`synchronize_sparse`.
    Time and memory grow linearly with the number of shapes (measured in
    ``benchmarks/bench_cluster.py``: 5,000 shapes in seconds). Same gauge as
    :func:`align_shapes`.
    """
    _check_transform(transform)
    x = _check_shapes(shapes)
    k = len(x)
    report(progress, 0.0, "neighbour graph")
    pairs = shape_neighbours(x, n_neighbors)
    centroids = x.mean(axis=1)
    centring = np.tile(np.eye(4), (k, 1, 1))
    centring[:, :3, 3] = -centroids
    centred = x - centroids[:, None, :]
    # Both directions of every pair, as in the dense method: a least-squares similarity is not
    # symmetric (its scale shrinks towards the target with noise), and the two fits balance.
    directed = np.vstack([pairs, pairs[:, ::-1]])
    rel = np.empty((len(directed), 4, 4))
    for start in range(0, len(directed), chunk):
        p = directed[start:start + chunk]
        rel[start:start + chunk] = batched_fit_transforms(centred[p[:, 1]], centred[p[:, 0]], transform)
        report(progress, 0.1 + 0.7 * min(start + chunk, len(directed)) / len(directed),
               "pairwise transforms")
    transforms = synchronize_sparse(k, directed, rel, transform) @ centring
    report(progress, 0.9, "synchronised")
    aligned = apply_transform(transforms, x)
    mean = aligned.mean(axis=0)
    gauge = np.eye(4)
    gauge[:3, 3] = -mean.mean(axis=0)
    if transform in ("similarity", "affine"):
        target_size = float(np.mean(np.sqrt(((centred) ** 2).sum(axis=2).mean(axis=1))))
        gauge[:3, :] *= target_size / max(_centroid_size(mean), 1e-300)
    transforms = gauge @ transforms
    aligned = apply_transform(transforms, x)
    mean = aligned.mean(axis=0)
    rmsd = np.sqrt(((aligned - mean) ** 2).sum(axis=2).mean(axis=1))
    report(progress, 1.0, "synchronised")
    return AlignmentResult(aligned, transforms, mean, "sync-sparse", transform, 0, True, rmsd)
