"""Varimax-rotated PCA (Kaiser, "The varimax criterion for analytic rotation in factor
analysis", Psychometrika 1958), a baseline of Bernard et al. (CVPR 2016).

The M leading PCA loadings L = V_M diag(sqrt(eigenvalues)) (3N x M) are rotated by the
orthogonal R maximising the varimax criterion sum_m [ sum_i L_im^4 - (1/p)(sum_i L_im^2)^2 ]
(p = 3N rows), which concentrates each factor on fewer coordinates. Rotation does not change
the spanned subspace (same reconstruction/generalisation as PCA with M modes), only the factors.
The classic SVD iteration: R <- U W^T with U S W^T = svd(L^T (Lr^3 - Lr diag(sum Lr^2)/p)).
"""

from __future__ import annotations

import numpy as np

from core.models._params import Integral, Interval, Real
from core.models.base import ShapeModelEstimator
from core.models.pca import pca_basis
from core.runtime.progress import ProgressCallback, report


def varimax_rotation(loadings: np.ndarray, *, max_iter: int = 500, tol: float = 1e-8,
                     progress: ProgressCallback | None = None) -> tuple[np.ndarray, int, bool]:
    """Orthogonal varimax rotation of ``loadings`` (p, M).

    Returns
    -------
    rotation : (M, M) orthogonal, so that the rotated loadings are ``loadings @ rotation``
    n_iter : int
    converged : bool
    """
    p, m = loadings.shape
    rotation = np.eye(m)
    criterion = 0.0
    for it in range(1, max_iter + 1):
        lr = loadings @ rotation
        target = lr ** 3 - lr * (np.sum(lr ** 2, axis=0) / p)
        u, s, wt = np.linalg.svd(loadings.T @ target)
        rotation = u @ wt
        new = float(s.sum())
        report(progress, it / max_iter, f"varimax iteration {it}")  # each: a cancel point
        if new - criterion <= tol * max(new, 1e-300):
            return rotation, it, True
        criterion = new
    return rotation, max_iter, False


class Varimax(ShapeModelEstimator):
    """PCA with varimax-rotated factors.

    Parameters
    ----------
    n_factors : int or None, default None
        Number of PCA modes rotated (None: all K - 1).
    max_iter : int, default 500
    tol : float, default 1e-8
        Relative increase of the varimax criterion below which the rotation stops.
    connectivity : (F, 3) int array or (N, N) sparse matrix, default None
        The mesh, kept with the model (not used by the rotation).
    """

    method = "varimax"
    _parameter_constraints = {
        "n_factors": [Interval(Integral, 1, None), None],
        "max_iter": [Interval(Integral, 1, None)],
        "tol": [Interval(Real, 0, None)],
        "connectivity": ["array-like", "sparse matrix", None],
    }

    def __init__(self, n_factors: int | None = None, *, max_iter: int = 500, tol: float = 1e-8,
                 connectivity=None):
        self.n_factors = n_factors
        self.max_iter = max_iter
        self.tol = tol
        self.connectivity = connectivity

    def _fit(self, X, progress: ProgressCallback | None):
        k, n, _ = X.shape
        mean = X.mean(axis=0)
        components, variances = pca_basis((X - mean).reshape(k, -1))
        m = len(components) if self.n_factors is None else min(int(self.n_factors), len(components))
        loadings = components[:m].T * np.sqrt(np.maximum(variances[:m], 0.0))  # (3N, M)
        rotation, self.n_iter_, self.converged_ = varimax_rotation(
            loadings, max_iter=int(self.max_iter), tol=float(self.tol), progress=progress)
        report(progress, 1.0, "varimax")
        return mean, (loadings @ rotation).T.reshape(m, n, 3)
