"""Fit a shape model to sparse 3D points: GMM-based surface reconstruction with a shape prior.

Bernard, Salamanca, Thunberg, Tack, Jentsch, Lamecker, Zachow, Hertel, Goncalves, Gemmar:
"Shape-aware surface reconstruction from sparse 3D point-clouds", Medical Image Analysis 38
(2017). The model's surface points are the centres of a Gaussian mixture and the user's points
y_i (P, 3) are samples of it. With the base frame (model frame mapped by world_transform) ->
world similarity T(x) = s R x + t and the model x_j(a) = mean_j + Phi_j a (N vertices, M
factors), EM minimises the negative log posterior

    E(a, T, s2) = - sum_i log( (1 - w)/N sum_j g_j(y_i) + w/P ) + (lambda/2) a^T diag(var)^-1 a
                  [+ (1/2) |dev(T)|^2_pose_precision, the optional pose prior, Eq. 6]

    g_j(y) = sqrt(det W_j) (2 pi s2)^(-3/2) exp(-(y - T x_j)^T W_j (y - T x_j) / (2 s2))  # Eq. 1

with lambda = ``PRIOR_WEIGHT`` (1.4; 1 is the exact posterior of a shape inside the model's
span: real shapes are not, and a firmer prior resists the misfit; chosen on the tuning half,
issue 27), w the uniform outlier weight, W_j the precision of component j (the covariance strategy,
``covariance``): ``gmm-iso`` W_j = I; ``gmm-aniso`` W_j = eta n_j n_j^T + (I - n_j n_j^T), n_j
the current model normal (Eq. 5), so points slide along the surface instead of snapping to
vertices; ``icp`` hard nearest-vertex responsibilities with a point-to-plane metric (W_j as
gmm-aniso's with eta fixed at 100; Chen and Medioni 1992), the baseline, with the same
shape and pose priors.

Modules: ``em`` (:class:`GMMFitter`, the EM loop in scikit-learn's GaussianMixture style),
``covariance`` (the strategies), ``pose`` (similarity, Procrustes, Gauss-Newton pose step,
pose prior), ``snapshot`` (the immutable, content-keyed model snapshot), ``result``
(:class:`FitResult`), ``mirror`` (one contour's or parallel slices' mirror mode, which the fit
restarts from and the posterior counts), ``fit`` (:func:`fit_points`, the entry point).
Normals, closest points, Umeyama and rotations come from ``core.geometry.toolkit``.

E-step (Eq. 2): p_ij = g_j(y_i) / (sum_k g_k(y_i) + c), c = (N w) / (P (1 - w)), over each
point's K nearest vertices with K covering the vertices within 4.5 standard deviations (all
while s2 is large; issue 11: a fixed small K renormalised the responsibilities over the
near vertices, under-estimated s2 and trapped gmm-iso in ICP-like local minima about 1 mm
off). User normals (optional) multiply the weight by exp(kappa (u_i . n_j - 1)); this factor
is held fixed in the M-step (generalised EM) and is part of the objective.

M-step, with the responsibilities fixed, from per-vertex sums w_j = sum_i p_ij and
ybar_j = sum_i p_ij y_i (pairs with p_ij < 1e-4 left out):

- pose (Eq. 3): weighted Procrustes (Umeyama) for W_j = I without a pose prior; otherwise
  one Gauss-Newton step in (log scale, rotation vector, translation) with the Gaussian prior
  on the deviation from the placement (Eq. 6; ``pose_sd`` "auto" = 3 deg, 0.064 r, 0.03 in
  log scale, r the model size): it only matters in directions the points leave free;
- shape (Eq. 4), in the base frame with y'_i = R^T (y_i - t) / s and s2' = s2 / s^2:
  (sum_j w_j Phi_j^T W'_j Phi_j + lambda s2' diag(1/var)) a = sum_j Phi_j^T W'_j (ybar'_j - w_j mean_j);
  with ``prior_weight=0`` the minimum-norm solution inside a +-``coef_bound`` SD box;
- variance: s2 = sum_ij p_ij (y_i - x_j)^T W_j (y_i - x_j) / (3 sum_ij p_ij), floored at
  ``min_sigma**2`` ("auto": 0.003 r, i.e. 0.05 mm on a caudate, r = 15.6 mm; the former
  absolute 0.3 mm floor kept the prior's weight high and biased accurate data);
- adaptive anisotropy (gmm-aniso, default): the covariance s2 (I - n n^T) + (s2 / eta) n n^T
  has a tangential variance s2 and a normal variance s2 / eta; both are estimated (their EM
  updates) and eta is bounded below by a coverage rule, eta >= clip(20 g / r, 1, anisotropy)
  (g: mean distance from the initial model vertices to their nearest user point, r: the
  model's RMS radius; about 0.5 for two contours of the caudate, 0.1-0.15 for 6-12), and
  above by ``anisotropy``. With very few contours the tangential spread is mostly the gap
  between the contour and the vertices that happen to be nearest, not information, and a
  high eta keeps the shape from being dragged along the surface; with dense contours a fixed
  eta = 10 over-fits (4-11 % larger error than the fitted eta of 2-4).

Each step is accepted only if E decreases (else the step is halved, up to six times; issue
11 defect 3: one undamped Gauss-Newton pose step does not guarantee descent). Convergence:
relative change of E below ``tol``, or the largest vertex move below ``xtol`` ("auto":
6.4e-4 r, 0.01 mm on a caudate) with a small change of E. A warm start (``init``) starts from
the previous pose, coefficients, variance and eta; with an outlier term the variance is raised
to cover every point (a newly placed point is not an outlier). ``placement`` (default
``model.world_transform``) is the cold start and the centre of the pose prior (issue 11
defect 1). All length defaults are relative to the model size (defect 7), so fitting a
scaled problem gives the scaled result.

Correlated residuals (issue 27): after the fit, the lag-one correlation rho of neighbouring
points' normal residuals is measured (neighbours by foot point); a shape outside the model's
span leaves residuals that vary smoothly along a contour, so P points carry the information
of about P (1 - rho) / (1 + rho). When rho exceeds its standard error 1/sqrt(P), the fit is
run again from the same start with the shape prior's weight times (1 + rho) / (1 - rho)
(not the pose prior's: a wrong pose also leaves correlated residuals, and a tighter pose
prior held it there); ``FitResult.residual_correlation`` and ``.prior_inflation`` record it.
The normal variance of gmm-aniso is also divided by P - dof
rather than P (dof: the trace of the data part of the shape step), as the residuals are
what the shape was fitted to.

Placement: ``placement="points"`` moves the stored placement to the points' centre (the
GUI's *Place here*); when the points lie farther from the placed mean surface than the
population's spread plus two pose-prior SDs, ``FitResult.warnings`` says so, with the
distance and the remedy (``--placement``): the pose, not the shape, is then what is uncertain.

The reported ``pose`` is the full model frame -> world transform (the fitted similarity
composed with ``model.world_transform``).
"""

from core.geometry.toolkit import rodrigues as _rodrigues  # noqa: F401 (the former import path)
from core.geometry.toolkit import surface_distance
from core.reconstruction.em import FitState, GMMFitter
from core.reconstruction.fit import METHODS, MIN_POINTS, POSES, fit_points
from core.reconstruction.result import FitResult
from core.reconstruction.snapshot import ModelSnapshot, model_snapshot

__all__ = ["FitResult", "FitState", "GMMFitter", "METHODS", "MIN_POINTS", "ModelSnapshot",
           "POSES", "fit_points", "model_snapshot", "surface_distance"]
