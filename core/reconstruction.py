"""Fit a shape model to sparse 3D points: GMM-based surface reconstruction with a shape prior.

Bernard, Salamanca, Thunberg, Tack, Jentsch, Lamecker, Zachow, Hertel, Goncalves, Gemmar:
"Shape-aware surface reconstruction from sparse 3D point-clouds", Medical Image Analysis 38
(2017). The model's surface points are the centres of a Gaussian mixture and the user's points
y_i (P, 3) are samples of it. With the model frame -> world similarity T(x) = s R x + t and
the model x_j(a) = mean_j + Phi_j a (N vertices, M factors), EM minimises the negative log
posterior

    E(a, T, s2) = - sum_i log( (1 - w)/N sum_j g_j(y_i) + w/P ) + (lambda/2) a^T diag(var)^-1 a
                  [+ (1/2) |dev(T)|^2_pose_precision, the optional pose prior, Eq. 6]

    g_j(y) = sqrt(det W_j) (2 pi s2)^(-3/2) exp(-(y - T x_j)^T W_j (y - T x_j) / (2 s2))  # Eq. 1

where w is the uniform outlier weight and W_j the precision of component j:

- ``gmm-iso``: W_j = I (spherical components, the CPD-like fit);
- ``gmm-aniso``: W_j = eta n_j n_j^T + (I - n_j n_j^T), n_j the current model normal at
  vertex j (in world), eta > 1: a flat covariance along the normal, wide in the tangent plane,
  so user points slide along the surface instead of snapping to vertices (Eq. 5 of the paper).
  With ``adaptive_anisotropy`` (the default) eta is not fixed but adapts to the data, see
  below;
- ``icp``: hard nearest-vertex correspondences and W_j = I, with the same prior: the
  baseline.

E-step (Eq. 2): p_ij = g_j(y_i) / (sum_k g_k(y_i) + c), c = (N w) / (P (1 - w)).
The sum over j is truncated to the K nearest model vertices of each user point (a
``scipy.spatial.cKDTree`` on the current vertices; K grows while s2 is large, about the
vertices within 1.5 sigma, up to ``max_neighbors``), so one iteration costs
O((N + P K) log N) instead of O(N P). The candidate pairs are reused until some vertex has
moved a quarter of the mean edge length (every iteration for ICP); responsibilities below
1e-4 are dropped.

User normals (optional, e.g. contour tangent x slice normal, pointing outwards) multiply the
E-step weight by exp(kappa (u_i . n_j - 1)): a point is unlikely to belong to a part of the
surface facing the other way (the two sides of a thin structure). This factor is treated as
fixed in the M-step (a generalised EM step) and is part of the reported objective.

M-step, with the responsibilities fixed, reduced to per-vertex sums w_j = sum_i p_ij and
ybar_j = sum_i p_ij y_i (so it costs O(|J| M^2) for the |J| vertices with weight):

- pose: for W_j = I the weighted Procrustes problem has the closed form of Umeyama (SVD of
  the weighted cross-covariance, Eq. 3; used by ICP, and by gmm-iso without a pose prior);
  for anisotropic W_j there is none, and we take one Gauss-Newton step of the
  point-to-plane-like energy in the similarity parameters (scale, small rotation via
  Rodrigues, translation), linearised at the current pose (a generalised EM step: the
  energy decreases, the step is not the exact minimiser). With ``pose_sd`` (default 3 deg,
  1 mm, 0.03 in log scale) a Gaussian prior on the deviation from the initial placement is
  added to that step (Eq. 6): it only matters in directions the points leave free (one
  or two parallel contours), where it keeps the model from sliding or scaling away;
- shape (Eq. 4): with the points mapped to the model frame, y'_i = R^T (y_i - t) / s and
  s2' = s2 / s^2,
      (sum_j w_j Phi_j^T W'_j Phi_j + lambda s2' diag(1/var)) a = sum_j Phi_j^T W'_j (ybar'_j - w_j mean_j)
  (W'_j with the normals rotated to the model frame);
- variance: s2 = sum_ij p_ij (y_i - x_j)^T W_j (y_i - x_j) / (3 sum_ij p_ij), floored at
  ``min_sigma**2`` (without a floor, s2 -> 0 on sparse data removes the prior's weight and
  the fit over-fits the few points).
- adaptive anisotropy (gmm-aniso, ``adaptive_anisotropy=True``): the covariance s2 (I - n n^T)
  + (s2 / eta) n n^T has a tangential variance s2 and a normal variance s2 / eta, and both are
  estimated (the M-step of EM for them): s2 = sum_ij p_ij |t_ij|^2 / (2 sum_ij p_ij) and
  s2 / eta = sum_ij p_ij (n_j . (y_i - x_j))^2 / sum_ij p_ij, with t_ij the tangential part of
  y_i - x_j. Why: a fixed eta = 10 (the paper's order of magnitude) states a normal noise a
  tenth of the tangential spread, and trusting the
  points along the normal more than their noise allows over-fits them when the contours are
  dense (6-12 mixed contours of the leave-one-out benchmark: 4-11 % larger mean surface
  distance than with the fitted eta, which comes out at 2-4). With very few contours
  the opposite holds: the tangential spread is then mostly the distance between the contour
  points and the vertices that merely happen to be nearest, not information, and a high eta
  (loose tangential, firm normal) is what keeps the shape from being dragged along the
  surface. So eta is bounded below by a coverage rule, eta >= clip(20 g / r, 1, anisotropy),
  with g the mean distance from the (initial) model vertices to their nearest user point and
  r the model's RMS radius (scale-free: g / r is about 0.5 for two contours of the caudate,
  0.25 for three, 0.1-0.15 for 6-12), and above by ``anisotropy``. The variance and eta are
  updated together, so each EM step still decreases E (generalised EM); when eta is clipped,
  s2 takes the fixed-eta update above. A warm start begins from the previous fit's eta.

Convergence: relative change of E below ``tol``, or the largest vertex displacement in one
iteration below ``xtol`` mm (with a small change of E). A warm start (``init``: a previous
:class:`FitResult`) starts from its pose, coefficients and variance; with an outlier term the
variance is raised to cover every point's distance to the previous surface (so a newly
placed point is not taken for an outlier). The default ``outlier_weight`` is 0: the user's
clicks are deliberate, and without an outlier term no point can lose its weight; set it > 0
for imported point clouds. ``pose_first`` (cold start only) fits the pose alone before the
shape, which helps for large initial misalignments of dense data and hurts on sparse
contours (so it is off by default).

The reported ``pose`` is the full model frame -> world transform: ``D @ model.world_transform``
with D the fitted world similarity (identity for ``pose="none"``).
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from core.geometry import (rodrigues, rotation_vector, surface_distance, umeyama,  # noqa: F401
                           vertex_face_table, vertex_normals)
from core.mesh import mean_edge_length
from core.shape_model import ShapeModel

METHODS = ("gmm-aniso", "gmm-iso", "icp")
POSES = ("similarity", "rigid", "none")
MIN_POINTS = {"similarity": 3, "rigid": 3, "none": 1}
_COVERAGE_GAIN = 20.0  # eta floor = clip(gain * gap / radius, 1, anisotropy), module docstring


@dataclass
class FitResult:
    """The result of :func:`fit_points`.

    Attributes
    ----------
    coef : (M,) float ndarray
        Shape coefficients.
    pose : (4, 4) float ndarray
        Model frame -> world transform (the fitted similarity composed with the model's
        ``world_transform``).
    vertices : (N, 3) float ndarray
        Fitted surface in world coordinates (mm).
    objective : list of float
        Negative log posterior E (Eq. 1, plus the pose prior of Eq. 6 when used) at the start
        of each iteration, and after the last.
    n_iter : int
        EM iterations run.
    converged : bool
        True when a convergence test was met (not the iteration limit).
    stop_reason : str
        Why the iteration stopped, in words.
    residual_mm : float
        Mean Euclidean distance (mm) from the user's points to the fitted surface (closest
        point on the triangles).
    sigma2 : float
        Final GMM variance (mm^2; the tangential variance for gmm-aniso).
    anisotropy : float
        Final eta, normal / tangential precision ratio (1 for gmm-iso and icp).
    method, pose_mode : str
        The options used.
    n_points : int
        Number of user points.
    elapsed_s : float
        Wall time of the fit.
    """

    coef: np.ndarray
    pose: np.ndarray
    vertices: np.ndarray
    objective: list[float] = field(default_factory=list)
    n_iter: int = 0
    converged: bool = False
    stop_reason: str = ""
    residual_mm: float = float("nan")
    sigma2: float = float("nan")
    method: str = "gmm-aniso"
    pose_mode: str = "similarity"
    anisotropy: float = 1.0
    n_points: int = 0
    elapsed_s: float = 0.0

    @property
    def scale(self) -> float:
        """Isotropic scale of ``pose`` (cube root of |det| of its linear part)."""
        return float(abs(np.linalg.det(self.pose[:3, :3])) ** (1.0 / 3.0))

    def to_dict(self) -> dict:
        """JSON-friendly summary (no vertices)."""
        return {
            "method": self.method, "pose_mode": self.pose_mode, "coef": self.coef.tolist(),
            "pose": self.pose.tolist(), "objective": [float(v) for v in self.objective],
            "n_iter": self.n_iter, "converged": self.converged, "stop_reason": self.stop_reason,
            "residual_mm": self.residual_mm, "sigma2": self.sigma2, "anisotropy": self.anisotropy,
            "n_points": self.n_points,
            "elapsed_s": self.elapsed_s,
        }


# --------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------


def _check_inputs(model: ShapeModel, points, normals, method: str, pose: str,
                  init: FitResult | None) -> tuple[np.ndarray, np.ndarray | None]:
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if pose not in POSES:
        raise ValueError(f"unknown pose {pose!r}; choose one of {', '.join(POSES)}")
    pts = np.asarray(points, dtype=np.float64)
    if pts.size == 0:
        raise ValueError("no points to fit: place at least one contour point")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be a (P, 3) array of world coordinates, got shape {pts.shape}")
    bad = ~np.all(np.isfinite(pts), axis=1)
    if bad.any():
        rows = ", ".join(str(i) for i in np.flatnonzero(bad)[:5])
        raise ValueError(f"{int(bad.sum())} point(s) have NaN or infinite coordinates (rows {rows})")
    need = MIN_POINTS[pose]
    if len(pts) < need:
        raise ValueError(f"pose={pose!r} needs at least {need} points, got {len(pts)}")
    nrm = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise ValueError(f"normals must have the points' shape {pts.shape}, got {nrm.shape}")
        if not np.all(np.isfinite(nrm)):
            raise ValueError("normals contain NaN or infinite values")
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = np.where(length > 1e-12, nrm / np.maximum(length, 1e-300), 0.0)
    if init is not None:
        if np.shape(init.coef) != (model.n_factors,) or np.shape(init.pose) != (4, 4):
            raise ValueError("the warm-start result does not belong to this model "
                             f"({np.shape(init.coef)[0]} coefficients, model has {model.n_factors})")
    return pts, nrm


def _check_extent(points: np.ndarray, vertices: np.ndarray, factor: float) -> None:
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    outside = np.linalg.norm(np.maximum(lo - points, 0) + np.maximum(points - hi, 0), axis=1)
    far = outside > factor * diag
    if far.any():
        raise ValueError(
            f"{int(far.sum())} of {len(points)} point(s) lie far outside the model "
            f"(up to {outside.max():.1f} mm from its bounding box; the model is {diag:.1f} mm "
            "across): are the points in the same world (RAS, mm) space as the model?")


# --------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------


class _ModelCache:
    """Model quantities in the 'base' frame (model frame mapped by world_transform)."""

    def __init__(self, model: ShapeModel, key: tuple):
        t0 = model.world_transform
        self.key = key
        self.sources = (model.mean, model.factors, model.coef_var, model.faces)  # ids stay unique
        self.t0 = t0.copy()
        self.mean = model.mean @ t0[:3, :3].T + t0[:3, 3]  # (N, 3)
        self.factors = model.factors @ t0[:3, :3].T  # (M, N, 3)
        self.basis_t = np.ascontiguousarray(self.factors.reshape(model.n_factors, 3 * model.n_vertices))
        self.inv_var = 1.0 / model.coef_var
        self.faces = model.faces
        self.table = vertex_face_table(model.faces, model.n_vertices)
        # Same table padded with the index F of an extra all-zero face normal (no repeats).
        self.table_pad = vertex_face_table(model.faces, model.n_vertices, fill=len(model.faces))
        self.edge_length = mean_edge_length(self.mean, model.faces)

    def shape(self, coef: np.ndarray) -> np.ndarray:
        if len(coef) == 0:
            return self.mean.copy()
        return self.mean + (coef @ self.basis_t).reshape(-1, 3)


def _is_frozen(array: np.ndarray) -> bool:
    """True when no one can write to ``array``'s memory (it and every base are read-only)."""
    while isinstance(array, np.ndarray):
        if array.flags.writeable:
            return False
        array = array.base
    return array is None or isinstance(array, bytes)


def _content_key(array: np.ndarray) -> tuple:
    """Identity of a frozen array; a digest of the content of a writable one (in-place edits)."""
    if _is_frozen(array):
        return ("id", id(array), array.shape)
    data = np.ascontiguousarray(array)
    return ("blake2b", array.shape, array.dtype.str,
            hashlib.blake2b(data.data, digest_size=16).digest())


def _cache(model: ShapeModel) -> _ModelCache:
    """The fit's precomputed model quantities, rebuilt whenever the model's content changed."""
    key = tuple(_content_key(np.asarray(getattr(model, name)))
                for name in ("mean", "factors", "coef_var", "faces", "world_transform"))
    cached = model.__dict__.get("_fit_cache")
    if cached is None or cached.key != key:
        cached = _ModelCache(model, key)
        model.__dict__["_fit_cache"] = cached
    return cached


def _solve_shape(lhs: np.ndarray, rhs: np.ndarray, bound: np.ndarray | None) -> np.ndarray:
    """Minimise a^T lhs a / 2 - rhs^T a (lhs symmetric positive semi-definite).

    With a prior (``bound`` None) lhs is positive definite: Cholesky. Without one
    (``prior_weight=0``) the data may leave directions free or barely constrained: the
    minimum-norm solution (pseudo-inverse), and if it leaves the box |a_m| <= bound_m, the
    exact box-constrained minimiser (bounded least squares on the Cholesky factor).
    """
    if bound is None:
        return np.linalg.solve(lhs, rhs)
    vals, vecs = np.linalg.eigh(lhs)
    keep = vals > 1e-10 * max(float(vals.max()), 1e-300)
    coef = vecs[:, keep] @ ((vecs[:, keep].T @ rhs) / vals[keep])
    if np.all(np.abs(coef) <= bound):
        return coef
    from scipy.optimize import lsq_linear

    # lhs = F^T F with F = diag(sqrt(vals)) V^T: minimise |F a - F^+T rhs|^2 in the box
    root = np.sqrt(np.maximum(vals, 0.0))
    f_mat = root[:, None] * vecs.T
    target = np.where(keep, (vecs.T @ rhs) / np.where(keep, root, 1.0), 0.0)
    return lsq_linear(f_mat, target, bounds=(-bound, bound), method="bvls").x


def _similarity_parts(delta: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation, translation) of a 4x4 similarity (nearest rotation by SVD)."""
    lin = delta[:3, :3]
    scale = float(abs(np.linalg.det(lin)) ** (1.0 / 3.0))
    u, _, vt = np.linalg.svd(lin / scale)
    return scale, u @ vt, delta[:3, 3].copy()


def _checked_transform(matrix, name: str) -> np.ndarray:
    t = np.asarray(matrix, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise ValueError(f"{name} must be a finite 4x4 transform, got shape {t.shape}")
    if abs(np.linalg.det(t[:3, :3])) < 1e-12:
        raise ValueError(f"{name} is singular (its 3x3 part has determinant 0)")
    return t


def _procrustes(wj: np.ndarray, ybar: np.ndarray, z: np.ndarray, with_scale: bool,
                fixed_scale: float = 1.0) -> tuple[float, np.ndarray, np.ndarray]:
    """Weighted similarity y ~ s R z + t (Eq. 3) from per-vertex sums ybar_j = sum_i p_ij y_i;
    without ``with_scale`` the scale is ``fixed_scale``.

    The weighted Umeyama fit of z_j onto ybar_j / w_j with weights w_j (the same cross
    covariance as over all pairs (i, j) weighted by p_ij).
    """
    target = np.divide(ybar, wj[:, None], out=np.zeros_like(ybar), where=wj[:, None] > 0)
    if with_scale:
        return umeyama(z, target, wj, scaling=True)
    _, rot, _ = umeyama(z, target, wj, scaling=False)
    w = wj / wj.sum()
    return float(fixed_scale), rot, w @ target - float(fixed_scale) * rot @ (w @ z)


def fit_points(model: ShapeModel, points: np.ndarray, normals: np.ndarray | None = None, *,
               placement: np.ndarray | None = None, method: str = "gmm-aniso", pose: str = "similarity", prior_weight: float = 1.0,
               init: FitResult | None = None, max_iter: int = 100, tol: float = 1e-5,
               xtol: float = 1e-2, outlier_weight: float = 0.0, anisotropy: float = 10.0,
               normal_weight: float = 2.0, n_neighbors: int = 6, max_neighbors: int = 48,
               min_sigma: float = 0.3, adaptive_anisotropy: bool = True,
               max_distance_factor: float = 1.0, pose_first: bool = False,
               pose_sd: tuple[float, float, float] | None = (3.0, 1.0, 0.03),
               pose_spread: float = 1.0, coef_bound: float = 5.0,
               callback: Callable[[int, float], None] | None = None) -> FitResult:
    """Fit ``model`` to user points by EM on the model-centred Gaussian mixture.

    Parameters
    ----------
    model : ShapeModel
        The model; its ``world_transform`` is the initial placement (when ``init`` is None).
    points : (P, 3) array
        User points in world coordinates (mm).
    normals : (P, 3) array, optional
        Outward unit normals at the points (rows of zeros: unknown). Used in the E-step.
    placement : (4, 4) array, optional
        The pose the user set (model frame -> world, e.g. the GUI's *Place here*): the cold
        start, the pose of ``pose="none"`` (and the scale of ``"rigid"``), and the centre of
        the pose prior. Default: ``model.world_transform``.
    method : {"gmm-aniso", "gmm-iso", "icp"}
        Anisotropic GMM, isotropic GMM, or ICP with the same prior.
    pose : {"similarity", "rigid", "none"}
        Which world transform is estimated on top of ``model.world_transform``.
    prior_weight : float
        lambda, the weight of the Gaussian shape prior a ~ N(0, diag(coef_var)). 0: no
        prior; the coefficients are then the minimum-norm least-squares ones, bounded to
        +-``coef_bound`` standard deviations.
    coef_bound : float
        The box |a_m| <= coef_bound sqrt(coef_var_m) used when ``prior_weight`` is 0.
    init : FitResult, optional
        Warm start (previous fit of the same model).
    max_iter, tol, xtol : int, float, float
        Iteration limit; relative objective change; largest vertex move (mm).
    outlier_weight : float
        w in [0, 1), the weight of the uniform outlier component (ignored by ICP).
    anisotropy : float
        eta >= 1, normal / tangential precision ratio of the anisotropic components (the
        upper bound of eta with ``adaptive_anisotropy``).
    adaptive_anisotropy : bool
        gmm-aniso: estimate eta with the variance in each M-step, bounded below by the
        coverage rule of the module docstring (high for few contours, lower for dense ones)
        and above by ``anisotropy``. False: eta = ``anisotropy`` throughout.
    normal_weight : float
        kappa >= 0, weight of the user-normal agreement exp(kappa (u . n - 1)).
    n_neighbors, max_neighbors : int
        K, model vertices considered per user point in the E-step: at least ``n_neighbors``,
        more while s2 is large (about those within 1.5 sigma), at most ``max_neighbors``.
    min_sigma : float
        Floor of the GMM standard deviation (mm), about the expected point noise.
    pose_sd : (rotation deg, translation mm, log scale), optional
        Standard deviations of a Gaussian prior on the fitted pose's deviation from the
        placement (``placement``, default ``model.world_transform``; also on a warm start):
        it keeps an underdetermined fit (one or two contours) from sliding or scaling away,
        and is outweighed by the data wherever the points constrain the pose. Widen it (or
        pass None) when the model is placed only roughly. GMM methods only (the pose step is
        then the linearised one, also for ``gmm-iso``).
    pose_spread : float
        Multiplies the three standard deviations of ``pose_sd`` (the Fit panel's "pose prior
        spread"); 0 removes the pose prior (like ``pose_sd=None``).
    pose_first : bool
        On a cold start, run pose-only EM to convergence before fitting the shape.
    max_distance_factor : float
        Points farther than this many model diagonals from the model's box are refused.
    callback : callable(iteration, objective), optional
        Called once per iteration; may raise ``core.progress.Cancelled``.

    Returns
    -------
    FitResult

    Raises
    ------
    ValueError
        No points, too few points for the pose, NaN coordinates, points far outside the
        model, or bad options (the message says which).
    """
    start_time = time.perf_counter()
    pts, user_normals = _check_inputs(model, points, normals, method, pose, init)
    if not prior_weight >= 0 or not 0 <= outlier_weight < 1 or not anisotropy >= 1:
        raise ValueError("need prior_weight >= 0, 0 <= outlier_weight < 1 and anisotropy >= 1")
    cache = _cache(model)
    n_vertices, n_factors, n_points = model.n_vertices, model.n_factors, len(pts)
    faces = cache.faces

    # State: world similarity D = (scale, rot, trans) applied after world_transform; coef.
    # The placement (the pose the user set) is D0: the cold start and the pose prior's centre.
    if placement is None:
        place_scale, place_rot, place_trans = 1.0, np.eye(3), np.zeros(3)
    else:
        place_scale, place_rot, place_trans = _similarity_parts(
            _checked_transform(placement, "placement") @ np.linalg.inv(cache.t0))
    if init is None:
        coef = np.zeros(n_factors)
        scale, rot, trans = place_scale, place_rot.copy(), place_trans.copy()
    else:
        coef = np.asarray(init.coef, dtype=np.float64).copy()
        scale, rot, trans = _similarity_parts(np.asarray(init.pose, dtype=np.float64)
                                              @ np.linalg.inv(cache.t0))
    if pose == "none":  # shape only, at the placement
        scale, rot, trans = place_scale, place_rot.copy(), place_trans.copy()
    elif pose == "rigid":
        scale = place_scale

    # Without a prior (prior_weight=0), the coefficients are bounded to +-coef_bound SD.
    shape_bound = None if prior_weight > 0 else float(coef_bound) * np.sqrt(model.coef_var)
    aniso = method == "gmm-aniso"
    icp = method == "icp"
    if not pose_spread >= 0:
        raise ValueError(f"pose_spread must be >= 0, got {pose_spread}")
    if pose_sd is not None and pose_spread > 0:
        pose_sd = tuple(float(v) * pose_spread for v in pose_sd)
    else:
        pose_sd = None
    if icp:
        pose_sd = None  # the ICP baseline keeps its closed-form Procrustes step
    eta = anisotropy if aniso else 1.0
    w_out = 0.0 if icp else outlier_weight
    k_near = 1 if icp else min(n_neighbors, n_vertices)
    use_normals = user_normals is not None and normal_weight > 0 and not icp
    # a model's own noise variance (statismo's PPCA noiseVariance) floors the GMM variance too
    sigma2_min = max(float(min_sigma) ** 2, float(model.info.get("noise_variance", 0.0) or 0.0))

    z = cache.shape(coef)  # base-frame shape (N, 3)
    x = scale * z @ rot.T + trans  # world vertices
    _check_extent(pts, x, max_distance_factor)
    eta_floor = eta
    if aniso and adaptive_anisotropy:
        # Coverage rule (module docstring): mean vertex -> nearest point gap over the RMS radius.
        gap, _ = cKDTree(pts).query(x)
        radius = float(np.sqrt(((x - x.mean(axis=0)) ** 2).sum(axis=1).mean()))
        eta_floor = float(np.clip(_COVERAGE_GAIN * float(gap.mean()) / max(radius, 1e-300),
                                  1.0, anisotropy))
        eta = eta_floor
        if init is not None and np.isfinite(init.anisotropy):  # warm start: the previous eta
            eta = float(np.clip(init.anisotropy, eta_floor, anisotropy))
    refresh_dist = 0.25 * cache.edge_length

    class Pairs:
        """Candidate pairs (user point, K nearest vertices), refreshed when vertices move."""

        def __init__(self, x_world: np.ndarray, k: int):
            self.k = k
            _, near = cKDTree(x_world).query(pts, k=k)
            near = np.asarray(near).reshape(n_points, k)
            self.verts, inv = np.unique(near, return_inverse=True)  # V candidate vertices
            self.inv = inv.reshape(n_points, k)  # (P, K) into verts
            self.x_ref = x_world[self.verts]
            self.phi = np.take(cache.factors, self.verts, axis=1)  # (M, V, 3), C-contiguous
            self.mean = cache.mean[self.verts]
            self.rows = np.repeat(pts, k, axis=0)  # (P K, 3)

    def normals_at(verts: np.ndarray, x_world: np.ndarray) -> np.ndarray:
        return vertex_normals(x_world, faces, at=verts, table=cache.table_pad)

    parts: dict[str, np.ndarray] = {}  # last squared distances: "full" and "along" the normal

    def mahalanobis(pairs: Pairs, xv: np.ndarray, nv: np.ndarray | None) -> np.ndarray:
        diff = pts[:, None, :] - xv[pairs.inv]  # (P, K, 3)
        d = np.einsum("pkc,pkc->pk", diff, diff)
        if aniso:
            along2 = np.einsum("pkc,pkc->pk", diff, nv[pairs.inv]) ** 2
            parts["full"], parts["along"] = d, along2
            d = d + (eta - 1.0) * along2
        return d

    need_normals = aniso or use_normals

    def neighbours_for(sigma2: float) -> int:
        """K grows with s2 (about the vertices within 1.5 sigma), so a coarse start sees far."""
        if icp:
            return 1
        wanted = int(np.ceil(8.0 * sigma2 / cache.edge_length**2))
        return int(min(max(k_near, wanted), max_neighbors, n_vertices))

    pairs = Pairs(x, k_near)
    xv = x[pairs.verts]
    nv = normals_at(pairs.verts, x) if need_normals else None
    d = mahalanobis(pairs, xv, nv)
    dmin = d.min(axis=1)
    if init is None:
        sigma2 = max(float(d.mean()) / 3.0, float(dmin.max()) / 3.0, sigma2_min)
    else:
        # Warm start: keep the previous variance. With an outlier term, raise it to cover the
        # farthest point (a newly placed point is not an outlier); without one, every point
        # keeps its full weight whatever s2 is.
        usable = np.isfinite(init.sigma2) and init.sigma2 > 0
        previous = float(init.sigma2) if usable else float(d.mean()) / 3.0
        sigma2 = max(previous, float(dmin.max()) / 3.0 if outlier_weight > 0 else 0.0, sigma2_min)

    if neighbours_for(sigma2) > pairs.k:
        pairs = Pairs(x, neighbours_for(sigma2))
        xv = x[pairs.verts]
        nv = normals_at(pairs.verts, x) if need_normals else None
        d = mahalanobis(pairs, xv, nv)
    # Cold start with a pose to fit: pose-only EM first (the shape would otherwise absorb
    # the misalignment while s2 is large), then pose and shape together.
    centre0 = cache.mean.mean(axis=0)
    placed_centre = place_scale * place_rot @ centre0 + place_trans

    def pose_deviation(scale: float, rot: np.ndarray, trans: np.ndarray) -> np.ndarray:
        """Deviation of the pose from the placement: log scale ratio, rotation vector, and the
        displacement of the model's centre (mm); the pose prior's argument (Eq. 6)."""
        return np.concatenate([[np.log(scale / place_scale)], rotation_vector(rot @ place_rot.T),
                               scale * rot @ centre0 + trans - placed_centre])

    if pose_sd is not None:
        rot_sd, trans_sd, log_scale_sd = (float(v) for v in pose_sd)
        pose_precision = 1.0 / np.array([log_scale_sd] + [np.deg2rad(rot_sd)] * 3 + [trans_sd] * 3) ** 2
    shape_active = not pose_first or init is not None or pose == "none" or n_factors == 0
    log_c = (np.log(n_vertices * w_out / ((1.0 - w_out) * n_points)) if w_out > 0 else -np.inf)
    log_norm_const = 0.5 * np.log(eta)
    objective: list[float] = []
    converged = False
    stop_reason = f"reached max_iter={max_iter}"
    n_iter = 0

    def energy(d: np.ndarray, sigma2: float, coef: np.ndarray,
               nv: np.ndarray | None) -> tuple[float, np.ndarray]:
        """Negative log posterior (Eq. 1) and the responsibilities (Eq. 2), (P, K)."""
        logits = -d / (2.0 * sigma2)
        if use_normals:
            logits = logits + normal_weight * (
                np.einsum("pc,pkc->pk", user_normals, nv[pairs.inv]) - 1.0)
        if icp:
            logits = logits[:, :1]
        m = logits.max(axis=1, keepdims=True)
        ex = np.exp(logits - m)
        s = ex.sum(axis=1, keepdims=True)
        log_norm = log_norm_const - 1.5 * np.log(2.0 * np.pi * sigma2)  # sqrt(det W)(2 pi s2)^-3/2
        comp = np.log(1.0 - w_out) - np.log(n_vertices) + log_norm + m[:, 0] + np.log(s[:, 0])
        if w_out > 0:
            loglik = np.logaddexp(comp, np.log(w_out / n_points))
            denom = s + np.exp(np.minimum(log_c - log_norm - m, 700.0))
        else:
            loglik = comp
            denom = s
        prior = 0.5 * prior_weight * float(coef @ (cache.inv_var * coef))
        if pose_sd is not None and pose != "none":  # Eq. 6, the pose prior
            dev = pose_deviation(scale, rot, trans)
            prior += 0.5 * float((pose_precision * dev**2).sum())
        resp = ex / denom
        resp[resp < 1e-4] = 0.0  # negligible pairs: fewer vertices in the M-step
        return float(-loglik.sum() + prior), resp

    for it in range(max_iter):
        e_value, p = energy(d, sigma2, coef, nv)
        objective.append(e_value)
        if callback is not None:
            callback(it, e_value)
        if it > 0 and abs(objective[-2] - e_value) <= tol * max(abs(e_value), 1.0):
            if shape_active:
                converged, stop_reason = True, f"objective change below tol={tol:g}"
                break
            shape_active = True
        n_iter = it + 1

        # Per-vertex sums over the candidate vertices: w_j = sum_i p_ij, ybar_j = sum_i p_ij y_i.
        k_used = p.shape[1]
        flat_inv = pairs.inv[:, :k_used].reshape(-1)
        flat_p = p.reshape(-1)
        n_cand = len(pairs.verts)
        wj = np.bincount(flat_inv, weights=flat_p, minlength=n_cand)
        rows = pairs.rows if k_used == pairs.k else pts
        weighted_rows = flat_p[:, None] * rows
        ybar = np.stack([np.bincount(flat_inv, weights=weighted_rows[:, c], minlength=n_cand)
                         for c in range(3)], axis=1)
        zv = (pairs.mean + (coef @ pairs.phi.reshape(n_factors, -1)).reshape(-1, 3)
              if n_factors else pairs.mean)

        # M-step, pose (Eq. 3).
        if pose != "none":
            if not aniso and pose_sd is None:
                scale, rot, trans = _procrustes(wj, ybar, zv, with_scale=pose == "similarity",
                                                fixed_scale=place_scale)
            else:
                xj = scale * zv @ rot.T + trans
                centre = (wj[:, None] * xj).sum(axis=0) / wj.sum()
                q = xj - centre
                # Jacobian of x_j in (dscale, omega, tau): [q | -[q]_x | I], (V, 3, 7)
                jac = np.zeros((n_cand, 3, 7))
                jac[:, :, 0] = q
                jac[:, 0, 2], jac[:, 0, 3] = q[:, 2], -q[:, 1]
                jac[:, 1, 1], jac[:, 1, 3] = -q[:, 2], q[:, 0]
                jac[:, 2, 1], jac[:, 2, 2] = q[:, 1], -q[:, 0]
                jac[:, :, 4:] = np.eye(3)
                if pose == "rigid":
                    jac = jac[:, :, 1:]
                resid = ybar - wj[:, None] * xj  # sum_i p_ij (y_i - x_j)
                if aniso:
                    wjac = jac + (eta - 1.0) * nv[:, :, None] * np.einsum("jc,jcq->jq", nv, jac)[:, None, :]
                else:
                    wjac = jac
                n_par = jac.shape[2]
                lhs = (jac * wj[:, None, None]).reshape(-1, n_par).T @ wjac.reshape(-1, n_par)
                rhs = wjac.reshape(-1, n_par).T @ resid.reshape(-1)
                if pose_sd is not None:
                    # Gaussian prior on the deviation from the initial placement: log scale,
                    # rotation vector, and the displacement of the model's centre (Eq. 6),
                    # linearised like the data term and weighted by s2 (the data term's 1/s2).
                    q0 = scale * rot @ centre0 + trans - centre
                    jac_p = np.zeros((7, 7))
                    jac_p[0, 0] = 1.0
                    jac_p[1:4, 1:4] = np.eye(3)
                    jac_p[4:, 0] = q0
                    jac_p[4:, 1:4] = -np.array([[0, -q0[2], q0[1]], [q0[2], 0, -q0[0]], [-q0[1], q0[0], 0]])
                    jac_p[4:, 4:] = np.eye(3)
                    r0 = pose_deviation(scale, rot, trans)
                    if pose == "rigid":
                        jac_p = jac_p[1:, 1:]
                        r0, prec = r0[1:], pose_precision[1:]
                    else:
                        prec = pose_precision
                    lhs += sigma2 * (jac_p.T * prec) @ jac_p
                    rhs -= sigma2 * (jac_p.T * prec) @ r0
                lhs += 1e-9 * np.trace(lhs) * np.eye(len(lhs))
                theta = np.linalg.solve(lhs, rhs)
                if pose == "rigid":
                    theta = np.concatenate([[0.0], theta])
                grow = 1.0 + theta[0]
                rot_d = rodrigues(theta[1:4])
                scale = scale * grow
                rot = rot_d @ rot
                trans = grow * rot_d @ (trans - centre) + centre + theta[4:]

        # M-step, shape (Eq. 4), in the base frame.
        if shape_active and n_factors > 0:
            ybar_b = ((ybar - wj[:, None] * trans) @ rot) / scale  # R^T (ybar - w t) / s
            sigma2_b = sigma2 / scale**2
            # only the vertices that carry weight (as s2 shrinks, a few per point)
            sel = np.flatnonzero(wj > 0.0)
            w_sel = wj[sel]
            phi = np.take(pairs.phi, sel, axis=1)  # (M, J, 3), C-contiguous
            r = ybar_b[sel] - w_sel[:, None] * pairs.mean[sel]
            b = (phi * np.sqrt(w_sel)[None, :, None]).reshape(n_factors, -1)
            lhs = b @ b.T
            if aniso:
                n_b = nv[sel] @ rot  # normals in the base frame, R^T n
                along = np.einsum("mjc,jc->mj", phi, n_b)
                c_mat = along * np.sqrt((eta - 1.0) * w_sel)[None, :]
                lhs += c_mat @ c_mat.T
                r = r + (eta - 1.0) * n_b * np.einsum("jc,jc->j", n_b, r)[:, None]
            rhs = phi.reshape(n_factors, -1) @ r.reshape(-1)
            lhs[np.diag_indices(n_factors)] += prior_weight * sigma2_b * cache.inv_var
            coef = _solve_shape(lhs, rhs, shape_bound)

        # New vertices; variance update on the same pairs (Eq. 4 of s2); refresh pairs if moved.
        x_new = scale * cache.shape(coef) @ rot.T + trans
        moved = float(np.sqrt(((x_new - x) ** 2).sum(axis=1).max()))
        x = x_new
        xv = x[pairs.verts]
        nv = normals_at(pairs.verts, x) if need_normals else None
        d = mahalanobis(pairs, xv, nv)
        if aniso and adaptive_anisotropy:
            # Tangential variance s2 and normal variance s2 / eta, both by EM (docstring).
            total = max(float(p.sum()), 1e-300)
            along2, full = parts["along"][:, :k_used], parts["full"][:, :k_used]
            normal_var = float((p * along2).sum()) / total
            tangent_var = float((p * (full - along2)).sum()) / (2.0 * total)
            eta = float(np.clip(tangent_var / max(normal_var, 1e-300), eta_floor, anisotropy))
            log_norm_const = 0.5 * np.log(eta)
            d = parts["full"] + (eta - 1.0) * parts["along"]
            # = tangent_var when eta is not clipped; the fixed-eta update when it is.
            sigma2 = (2.0 * tangent_var + eta * normal_var) / 3.0
            if sigma2 < sigma2_min:  # at the floor, eta's own update for the floored s2
                sigma2 = sigma2_min
                eta = float(np.clip(sigma2 / max(normal_var, 1e-300), eta_floor, anisotropy))
                log_norm_const = 0.5 * np.log(eta)
                d = parts["full"] + (eta - 1.0) * parts["along"]
        else:
            sigma2 = max(float((p * d[:, :k_used]).sum()) / (3.0 * max(p.sum(), 1e-300)), sigma2_min)
        k_wanted = neighbours_for(sigma2)
        if (icp or np.sqrt(((xv - pairs.x_ref) ** 2).sum(axis=1).max()) > refresh_dist
                or not pairs.k / 1.5 <= k_wanted <= pairs.k * 1.5):
            pairs = Pairs(x, k_wanted)
            xv = x[pairs.verts]
            nv = normals_at(pairs.verts, x) if need_normals else None
            d = mahalanobis(pairs, xv, nv)
        if moved < xtol and abs(objective[-1] - (e_next := energy(d, sigma2, coef, nv)[0])) <= (
                100 * tol * max(abs(e_next), 1.0)):
            if not shape_active:
                shape_active = True
                continue
            objective.append(e_next)
            converged, stop_reason = True, f"largest vertex move below xtol={xtol:g} mm"
            break

    pose_delta = np.eye(4)
    pose_delta[:3, :3] = scale * rot
    pose_delta[:3, 3] = trans
    residual = surface_distance(pts, x, faces, k=3, table=cache.table)
    return FitResult(coef=coef, pose=pose_delta @ cache.t0, vertices=x, objective=objective,
                     n_iter=n_iter, converged=converged, stop_reason=stop_reason,
                     residual_mm=float(residual.mean()), sigma2=float(sigma2),
                     anisotropy=float(eta), method=method,
                     pose_mode=pose, n_points=n_points,
                     elapsed_s=time.perf_counter() - start_time)
