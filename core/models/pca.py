"""Principal component analysis shape model (Cootes et al., "Active Shape Models", 1995).

The factors are the leading right singular vectors of the centred data matrix
X_c (K x 3N) = U S V^T, i.e. the eigenvectors of the sample covariance; the coefficient prior
variances are the eigenvalues S^2 / (K - 1). The number of modes is given directly
(``n_factors``) or as the smallest number retaining a fraction of the total variance
(``variance_retained``, e.g. 0.95). Global support: every factor moves the whole shape.
"""

from __future__ import annotations

import numpy as np

from core.models._params import Integral, Interval, Real
from core.models.base import ShapeModelEstimator
from core.runtime.progress import ProgressCallback, report


def pca_basis(Xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Principal directions and variances of centred data.

    Parameters
    ----------
    Xc : (K, D) float array
        Centred data, one sample per row.

    Returns
    -------
    components : (r, D) orthonormal rows, r = min(K - 1, D), by decreasing variance
    variances : (r,) eigenvalues of the sample covariance (ddof = 1)
    """
    k = Xc.shape[0]
    _, s, vt = np.linalg.svd(Xc, full_matrices=False)
    r = min(k - 1, vt.shape[0])
    return vt[:r], s[:r] ** 2 / max(k - 1, 1)


def n_modes_for_variance(variances: np.ndarray, fraction: float) -> int:
    """Smallest number of leading modes whose variance sum is >= ``fraction`` of the total."""
    cum = np.cumsum(variances) / max(float(variances.sum()), 1e-300)
    return min(int(np.searchsorted(cum, fraction - 1e-12)) + 1, len(variances))


class PCA(ShapeModelEstimator):
    """PCA point distribution model.

    Parameters
    ----------
    n_factors : int or None, default None
        Number of modes. None: decided by ``variance_retained`` (all K - 1 modes if that is
        None too).
    variance_retained : float in (0, 1] or None, default None
        Keep the fewest modes explaining this fraction of the variance (used when
        ``n_factors`` is None).
    connectivity : (F, 3) int array or (N, N) sparse matrix, default None
        The mesh, kept with the model (PCA itself does not use the graph).

    Attributes
    ----------
    mean_ : (N, 3), factors_ : (M, N, 3) orthonormal, coef_var_ : (M,) eigenvalues,
    explained_variance_ratio_ : (M,) fraction of the total variance per mode (eigenvalue over
    the sum of all eigenvalues).
    """

    method = "pca"
    _parameter_constraints = {
        "n_factors": [Interval(Integral, 1, None), None],
        "variance_retained": [Interval(Real, 0, 1, closed="right"), None],
        "connectivity": ["array-like", "sparse matrix", None],
    }

    def __init__(self, n_factors: int | None = None, *, variance_retained: float | None = None,
                 connectivity=None):
        self.n_factors = n_factors
        self.variance_retained = variance_retained
        self.connectivity = connectivity

    def _fit(self, X, progress: ProgressCallback | None):
        report(progress, 0.0, "PCA")
        k, n, _ = X.shape
        mean = X.mean(axis=0)
        components, variances = pca_basis((X - mean).reshape(k, -1))
        if self.n_factors is not None:
            m = min(int(self.n_factors), len(components))
        elif self.variance_retained is not None:
            m = n_modes_for_variance(variances, float(self.variance_retained))
        else:
            m = len(components)
        self.n_iter_ = 1
        self.converged_ = True
        report(progress, 1.0, "PCA")
        return mean, components[:m].reshape(m, n, 3)
