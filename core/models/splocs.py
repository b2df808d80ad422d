"""Sparse localised deformation components (SPLOCS), the local-support baseline.

Neumann, Varanasi, Wenger, Wacker, Magnor & Theobalt, "Sparse Localized Deformation
Components", ACM Trans. Graph. 32(6), SIGGRAPH Asia 2013.

Problem (X: centred shapes (K, N, 3), scaled to unit standard deviation; C: M components
(M, N, 3); W: weights (K, M))::

    min_{W, C} ||X - W C||_F^2 + Omega(C)   s.t.  max_k |W_km| = 1                         # Eq. 2
    Omega(C) = sum_m sum_i Lambda_mi ||C_m,i||_2                                           # Eq. 3

with the support map Lambda_mi = lambda * clip((d(c_m, i) - d_min) / (d_max - d_min), 0, 1),
d the geodesic distance on the mean shape from the component's centre c_m (its vertex of
largest displacement): the l1/l2 penalty is zero near the centre and grows outside, which
explicitly models each component's support region and so needs its size (d_min, d_max) up
front -- the initialisation LSF does without.

Algorithm (the published one): greedy initialisation -- component m starts at the vertex with
the largest residual displacement over the training set, its weights are that vertex's
residual magnitude per shape, the component the least-squares fit to the residual; then
alternate (i) weights by coordinate descent with the max-|w| = 1 normalisation (signed
weights: the data are mean-centred shapes, not animation frames relative to a rest pose),
(ii) support maps from the current centres, (iii) components by ADMM on Eq. 2-3 with the
splitting C = Z: (W^T W + rho I) C = W^T X + rho (Z - U); Z = group-shrink(C + U, Lambda / rho);
U += C - Z. Geodesic distances are approximated by shortest paths along mesh edges (Dijkstra)
and d_min, d_max are given as fractions of the mean shape's bounding-box diagonal.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.csgraph import dijkstra

from core.models._params import Integral, Interval, Real
from core.models.base import ShapeModelEstimator, edge_adjacency
from core.runtime.progress import ProgressCallback, report


def _group_shrink(Y: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Prox of sum t_mi ||Y_m,i||_2 over vertex triples; Y (M, N, 3), t (M, N)."""
    norms = np.linalg.norm(Y, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(norms > 0, np.maximum(1.0 - t / norms, 0.0), 0.0)
    return Y * scale[:, :, None]


def greedy_init(data: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Components (M, N, 3) and weights (K, M) started at the vertices of largest residual
    (Neumann et al., section 4.2)."""
    k, n, _ = data.shape
    C = np.zeros((m, n, 3))
    W = np.zeros((k, m))
    R = data.copy()
    for j in range(m):
        idx = int(np.argmax(np.einsum("kni,kni->n", R, R)))
        w = np.linalg.norm(R[:, idx, :], axis=1)
        signs = np.sign(R[:, idx, :] @ (R[:, idx, :].T @ w))  # consistent direction
        w = w * np.where(signs == 0, 1.0, signs)
        if not np.any(w):
            break
        w = w / np.abs(w).max()
        c = np.tensordot(w, R, axes=(0, 0)) / (w @ w)
        C[j], W[:, j] = c, w
        R -= w[:, None, None] * c[None]
    return C, W


def update_weights(flat: np.ndarray, W: np.ndarray, Cf: np.ndarray) -> None:
    """Weights by coordinate descent, each column normalised to max |w| = 1 (the scale moves
    into the component); updates W (K, M) and Cf (M, 3N) in place."""
    Rf = flat - W @ Cf
    for j in range(W.shape[1]):  # M columns, each a vectorised least-squares update
        cj = Cf[j]
        cc = cj @ cj
        if cc <= 0:
            W[:, j] = 0.0
            continue
        Rj = Rf + np.outer(W[:, j], cj)
        w = Rj @ cj / cc
        peak = np.abs(w).max()
        if peak > 0:
            w = w / peak
            Cf[j] = cj * peak
        W[:, j] = w
        Rf = Rj - np.outer(w, Cf[j])


def admm_components(flat: np.ndarray, W: np.ndarray, lam: np.ndarray, Z: np.ndarray,
                    U: np.ndarray, rho: float, n_admm: int) -> tuple[np.ndarray, np.ndarray]:
    """Components Z (M, N, 3) minimising ||X - W C||^2 + sum Lambda_mi ||C_m,i|| by ADMM on the
    splitting C = Z, from Z and the scaled dual U (kept across outer iterations); returns both."""
    m = W.shape[1]
    chol = np.linalg.cholesky(W.T @ W + rho * np.eye(m))
    wtx = W.T @ flat
    for _ in range(n_admm):
        rhs = wtx + rho * (Z - U).reshape(m, -1)
        C = np.linalg.solve(chol.T, np.linalg.solve(chol, rhs)).reshape(Z.shape)
        Z = _group_shrink(C + U, lam / rho)
        U = U + C - Z
    return Z, U


class SPLOCS(ShapeModelEstimator):
    """Sparse localised deformation components (Neumann et al., 2013).

    Parameters
    ----------
    n_factors : int, default 32
        Number of components M.
    connectivity : (F, 3) int array or (N, N) sparse matrix, default None
        The mesh graph (required): geodesic distances run along its edges.
    sparsity : float, default 2.0
        lambda, weight of the support-weighted l1/l2 penalty (paper default).
    d_min, d_max : float, default 0.1, 0.7
        Support-map distances as fractions of the mean shape's bounding-box diagonal.
    max_iter : int, default 20
        Outer iterations (weights, support maps, components).
    n_admm : int, default 10
        ADMM iterations per component update.
    rho : float, default 10.0
        ADMM penalty parameter.
    tol : float, default 1e-6
        Stop when the relative change of the data term is below tol.
    """

    method = "splocs"
    needs_graph = True
    _parameter_constraints = {
        "n_factors": [Interval(Integral, 1, None)],
        "connectivity": ["array-like", "sparse matrix", None],
        "sparsity": [Interval(Real, 0, None)],
        "d_min": [Interval(Real, 0, None)],
        "d_max": [Interval(Real, 0, None, closed="neither")],
        "max_iter": [Interval(Integral, 1, None)],
        "n_admm": [Interval(Integral, 1, None)],
        "rho": [Interval(Real, 0, None, closed="neither")],
        "tol": [Interval(Real, 0, None)],
    }

    def __init__(self, n_factors: int = 32, *, connectivity=None, sparsity: float = 2.0,
                 d_min: float = 0.1, d_max: float = 0.7, max_iter: int = 20, n_admm: int = 10,
                 rho: float = 10.0, tol: float = 1e-6):
        self.n_factors = n_factors
        self.connectivity = connectivity
        self.sparsity = sparsity
        self.d_min = d_min
        self.d_max = d_max
        self.max_iter = max_iter
        self.n_admm = n_admm
        self.rho = rho
        self.tol = tol

    def _support_maps(self, C: np.ndarray, graph, d_min: float, d_max: float) -> np.ndarray:
        """Lambda (M, N) from geodesic distances to each component's centre (Eq. 3)."""
        mags = np.linalg.norm(C, axis=2)
        live = mags.max(axis=1) > 0
        lam = np.full(mags.shape, float(self.sparsity))
        if np.any(live):
            centres = np.argmax(mags[live], axis=1)
            d = dijkstra(graph, directed=False, indices=centres)
            d = np.where(np.isfinite(d), d, d_max)
            lam[live] = self.sparsity * (np.clip(d, d_min, d_max) - d_min) / (d_max - d_min)
        return lam

    def _fit(self, X, progress: ProgressCallback | None):
        if self.d_max <= self.d_min:
            raise ValueError(f"d_max must be larger than d_min; got d_min={self.d_min}, "
                             f"d_max={self.d_max}")
        k, n, _ = X.shape
        mean = X.mean(axis=0)
        scale = float((X - mean).std())
        if scale <= 0:
            raise ValueError("the training shapes are identical: nothing to factorise")
        data = (X - mean) / scale  # (K, N, 3)
        flat = data.reshape(k, -1)
        e = self._graph_edges()
        length = np.linalg.norm(mean[e[:, 0]] - mean[e[:, 1]], axis=1)
        graph = edge_adjacency(e, n, np.maximum(length, 1e-12))
        diag = float(np.linalg.norm(np.ptp(mean, axis=0)))
        d_min, d_max = self.d_min * diag, self.d_max * diag
        C, W = greedy_init(data, int(self.n_factors))
        report(progress, 0.02, "SPLOCS initialised")
        U = np.zeros_like(C)
        prev, converged, it = np.inf, False, 0
        for it in range(1, int(self.max_iter) + 1):
            Cf = C.reshape(len(C), -1)
            update_weights(flat, W, Cf)
            C = Cf.reshape(C.shape)
            lam = self._support_maps(C, graph, d_min, d_max)
            C, U = admm_components(flat, W, lam, C.copy(), U, float(self.rho),
                                   int(self.n_admm))
            err = float(np.sum((flat - W @ C.reshape(len(C), -1)) ** 2))
            report(progress, it / self.max_iter, f"SPLOCS iteration {it}/{self.max_iter}")
            if abs(prev - err) <= self.tol * max(err, 1e-300):
                converged = True
                break
            prev = err
        self.n_iter_, self.converged_ = it, converged
        self.weights_ = W
        return mean, C * scale
