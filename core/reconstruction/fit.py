"""``fit_points``: the reconstruction's entry point (input checks, relative defaults, result).

A thin wrapper around :class:`core.reconstruction.em.GMMFitter`; see the package docstring
for the method (Bernard et al., Medical Image Analysis 38, 2017).
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from core.geometry.toolkit import surface_distance, vertex_normals
from core.models.shape_model import ShapeModel
from core.reconstruction.covariance import make_covariance
from core.reconstruction.em import FitState, GMMFitter
from core.reconstruction.mirror import SliceStack, mirror_shift, slice_stack
from core.reconstruction.pose import PosePrior, Similarity
from core.reconstruction.result import FitResult
from core.reconstruction.snapshot import ModelSnapshot, model_snapshot

METHODS = ("gmm-aniso", "gmm-iso", "icp")
POSES = ("similarity", "rigid", "none")
MIN_POINTS = {"similarity": 3, "rigid": 3, "none": 1}

# Defaults relative to the model's size r (RMS radius of the mean shape; issue 11, defect 7),
# set where the former absolute ones were tuned: r = 15.6 mm for the demo caudate.
MIN_SIGMA_PER_SIZE = 0.003       # variance floor sqrt: 0.047 mm on the caudate
XTOL_PER_SIZE = 6.4e-4           # largest vertex move: 0.01 mm on the caudate
POSE_SD = (3.0, 0.064, 0.03)     # rotation deg, translation per size (1 mm), log scale
MAX_CORRELATION = 0.8            # cap of the residual correlation (inflation at most 9)
# The shape prior's weight lambda. 1 is the exact posterior when a shape lies in the model's
# span; shapes that are not (every real one) leave misfit the points pull the coefficients
# toward, and a firmer prior resists it. 1.4 was chosen on the tuning half only (issue 27,
# benchmarks/RESULTS.md "The shape prior's weight"): lower error in 14 of 16 end-to-end tuning
# cells and on both tuning kinds of the reconstruction families; an exactly in-span kind
# (the report's caudate) loses about 2 %.
PRIOR_WEIGHT = 1.4


def residual_correlation(points: np.ndarray, vertices: np.ndarray,
                         faces: np.ndarray) -> tuple[float, float]:
    """(correlation of the points' normal residuals with their nearest neighbour's, RMS
    normal residual in mm).

    r_i = n_j . (y_i - x_j) at the nearest fitted vertex j; the statistic is the lag-one
    autocorrelation sum_i a_i a_nn(i) / sum_i a_i^2 (a = r - mean r, nn(i) the nearest other
    point by its foot point y_i - r_i n_j, i.e. the contour neighbour). White noise gives ~0
    (standard error 1/sqrt(P)); a shape the model cannot reach leaves residuals that vary
    smoothly along the contours.
    """
    if len(points) < 4:
        return 0.0, 0.0
    nearest = cKDTree(vertices).query(points)[1]
    normals = vertex_normals(vertices, faces)[nearest]
    resid = np.einsum("pc,pc->p", points - vertices[nearest], normals)
    # neighbours among the foot points y - r n: choosing them among the points themselves
    # would pair points with similar residuals (the residual adds to the distance), a bias
    # of +0.4 for white noise at 0.4 mm spacing
    foot = points - resid[:, None] * normals
    neighbour = cKDTree(foot).query(foot, k=2)[1][:, 1]
    centred = resid - resid.mean()
    rho = float(centred @ centred[neighbour] / max(float(centred @ centred), 1e-300))
    return rho, float(np.sqrt(np.mean(resid ** 2)))


def information_inflation(rho: float, n_points: int) -> tuple[float, float]:
    """(shrunk correlation, inflation (1 + rho) / (1 - rho)): the factor by which P points
    with AR(1)-correlated residuals over-count their information (effective count
    P (1 - rho) / (1 + rho)). ``rho`` is shrunk by one standard error, 1/sqrt(P), so white
    noise is left alone."""
    shrunk = float(np.clip(rho - 1.0 / np.sqrt(max(n_points, 1)), 0.0, MAX_CORRELATION))
    return shrunk, (1.0 + shrunk) / (1.0 - shrunk)


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


def _checked_transform(matrix, name: str) -> np.ndarray:
    t = np.asarray(matrix, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise ValueError(f"{name} must be a finite 4x4 transform, got shape {t.shape}")
    if abs(np.linalg.det(t[:3, :3])) < 1e-12:
        raise ValueError(f"{name} is singular (its 3x3 part has determinant 0)")
    return t


def _pose_prior(pose_sd, pose_spread: float, snap: ModelSnapshot,
                place: Similarity) -> PosePrior | None:
    if not pose_spread >= 0:
        raise ValueError(f"pose_spread must be >= 0, got {pose_spread}")
    # ICP too (issue 27): point-to-plane ICP leaves sliding along the surface and the scale
    # nearly free on two parallel contours; without the prior its pose drifted (scale up to
    # 1.3, centre 5-7 mm along a thin tube) where gmm-aniso's stayed put
    if pose_sd is None or pose_spread == 0:
        return None
    if isinstance(pose_sd, str):
        if pose_sd != "auto":
            raise ValueError(f"pose_sd must be 'auto', None or (deg, mm, log scale), got {pose_sd!r}")
        pose_sd = (POSE_SD[0], POSE_SD[1] * snap.size, POSE_SD[2])
    rot_sd, trans_sd, log_scale_sd = (float(v) * pose_spread for v in pose_sd)
    return PosePrior.from_sd(place, snap.centre, rot_sd, trans_sd, log_scale_sd)


def placement_at(model: ShapeModel, target) -> np.ndarray:
    """The model's stored placement moved so its mean shape's centre is at ``target`` (world
    mm): what the GUI's *Place here* and ``--placement x,y,z`` do."""
    placement = np.array(model.world_transform, dtype=np.float64)
    placement[:3, 3] += np.asarray(target, dtype=np.float64) - model.world_instance().mean(axis=0)
    return placement


def placement_warnings(snap: ModelSnapshot, points: np.ndarray, place: Similarity,
                       trans_sd: float) -> list[str]:
    """Warn when the points are far from the placed model: the pose, not the shape, is then
    what is uncertain, and the pose prior around the placement would hold the fit off.

    Far: the points' mean distance to the placed mean surface exceeds twice the model's RMS
    per-vertex prior SD plus two pose-prior translation SDs (what a correctly placed shape
    of the population leaves)."""
    x0 = place.apply(snap.mean)
    gap = float(surface_distance(points, x0, snap.faces, k=3, table=snap.table).mean())
    spread = float(np.sqrt((snap.coef_var[:, None] * (snap.factors ** 2).sum(axis=2)).sum(axis=0).mean())) \
        if snap.n_factors else 0.0
    if gap <= 2.0 * spread + 2.0 * trans_sd:
        return []
    offset = float(np.linalg.norm(points.mean(axis=0) - place.apply(snap.centre)))
    return [f"the points lie {gap:.1f} mm from the placed model on average (their centre is "
            f"{offset:.1f} mm from the model's; a placed shape of this model is within about "
            f"{2.0 * spread + 2.0 * trans_sd:.1f} mm): the placement, not the shape, is what is "
            "uncertain. Place the model at the points (GUI: Place here; CLI: --placement x,y,z "
            "or --placement points) and fit again"]


def _relative(value, per_size: float, size: float, name: str) -> float:
    if isinstance(value, str):
        if value != "auto":
            raise ValueError(f"{name} must be a number (mm) or 'auto', got {value!r}")
        return per_size * size
    return float(value)


def fit_points(model: ShapeModel, points: np.ndarray, normals: np.ndarray | None = None, *,
               placement: np.ndarray | str | None = None, method: str = "gmm-aniso",
               pose: str = "similarity", prior_weight: float = PRIOR_WEIGHT,
               init: FitResult | None = None, max_iter: int = 100, tol: float = 1e-5,
               xtol: float | str = "auto", outlier_weight: float = 0.0, anisotropy: float = 10.0,
               normal_weight: float = 2.0, n_neighbors: int = 6, max_neighbors: int | None = None,
               min_sigma: float | str = "auto", adaptive_anisotropy: bool = True,
               max_distance_factor: float = 1.0, pose_first: bool = False,
               pose_sd: tuple[float, float, float] | str | None = "auto",
               pose_spread: float = 1.0, coef_bound: float = 5.0,
               correlated_residuals: bool = True, overrelax: bool = True,
               mirror_restart: bool = True,
               callback: Callable[[int, float], None] | None = None) -> FitResult:
    """Fit ``model`` to user points by EM on the model-centred Gaussian mixture.

    Parameters
    ----------
    model : ShapeModel
        The model; its ``world_transform`` is the default placement.
    points : (P, 3) array
        User points in world coordinates (mm).
    normals : (P, 3) array, optional
        Outward unit normals at the points (rows of zeros: unknown). Used in the E-step.
    placement : (4, 4) array or "points", optional
        The pose the user set (model frame -> world, e.g. the GUI's *Place here*): the cold
        start, the pose of ``pose="none"`` (and the scale of ``"rigid"``), and the centre of
        the pose prior. Default: ``model.world_transform``. "points": the stored placement
        moved to the points' centre (:func:`placement_at`). When the points lie far from the
        placed model, ``FitResult.warnings`` says so, with the distance and the remedy.
    method : {"gmm-aniso", "gmm-iso", "icp"}
        Anisotropic GMM, isotropic GMM, or ICP with the same prior.
    pose : {"similarity", "rigid", "none"}
        Which world transform is estimated on top of the placement.
    prior_weight : float
        lambda, the weight of the Gaussian shape prior a ~ N(0, diag(coef_var)) (default
        :data:`PRIOR_WEIGHT`, 1.4). 0: no prior; the coefficients are then the minimum-norm
        least-squares ones, bounded to +-``coef_bound`` standard deviations.
    init : FitResult, optional
        Warm start (previous fit of the same model): its pose, coefficients, variance, eta.
    max_iter, tol, xtol : int, float, float or "auto"
        Iteration limit; relative objective change; largest vertex move (mm; "auto":
        6.4e-4 of the model size r, the RMS radius of its mean shape: 0.01 mm on a caudate).
    outlier_weight : float
        w in [0, 1), the weight of the uniform outlier component (ignored by ICP).
    anisotropy : float
        eta >= 1, normal / tangential precision ratio of the anisotropic components (the
        upper bound of eta with ``adaptive_anisotropy``).
    adaptive_anisotropy : bool
        gmm-aniso: estimate eta with the variance in each M-step, bounded below by the
        coverage rule (package docstring) and above by ``anisotropy``. False: eta fixed.
    normal_weight : float
        kappa >= 0, weight of the user-normal agreement exp(kappa (u . n - 1)).
    n_neighbors, max_neighbors : int, int or None
        K, model vertices considered per user point in the E-step: at least ``n_neighbors``,
        about those within 4.5 SD of the points, at most ``max_neighbors`` (None: all).
    min_sigma : float or "auto"
        Floor of the GMM standard deviation (mm); "auto": 0.003 r (0.05 mm on a caudate);
        at least the model's noise variance ``model.info["noise_variance"]`` (statismo).
    pose_sd : (rotation deg, translation mm, log scale), "auto" or None
        Standard deviations of a Gaussian prior on the pose's deviation from the placement
        (also on a warm start): it keeps an underdetermined fit (one or two contours) from
        sliding or scaling away, and is outweighed by the data wherever the points constrain
        the pose. "auto": (3 deg, 0.064 r, 0.03), i.e. 1 mm on a caudate. None: no prior.
        All methods (the pose step is then the Gauss-Newton one, also for gmm-iso; ICP's
        always is, its metric being point-to-plane).
    pose_spread : float
        Multiplies the three standard deviations of ``pose_sd`` (the Fit panel's "pose prior
        spread"); 0 removes the pose prior.
    coef_bound : float
        The box |a_m| <= coef_bound sqrt(coef_var_m) used when ``prior_weight`` is 0.
    pose_first : bool
        On a cold start, run pose-only EM to convergence before fitting the shape.
    correlated_residuals : bool
        After the fit, measure the correlation rho of neighbouring points' normal residuals
        (:func:`residual_correlation`): a shape outside the model's span leaves residuals that
        vary smoothly along the contours, so the P points carry the information of only
        P (1 - rho) / (1 + rho) independent ones. When rho exceeds its standard error, the fit
        is refined (warm start) with the shape prior's weight multiplied by
        (1 + rho) / (1 - rho) (issue 27: the untempered fit trusted two parallel contours too
        much, 4-20 % worse than a more regularised CPD); the pose prior keeps its weight.
        Off: the plain fit.
    overrelax : bool
        Adaptive over-relaxation of the EM steps (Salakhutdinov & Roweis 2003; gmm-aniso and
        gmm-iso, not ICP): each step to the M-step's pose and coefficients is lengthened
        while that keeps lowering the objective. Plain EM crawls along what one or two
        contours hardly determine and stopped short of its optimum. False: plain EM.
    mirror_restart : bool
        Points in 2-3 parallel slices of one view (``core.reconstruction.mirror``) cannot
        tell which side of their middle plane the shape's centre lies on: the fit is run a
        second time from its mirror mode (the fitted pose moved across that plane, the
        mean shape) under the same priors, and the fit with the lower objective is kept
        (``FitResult.mirror_restart``: "fit" or "mirror"; "" when not tried). A warm start
        from a fit of the same slices (``init.mirror_key``, the ``SliceStack.key`` of
        ``core.reconstruction.mirror``) is not restarted: the live refit looks at the mirror
        once per new slice and each time the points double, not once per point. Not for one
        contour, nor for ICP: on the tuning half those lost as often as they won (issue 27).
    max_distance_factor : float
        Points farther than this many model diagonals from the model's box are refused.
    callback : callable(iteration, objective), optional
        Called once per iteration; may raise ``core.runtime.progress.Cancelled``.

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
    snap = model_snapshot(model)
    t0_inv = np.linalg.inv(snap.t0)
    source = "stored" if placement is None else "given"
    if isinstance(placement, str):
        if placement != "points":
            raise ValueError(f"placement must be a 4x4 matrix, None or 'points', got {placement!r}")
        placement, source = placement_at(model, pts.mean(axis=0)), "points"
    place = Similarity.identity() if placement is None else Similarity.from_matrix(
        _checked_transform(placement, "placement") @ t0_inv)
    floor = _relative(min_sigma, MIN_SIGMA_PER_SIZE, snap.size, "min_sigma")
    xtol_mm = _relative(xtol, XTOL_PER_SIZE, snap.size, "xtol")

    def make_fitter() -> GMMFitter:
        return GMMFitter(
            make_covariance(method, anisotropy, adaptive_anisotropy), pose=pose,
            prior_weight=prior_weight, coef_bound=float(coef_bound) * np.sqrt(snap.coef_var),
            pose_prior=_pose_prior(pose_sd, pose_spread, snap, place),
            outlier_weight=outlier_weight, normal_weight=normal_weight,
            sigma2_min=max(floor**2, float(model.info.get("noise_variance", 0.0) or 0.0)),
            max_iter=max_iter, tol=tol, xtol=xtol_mm,
            n_neighbors=n_neighbors, max_neighbors=max_neighbors, pose_first=pose_first,
            overrelax=overrelax, callback=callback)

    def run(f: GMMFitter, state: FitState | None) -> GMMFitter:
        return f.fit(snap, pts, user_normals, init=state, placement=place)

    fitter = make_fitter()
    start = None
    if init is not None:
        start = FitState(np.asarray(init.coef, dtype=np.float64),
                         Similarity.from_matrix(np.asarray(init.pose, dtype=np.float64) @ t0_inv),
                         float(init.sigma2), float(init.anisotropy))
    _check_extent(pts, (start.pose if start else place).apply(
        snap.shape(start.coef if start else np.zeros(snap.n_factors))), max_distance_factor)
    warnings = [] if start is not None or pose == "none" else placement_warnings(
        snap, pts, place, POSE_SD[1] * snap.size * pose_spread)
    run(fitter, start)
    # not ICP: its hard pairs' objectives picked the worse start as often as the better
    # (tuning families end to end, 2 parallel contours: concave 0.171 -> 0.174 mm)
    stack = slice_stack(pts) if mirror_restart and pose != "none" and method != "icp" else None
    stack = stack if stack is not None and stack.n_planes >= 2 else None
    restart, gap = "", float("nan")
    # a warm start from a fit that looked at these slices' mirror already stays on its side
    if stack is not None and (init is None or getattr(init, "mirror_key", None) != stack.key):
        fitter, start, restart, gap = _restart_from_mirror(fitter, start, make_fitter, run,
                                                           stack, xtol_mm)
    rho, inflation = 0.0, 1.0
    if correlated_residuals and snap.n_factors > 0:
        rho, inflation = _tempered_refit(fitter, start, run, prior_weight)
    result = _result(fitter, snap, model, method, pose, place, start_time)
    result.residual_correlation, result.prior_inflation = rho, inflation
    result.prior_weight = float(prior_weight)
    result.warnings, result.placement_source = warnings, source
    result.mirror_restart, result.mirror_gap = restart, gap
    result.mirror_key = None if stack is None else stack.key
    return result


#: ``run(fitter, start)``: fits the call's points from ``start`` (``fit_points``' closure).
_Run = Callable[[GMMFitter, "FitState | None"], GMMFitter]


def _restart_from_mirror(fitter: GMMFitter, start: FitState | None,
                         make_fitter: Callable[[], GMMFitter], run: _Run, stack: SliceStack,
                         xtol_mm: float) -> tuple[GMMFitter, FitState | None, str, float]:
    """The fit of parallel slices run again from its mirror mode (``mirror_restart`` of
    :func:`fit_points`; ``run(fitter, start)`` fits the points): (the fitter with the lower
    objective, its start, "fit" or "mirror", and the other start's objective minus the kept
    one's, >= 0; "" and NaN when the mirror mode is within ``xtol_mm`` of the fit)."""
    shift = mirror_shift(fitter.vertices_, stack)
    if np.linalg.norm(shift) <= xtol_mm:
        return fitter, start, "", float("nan")
    # the same objective (same priors about the same placement) from the mirror mode: the
    # fitted pose moved across the slices' middle plane, the mean shape, the cold variance
    snap, fitted = fitter.snap_, fitter.state_.pose
    mirror_start = FitState(np.zeros(snap.n_factors),
                            Similarity(fitted.scale, fitted.rot, fitted.trans + shift),
                            float("nan"), float("nan"))
    other = run(make_fitter(), mirror_start)
    other.n_iter_ += fitter.n_iter_
    gap = float(abs(other.objective_[-1] - fitter.objective_[-1]))
    if other.objective_[-1] < fitter.objective_[-1]:
        return other, mirror_start, "mirror", gap
    return fitter, start, "fit", gap


def _tempered_refit(fitter: GMMFitter, start: FitState | None, run: _Run,
                    prior_weight: float) -> tuple[float, float]:
    """The refit with the shape prior tempered by the residuals' correlation
    (``correlated_residuals`` of :func:`fit_points`), in place: (rho, the inflation)."""
    snap, pts = fitter.snap_, fitter.points_
    rho, rms = residual_correlation(pts, fitter.vertices_, snap.faces)
    shrunk, inflation = information_inflation(rho, len(pts))
    if rms <= 2.0 * np.sqrt(fitter.sigma2_min):  # on the surface to the floor: no misfit
        shrunk, inflation = 0.0, 1.0
    if shrunk > 0.0:  # the tempered posterior, from the plain fit's state
        # The shape prior only. A wrong pose leaves smoothly varying residuals too, so
        # tightening the pose prior by the same factor locked in the very pose error the
        # correlation came from (issue 27: a thin tube turned from the model's frame, 2
        # parallel contours, 1.36 -> 0.87 mm without; from the stored placement, 10 mm
        # off, the report kinds' mean error 4.7 against 9.5 mm with 2 parallel contours).
        fitter.prior_weight = prior_weight * inflation
        # the tempered objective from the same start: its record is non-increasing
        n_iter = fitter.n_iter_
        run(fitter, start)
        fitter.n_iter_ += n_iter
    return rho, inflation


def _result(fitter: GMMFitter, snap: ModelSnapshot, model: ShapeModel, method: str, pose: str,
            place: Similarity, start_time: float) -> FitResult:
    state, x = fitter.state_, fitter.vertices_
    residual = surface_distance(fitter.points_, x, snap.faces, k=3, table=snap.table)
    return FitResult(
        coef=state.coef, pose=state.pose.matrix() @ snap.t0, vertices=x,
        objective=list(fitter.objective_), n_iter=fitter.n_iter_, converged=fitter.converged_,
        stop_reason=fitter.stop_reason_, residual_mm=float(residual.mean()),
        sigma2=float(state.sigma2), anisotropy=float(state.eta), method=method, pose_mode=pose,
        n_points=len(fitter.points_), elapsed_s=time.perf_counter() - start_time,
        placement=place.matrix() @ snap.t0, model_size_mm=snap.size,
        coef_sd=np.sqrt(snap.coef_var), coef_precision=fitter.precision_,
        centre_offset_mm=state.pose.apply(snap.centre) - place.apply(snap.centre))
