"""EM for the model-centred Gaussian mixture with a shape prior (and a pose prior).

Bernard et al., "Shape-aware surface reconstruction from sparse 3D point-clouds", Medical
Image Analysis 38 (2017). :class:`GMMFitter` follows scikit-learn's ``GaussianMixture``: the
options are given to ``__init__``, ``fit`` alternates :meth:`GMMFitter._e_step` and
:meth:`GMMFitter._m_step` and stores the result in attributes ending in ``_``
(``state_``, ``objective_``, ``n_iter_``, ``converged_``); ``warm_start=True`` starts the
next ``fit`` from the last state. The covariance of the components is a strategy
(``core.reconstruction.covariance``), the pose step and the pose prior live in
``core.reconstruction.pose``.

What the fitter guarantees, and why (issue 11):

- the E-step's sum over the model vertices is truncated to each point's K nearest vertices,
  with K covering the vertices within ~4.5 standard deviations (all of them while s2 is
  large: a truncation to a fixed K renormalises the responsibilities over the near vertices
  only, underestimates s2, and the isotropic fit then falls into ICP-like local minima);
- the objective never increases: a step that would raise it is halved (pose, coefficients
  and variance interpolated between the old and the new state) until it decreases, and if
  six halvings do not help the fit stops ("no further decrease");
- the cold-start variance is the mean squared distance over all point/vertex pairs (CPD's
  initialisation), so the first iterations see the whole model;
- EM is over-relaxed (Salakhutdinov & Roweis, "Adaptive overrelaxed bound optimization
  methods", ICML 2003): the step to the M-step's pose and coefficients is taken ``relax``
  times (``relax`` grows by :data:`RELAX_GROWTH` after every step that lowers the
  objective, up to :data:`MAX_RELAX`, and falls back to 1 and the plain step when one does
  not). Plain EM crawls along the directions the points hardly determine (the pose against
  the shape on one or two contours): it stopped on its tolerance while still moving (issue
  27: two parallel contours, converged fits 10 % closer to the truth on the tuning kinds).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from core.geometry.toolkit import vertex_normals
from core.reconstruction.pose import PosePrior, Similarity, gauss_newton_step, procrustes
from core.reconstruction.snapshot import ModelSnapshot

COVERAGE_GAIN = 20.0   # eta floor = clip(gain * gap / radius, 1, cap), module docstring of __init__
_DROP = 1e-4           # responsibilities below this are left out of the M-step
_HALVINGS = 6
MAX_RELAX = 16.0       # largest over-relaxation of a step (module docstring)
RELAX_GROWTH = 1.5     # its factor after a step that lowered the objective


@dataclass(frozen=True)
class FitState:
    """The parameters EM estimates."""

    coef: np.ndarray
    pose: Similarity      # base frame -> world
    sigma2: float
    eta: float


class _Pairs:
    """Candidate pairs (user point, K nearest vertices), refreshed when the vertices move."""

    def __init__(self, snap: ModelSnapshot, x_world: np.ndarray, pts: np.ndarray, k: int):
        self.k = k
        if k >= snap.n_vertices:  # dense: every vertex
            near = np.broadcast_to(np.arange(snap.n_vertices), (len(pts), snap.n_vertices))
        else:
            near = np.asarray(cKDTree(x_world).query(pts, k=k)[1]).reshape(len(pts), k)
        self.verts, inv = np.unique(near, return_inverse=True)  # V candidate vertices
        self.inv = inv.reshape(len(pts), k)  # (P, K) into verts
        self.x_ref = x_world[self.verts]
        self.phi = np.take(snap.factors, self.verts, axis=1)  # (M, V, 3), C-contiguous
        self.mean = snap.mean[self.verts]
        self.rows = np.repeat(pts, k, axis=0)  # (P K, 3)


@dataclass
class _Evaluation:
    """An E-step: the objective at a state and the responsibilities (P, K')."""

    objective: float
    resp: np.ndarray
    parts: dict
    x: np.ndarray           # world vertices (N, 3)
    nv: np.ndarray | None   # normals of the candidate vertices


class GMMFitter:
    """EM fit of a shape model (a :class:`ModelSnapshot`) to points.

    Parameters
    ----------
    covariance : Isotropic, Anisotropic or NearestPoint (``core.reconstruction.covariance``)
    pose : {"similarity", "rigid", "none"}
    prior_weight : lambda of the shape prior; 0 with ``coef_bound`` (see ``fit_points``)
    coef_bound : (M,) box on the coefficients, used when ``prior_weight`` is 0
    pose_prior : PosePrior or None
    outlier_weight, normal_weight : w and kappa of ``fit_points``
    sigma2_min : variance floor (mm^2)
    max_iter, tol, xtol : iteration limit, relative objective change, largest vertex move (mm)
    n_neighbors, max_neighbors : bounds of K in the E-step (None: all vertices)
    pose_first : cold start: pose-only EM to convergence first
    warm_start : start ``fit`` from the previous ``state_`` when no ``init`` is given
    overrelax : adaptive over-relaxation of the EM steps (module docstring; not for ICP);
        False: plain EM
    callback : callable(iteration, objective), may raise ``core.runtime.progress.Cancelled``
    """

    state_: FitState        # set by fit
    _k_floor: int = 0       # K does not shrink below this in the current fit (_accept)
    _last_geometry: tuple   # (pairs, sigma2, eta, geometry) of the last variance step

    def __init__(self, covariance, *, pose: str = "similarity", prior_weight: float = 1.0,
                 coef_bound: np.ndarray | None = None, pose_prior: PosePrior | None = None,
                 outlier_weight: float = 0.0, normal_weight: float = 2.0,
                 sigma2_min: float = 0.0, max_iter: int = 100, tol: float = 1e-5,
                 xtol: float = 1e-2, n_neighbors: int = 6, max_neighbors: int | None = None,
                 pose_first: bool = False, warm_start: bool = False, dof_correction: bool = True,
                 overrelax: bool = True,
                 callback: Callable[[int, float], None] | None = None):
        self.covariance = covariance
        self.pose = pose
        self.prior_weight = prior_weight
        self.coef_bound = coef_bound
        self.pose_prior = pose_prior
        self.outlier_weight = 0.0 if covariance.hard else outlier_weight
        self.normal_weight = normal_weight
        self.sigma2_min = sigma2_min
        self.max_iter, self.tol, self.xtol = max_iter, tol, xtol
        self.n_neighbors, self.max_neighbors = n_neighbors, max_neighbors
        self.pose_first = pose_first
        self.warm_start = warm_start
        self.dof_correction = dof_correction
        # not ICP: its hard nearest-vertex pairs jump under a lengthened step (tuning families
        # end to end, 1 mm label maps, 2 parallel contours: 0.483 -> 0.531 mm)
        self.overrelax = overrelax and not covariance.hard
        self.callback = callback

    # -- set-up -----------------------------------------------------------------------------
    def _prepare(self, snap: ModelSnapshot, points: np.ndarray, normals: np.ndarray | None) -> None:
        self.snap_ = snap
        self.points_ = points
        hard = self.covariance.hard
        self.user_normals_ = normals if normals is not None and self.normal_weight > 0 and not hard else None
        n, p, w = snap.n_vertices, len(points), self.outlier_weight
        self.log_c_ = np.log(n * w / ((1.0 - w) * p)) if w > 0 else -np.inf
        self.need_normals_ = self.covariance.needs_normals or self.user_normals_ is not None

    def _neighbours_for(self, sigma2: float) -> int:
        """K covers the vertices within the strategy's ``truncation_sd`` standard deviations."""
        n = self.snap_.n_vertices
        cov = self.covariance
        if cov.hard:
            return 1
        per_vertex = 0.866 * self.snap_.edge_length**2  # area per vertex of a regular mesh
        wanted = int(np.ceil(np.pi * cov.truncation_sd**2 * sigma2 / per_vertex))
        cap = self.max_neighbors if self.max_neighbors is not None else cov.max_neighbors
        cap = n if cap is None else min(cap, n)
        return int(min(max(min(self.n_neighbors, n), wanted), cap))

    def _initial_state(self, start: FitState | None, place: Similarity):
        """(state, world vertices): a cold start at the placement, or ``start``."""
        snap, pts = self.snap_, self.points_
        if start is None:
            coef, pose = np.zeros(snap.n_factors), place
        else:
            coef, pose = np.asarray(start.coef, dtype=np.float64).copy(), start.pose
        if self.pose == "none":
            pose = place
        elif self.pose == "rigid":
            pose = Similarity(place.scale, pose.rot, pose.trans)
        x = pose.apply(snap.shape(coef))
        eta = self._eta_floor(x)
        if start is not None and np.isfinite(start.eta):
            eta = float(np.clip(start.eta, eta, getattr(self.covariance, "cap", 1.0)))
        if start is not None and np.isfinite(start.sigma2) and start.sigma2 > 0:
            sigma2 = float(start.sigma2)
            if self.outlier_weight > 0:  # a newly placed point must not start as an outlier
                sigma2 = max(sigma2, float(cKDTree(x).query(pts)[0].max()) ** 2 / 3.0)
        elif self.covariance.global_start:  # all pairs: mean |y|^2 + mean |x|^2 - 2 ybar . xbar
            sigma2 = float((pts**2).sum(axis=1).mean() + (x**2).sum(axis=1).mean()
                           - 2.0 * pts.mean(axis=0) @ x.mean(axis=0)) / 3.0
        else:  # the near vertices only, at least the farthest point's nearest distance
            near = np.asarray(cKDTree(x).query(pts, k=min(self.n_neighbors, len(x)))[0])
            near = near.reshape(len(pts), -1)
            sigma2 = max(float((near**2).mean()), float((near[:, 0] ** 2).max())) / 3.0
        return FitState(coef, pose, max(sigma2, self.sigma2_min), eta), x

    def _eta_floor(self, x: np.ndarray) -> float:
        """Coverage rule for the adaptive eta: gap to the nearest point over the RMS radius."""
        cov = self.covariance
        if not cov.adaptive:
            return getattr(cov, "cap", 1.0)
        gap = cKDTree(self.points_).query(x)[0]
        radius = float(np.sqrt(((x - x.mean(axis=0)) ** 2).sum(axis=1).mean()))
        cov.floor = float(np.clip(COVERAGE_GAIN * float(gap.mean()) / max(radius, 1e-300),
                                  1.0, cov.cap))
        return cov.floor

    # -- E-step -----------------------------------------------------------------------------
    def _geometry(self, state: FitState, pairs: _Pairs) -> tuple[np.ndarray, np.ndarray | None, dict]:
        """World vertices, candidate normals and pair distances at ``state``."""
        snap = self.snap_
        x = state.pose.apply(snap.shape(state.coef))
        nv = (vertex_normals(x, snap.faces, at=pairs.verts, table=snap.table_pad)
              if self.need_normals_ else None)
        diff = self.points_[:, None, :] - x[pairs.verts][pairs.inv]  # (P, K, 3)
        parts = self.covariance.distances(diff, None if nv is None else nv[pairs.inv], state.eta)
        return x, nv, parts

    def _e_step(self, state: FitState, pairs: _Pairs, geometry=None) -> _Evaluation:
        """Objective (Eq. 1 plus the priors) and responsibilities (Eq. 2) at ``state``."""
        x, nv, parts = self._geometry(state, pairs) if geometry is None else geometry
        sigma2, w = state.sigma2, self.outlier_weight
        logits = -parts["d"] / (2.0 * sigma2)
        if self.user_normals_ is not None:  # agreement of the user's and the model's normals
            assert nv is not None  # need_normals_ is set when the user gives normals
            logits = logits + self.normal_weight * (
                np.einsum("pc,pkc->pk", self.user_normals_, nv[pairs.inv]) - 1.0)
        if self.covariance.hard:
            logits = logits[:, :1]
        top = logits.max(axis=1, keepdims=True)
        ex = np.exp(logits - top)
        total = ex.sum(axis=1, keepdims=True)
        log_norm = 0.5 * np.log(state.eta) - 1.5 * np.log(2.0 * np.pi * sigma2)
        comp = (np.log(1.0 - w) - np.log(self.snap_.n_vertices) + log_norm + top[:, 0]
                + np.log(total[:, 0]))
        if w > 0:
            loglik = np.logaddexp(comp, np.log(w / len(self.points_)))
            total = total + np.exp(np.minimum(self.log_c_ - log_norm - top, 700.0))
        else:
            loglik = comp
        objective = float(-loglik.sum()) + self._prior_energy(state)
        return _Evaluation(objective, ex / total, parts, x, nv)

    def _prior_energy(self, state: FitState) -> float:
        coef = state.coef
        energy = 0.5 * self.prior_weight * float(coef @ (self.snap_.inv_var * coef))
        if self.pose_prior is not None and self.pose != "none":
            energy += self.pose_prior.energy(state.pose)
        return energy

    # -- M-step -----------------------------------------------------------------------------
    def _vertex_sums(self, ev: _Evaluation, pairs: _Pairs):
        """w_j = sum_i p_ij and ybar_j = sum_i p_ij y_i over the candidate vertices."""
        resp = np.where(ev.resp < _DROP, 0.0, ev.resp)  # negligible pairs: a smaller M-step
        k_used = resp.shape[1]
        flat_inv = pairs.inv[:, :k_used].reshape(-1)
        flat_p = resp.reshape(-1)
        n_cand = len(pairs.verts)
        wj = np.bincount(flat_inv, weights=flat_p, minlength=n_cand)
        rows = pairs.rows if k_used == pairs.k else self.points_
        weighted = flat_p[:, None] * rows
        ybar = np.stack([np.bincount(flat_inv, weights=weighted[:, c], minlength=n_cand)
                         for c in range(3)], axis=1)
        return resp, wj, ybar

    def _m_step(self, state: FitState, ev: _Evaluation, pairs: _Pairs,
                shape_active: bool) -> FitState:
        """New pose (Eq. 3), coefficients (Eq. 4) and variance from the responsibilities."""
        resp, wj, ybar = self._vertex_sums(ev, pairs)
        n_factors = self.snap_.n_factors
        zv = pairs.mean + (state.coef @ pairs.phi.reshape(n_factors, -1)).reshape(-1, 3) \
            if n_factors else pairs.mean
        pose = self._pose_step(state, ev, wj, ybar, zv)
        coef = state.coef
        if shape_active and n_factors > 0:
            coef = self._shape_step(state, pose, ev, pairs, wj, ybar)
        return self._variance_step(replace(state, pose=pose, coef=coef), resp, pairs)[0]

    def _pose_step(self, state: FitState, ev: _Evaluation, wj, ybar, zv) -> Similarity:
        if self.pose == "none":
            return state.pose
        iso = not self.covariance.needs_normals
        if iso and self.pose_prior is None:
            return procrustes(wj, ybar, zv, with_scale=self.pose == "similarity",
                              fixed_scale=state.pose.scale)
        nv = ev.nv if self.covariance.needs_normals else None
        return gauss_newton_step(state.pose, wj, ybar, state.pose.apply(zv), nv, state.eta,
                                 state.sigma2, self.pose_prior, rigid=self.pose == "rigid")

    def _shape_step(self, state: FitState, pose: Similarity, ev: _Evaluation, pairs: _Pairs,
                    wj, ybar) -> np.ndarray:
        """Eq. 4 in the base frame: y' = R^T (y - t) / s, s2' = s2 / s^2."""
        n_factors = self.snap_.n_factors
        ybar_b = ((ybar - wj[:, None] * pose.trans) @ pose.rot) / pose.scale
        sigma2_b = state.sigma2 / pose.scale**2
        sel = np.flatnonzero(wj > 0.0)  # only the vertices that carry weight
        w_sel = wj[sel]
        phi = np.take(pairs.phi, sel, axis=1)  # (M, J, 3)
        r = ybar_b[sel] - w_sel[:, None] * pairs.mean[sel]
        b = (phi * np.sqrt(w_sel)[None, :, None]).reshape(n_factors, -1)
        lhs = b @ b.T
        if self.covariance.needs_normals:
            assert ev.nv is not None  # need_normals_ is set when the covariance needs them
            n_b = ev.nv[sel] @ pose.rot  # normals in the base frame, R^T n
            along = np.einsum("mjc,jc->mj", phi, n_b)
            c_mat = along * np.sqrt((state.eta - 1.0) * w_sel)[None, :]
            lhs += c_mat @ c_mat.T
            r = r + (state.eta - 1.0) * n_b * np.einsum("jc,jc->j", n_b, r)[:, None]
        rhs = phi.reshape(n_factors, -1) @ r.reshape(-1)
        data = lhs.copy() if self.dof_correction else None
        lhs[np.diag_indices(n_factors)] += self.prior_weight * sigma2_b * self.snap_.inv_var
        self.precision_ = lhs / sigma2_b  # posterior precision of the coefficients (Laplace)
        if data is not None:  # effective number of parameters the points determine
            self.dof_ = float(np.trace(np.linalg.solve(lhs, data)))
        return solve_shape(lhs, rhs, None if self.prior_weight > 0 else self.coef_bound)

    def _variance_step(self, state: FitState, resp: np.ndarray, pairs: _Pairs):
        """(state with the new s2 and eta, its geometry on ``pairs``)."""
        x, nv, parts = self._geometry(state, pairs)
        sigma2, eta = self.covariance.update(resp, parts, self.sigma2_min, state.eta, self.dof_)
        self._last_geometry = (pairs, sigma2, eta, (x, nv, self.covariance.with_eta(parts, eta)))
        return replace(state, sigma2=sigma2, eta=eta), self._last_geometry[3]

    # -- the loop ---------------------------------------------------------------------------
    def _pairs_for(self, state: FitState, pairs: _Pairs, keep_k: bool = False) -> _Pairs:
        """``pairs``, or new ones when the vertices at ``state`` moved or K changed (with
        ``keep_k``, K does not shrink)."""
        k_wanted = max(self._neighbours_for(state.sigma2), self._k_floor)
        if keep_k:
            k_wanted = max(k_wanted, pairs.k)
        last = self._last_geometry
        x_new = (last[3][0] if last[0] is pairs and last[1] == state.sigma2 and last[2] == state.eta
                 else state.pose.apply(self.snap_.shape(state.coef)))
        moved = float(np.sqrt(((x_new[pairs.verts] - pairs.x_ref) ** 2).sum(axis=1).max()))
        if (self.covariance.hard or moved > 0.25 * self.snap_.edge_length
                or not pairs.k / 1.5 <= k_wanted <= pairs.k * 1.5):
            return _Pairs(self.snap_, x_new, self.points_, k_wanted)
        return pairs

    def _extrapolated(self, old: FitState, new: FitState, factor: float, ev: _Evaluation,
                      pairs: _Pairs) -> FitState:
        """The pose and coefficients ``factor`` of the way from ``old`` to ``new`` (a factor
        below 1 shortens the step, above 1 over-relaxes it), the variance re-estimated."""
        coef = old.coef + factor * (new.coef - old.coef)
        if self.prior_weight == 0 and self.coef_bound is not None:
            coef = np.clip(coef, -self.coef_bound, self.coef_bound)
        trial = replace(old, pose=old.pose.interpolate(new.pose, factor), coef=coef)
        return self._variance_step(trial, ev.resp, pairs)[0]

    def _accept(self, old: FitState, new: FitState, ev: _Evaluation, pairs: _Pairs,
                relax: float = 1.0):
        """(state, evaluation, pairs, over-relaxed) of the step: over-relaxed by ``relax``
        when that lowers the objective, else the plain step, halved until the objective is at
        most the previous one (``ev``); None when six halvings do not get there."""
        slack = 1e-12 * max(abs(ev.objective), 1.0)
        if relax > 1.0:
            far = self._extrapolated(old, new, relax, ev, pairs)
            far_pairs = self._pairs_for(far, pairs)
            last = self._last_geometry
            reuse = last[0] is far_pairs and last[1] == far.sigma2 and last[2] == far.eta
            far_ev = self._e_step(far, far_pairs, last[3] if reuse else None)
            if far_ev.objective <= ev.objective + slack:
                return far, far_ev, far_pairs, True
        # The E-step's sum runs over each point's K nearest vertices, K shrinking with the
        # variance; a smaller K drops mixture mass and raises the objective by itself, so a
        # step whose variance crossed that threshold could be refused however short (issue
        # 27: a fit stopped at iteration 7, 100 above the optimum's objective). The
        # shortened steps are then tried again with K kept.
        first_k = 0  # K of the first attempt's pairs
        for keep_k in (False, True):
            new_pairs = self._pairs_for(new, pairs, keep_k)
            if keep_k:
                if new_pairs.k <= first_k:  # K had not shrunk: nothing else to try
                    break
                self._k_floor = pairs.k  # for the rest of this fit: it would be refused again
            first_k = new_pairs.k
            trial = new
            for halving in range(_HALVINGS + 1):
                last = self._last_geometry
                reuse = last[0] is new_pairs and last[1] == trial.sigma2 and last[2] == trial.eta
                trial_ev = self._e_step(trial, new_pairs, last[3] if reuse else None)
                if trial_ev.objective <= ev.objective + slack:
                    return trial, trial_ev, new_pairs, False
                # pose, coefficients interpolated; s2, eta re-estimated
                trial = self._extrapolated(old, new, 0.5 ** (halving + 1), ev, pairs)
        return None

    def fit(self, snap: ModelSnapshot, points: np.ndarray, normals: np.ndarray | None = None,
            init: FitState | None = None, placement: Similarity | None = None) -> "GMMFitter":
        """Run EM; the result is in ``state_``, ``objective_``, ``n_iter_``, ``converged_``."""
        self._prepare(snap, points, normals)
        if init is None and self.warm_start and hasattr(self, "state_"):
            init = self.state_
        place = Similarity.identity() if placement is None else placement
        state, x = self._initial_state(init, place)
        pairs = _Pairs(snap, x, points, self._neighbours_for(state.sigma2))
        ev = self._e_step(state, pairs)
        shape_active = (not self.pose_first or init is not None or self.pose == "none"
                        or snap.n_factors == 0)
        self.objective_, self.converged_ = [ev.objective], False
        self.stop_reason_, self.n_iter_ = f"reached max_iter={self.max_iter}", 0
        self.precision_, self._last_geometry = None, (None, None, None, None)
        self.dof_, self._k_floor = 0.0, 0
        relax = 1.0
        for it in range(self.max_iter):
            if self.callback is not None:
                self.callback(it, ev.objective)
            step = self._accept(state, self._m_step(state, ev, pairs, shape_active), ev, pairs,
                                relax)
            if step is None:
                self.converged_, self.stop_reason_ = True, "no further decrease of the objective"
                break
            moved = float(np.sqrt(((step[1].x - ev.x) ** 2).sum(axis=1).max()))
            previous = ev.objective
            state, ev, pairs, relaxed = step
            if self.overrelax and shape_active and (relaxed or relax == 1.0):
                relax = min(RELAX_GROWTH * relax, MAX_RELAX)  # it paid: lengthen the next step
            else:
                relax = 1.0  # the lengthened step overshot (or no over-relaxation): plain EM
            self.n_iter_ = it + 1
            self.objective_.append(ev.objective)
            change = abs(previous - ev.objective)
            scale = max(abs(ev.objective), 1.0)
            if change <= self.tol * scale or (moved < self.xtol and change <= 100 * self.tol * scale):
                if shape_active:
                    self.converged_ = True
                    self.stop_reason_ = (f"objective change below tol={self.tol:g}"
                                         if change <= self.tol * scale else
                                         f"largest vertex move below xtol={self.xtol:.3g} mm")
                    break
                shape_active = True
        self.state_, self.vertices_ = state, ev.x
        return self


def solve_shape(lhs: np.ndarray, rhs: np.ndarray, bound: np.ndarray | None) -> np.ndarray:
    """Minimise a^T lhs a / 2 - rhs^T a (lhs symmetric positive semi-definite).

    With a prior (``bound`` None) lhs is positive definite: a direct solve. Without one
    (``prior_weight=0``) the data may leave directions free or barely constrained: the
    minimum-norm solution (pseudo-inverse), and if it leaves the box |a_m| <= bound_m, the
    exact box-constrained minimiser (bounded least squares on a square root of lhs).
    """
    if bound is None:
        return np.linalg.solve(lhs, rhs)
    vals, vecs = np.linalg.eigh(lhs)
    keep = vals > 1e-10 * max(float(vals.max()), 1e-300)
    coef = vecs[:, keep] @ ((vecs[:, keep].T @ rhs) / vals[keep])
    if np.all(np.abs(coef) <= bound):
        return coef
    from scipy.optimize import lsq_linear

    root = np.sqrt(np.maximum(vals, 0.0))  # lhs = F^T F, F = diag(root) V^T
    target = np.where(keep, (vecs.T @ rhs) / np.where(keep, root, 1.0), 0.0)
    return lsq_linear(root[:, None] * vecs.T, target, bounds=(-bound, bound), method="bvls").x
