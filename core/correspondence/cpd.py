"""Coherent Point Drift through rustcpd, as plain numpy (the adapter of the correspondence step).

Myronenko & Song, "Point Set Registration: Coherent Point Drift", TPAMI 2010: rigid (Fig. 2),
affine and nonrigid (Fig. 4) registration, and the posterior of Eq. 7. rustcpd (PyPI,
BSD-2-Clause) is a Rust CPD with a low-rank kernel, ~25x faster than pure-numpy pycpd; it is
used only through these functions, which return :class:`CPDResult`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class CPDResult:
    """A CPD registration, as plain numpy.

    Attributes
    ----------
    points : (M, 3) float
        The moved source points.
    sigma2 : float
        Final variance of the Gaussian mixture (squared input units).
    n_iter : int
        EM iterations run.
    matrix : (4, 4) float or None
        For rigid/affine: the transform applied to the source (column vectors).
    """

    points: np.ndarray
    sigma2: float
    n_iter: int
    matrix: np.ndarray | None = None
    source: np.ndarray | None = None
    coefficients: np.ndarray | None = None
    beta: float | None = None

    def warp(self, points: np.ndarray, chunk: int = 4096) -> np.ndarray:
        """Apply the fitted transformation to other points (P, 3).

        Rigid/affine: the matrix. Nonrigid: the continuous displacement field
        v(z) = G(z, Y) C of TPAMI 2010 Eq. 19, G(z, y) = exp(-|z - y|^2 / 2 beta^2), with the
        coefficients C set by :func:`cpd_nonrigid` so that v reproduces the moved points.
        """
        points = np.asarray(points, dtype=np.float64)
        if self.matrix is not None:
            return points @ self.matrix[:3, :3].T + self.matrix[:3, 3]
        if self.source is None or self.coefficients is None or self.beta is None:
            raise ValueError("this CPD result has neither a matrix nor a displacement field")
        out = np.empty_like(points)
        for start in range(0, len(points), chunk):
            z = points[start:start + chunk]
            d2 = np.maximum((z ** 2).sum(axis=1)[:, None] + (self.source ** 2).sum(axis=1)[None, :]
                            - 2.0 * z @ self.source.T, 0.0)
            out[start:start + chunk] = z + np.exp(-d2 / (2.0 * self.beta ** 2)) @ self.coefficients
        return out


def _rustcpd():
    import rustcpd  # imported lazily: only the adapter below knows it
    return rustcpd


def cpd_rigid(target: np.ndarray, source: np.ndarray, *, scaling: bool = True, w: float = 0.0,
              tolerance: float = 1e-5, max_iterations: int = 100, parallel: bool = True) -> CPDResult:
    """Rigid CPD (rotation, translation, optional scale) of ``source`` (M, 3) onto ``target`` (N, 3)."""
    r = _rustcpd().register_rigid(target, source, scale=scaling, outlier_weight=w, tolerance=tolerance,
                                  max_iterations=max_iterations, parallel=parallel)
    # rustcpd's convention is row vectors: points = s * source @ R + t.
    matrix = np.eye(4)
    matrix[:3, :3] = r.scale * np.asarray(r.rotation).T
    matrix[:3, 3] = r.translation
    return CPDResult(np.asarray(r.points), float(r.sigma2), int(r.iterations), matrix)


def cpd_affine(target: np.ndarray, source: np.ndarray, *, w: float = 0.0, tolerance: float = 1e-5,
               max_iterations: int = 100, parallel: bool = True) -> CPDResult:
    """Affine CPD of ``source`` (M, 3) onto ``target`` (N, 3)."""
    r = _rustcpd().register_affine(target, source, outlier_weight=w, tolerance=tolerance,
                                   max_iterations=max_iterations, parallel=parallel)
    matrix = np.eye(4)
    matrix[:3, :3] = np.asarray(r.transform).T  # rustcpd: points = source @ B + t
    matrix[:3, 3] = r.translation
    return CPDResult(np.asarray(r.points), float(r.sigma2), int(r.iterations), matrix)


def cpd_nonrigid(target: np.ndarray, source: np.ndarray, *, w: float = 0.0, beta: float = 2.0,
                 lam: float = 2.0, tolerance: float = 1e-5, max_iterations: int = 100,
                 low_rank: int | None = 80, low_rank_method: str = "eigen",
                 parallel: bool = True) -> CPDResult:
    """Nonrigid CPD (Gaussian motion coherence) of ``source`` (M, 3) onto ``target`` (N, 3).

    ``beta`` is the kernel width, ``lam`` the regularisation weight (TPAMI 2010 Eq. 20), both
    in the units of the points. ``low_rank`` approximates the kernel G by its leading
    eigenpairs, G ~ Q L Q^T, when smaller than M (None: exact).

    The displacement field for other points (:meth:`CPDResult.warp`): with the exact kernel,
    v(z) = G(z, Y) W with CPD's weights W. With the low-rank kernel the moved points are
    Y + Q L Q^T W, and G(z, Y) W does not reproduce them (W has large components where
    Q L Q^T is zero; rustcpd's own ``transform`` is off by far more than the point spacing
    there), so the field is extended by Nystrom: v(z) = G(z, Y) Q L^-1 Q^T D with D the
    displacements of the sources, exact at the sources for ``low_rank_method="eigen"``;
    with ``"pivoted_cholesky"`` (far cheaper to build: no dense eigendecomposition) the basis
    is not G's eigenbasis and the extension is approximate, measured within 1e-3 of the point
    spacing at the sources of a 3,000-point subsample of a 10,000-vertex pair.
    """
    rank = None if low_rank is None or low_rank >= len(source) else int(low_rank)
    r = _rustcpd().register_deformable(target, source, alpha=lam, beta=beta, low_rank=rank,
                                       low_rank_method=low_rank_method,
                                       outlier_weight=w, tolerance=tolerance,
                                       max_iterations=max_iterations, parallel=parallel)
    points = np.asarray(r.points)
    src = np.asarray(r.source)
    if rank is None:
        coefficients = np.asarray(r.weights)
    else:
        basis = np.asarray(r.low_rank_basis)
        eigenvalues = np.asarray(r.low_rank_eigenvalues)
        coefficients = basis @ ((basis.T @ (points - src)) / eigenvalues[:, None])
    return CPDResult(points, float(r.sigma2), int(r.iterations), None, src, coefficients,
                     float(r.beta))


def cpd_log_posterior(target: np.ndarray, moved: np.ndarray, sigma2: float, w: float = 0.0,
                      chunk: int = 4096) -> np.ndarray:
    """Log of the CPD posterior, log P_mn, (M, N), vectorised and chunked over target points.

    TPAMI 2010 Eq. 7: P_mn = exp(-|x_n - y_m|^2 / 2s2) / (sum_k exp(-|x_n - y_k|^2 / 2s2) + c),
    c = (2 pi s2)^(D/2) w/(1-w) M/N. Computed with log-sum-exp, so it does not underflow.
    """
    m, n, d = len(moved), len(target), target.shape[1]
    out = np.empty((m, n))
    log_c = -np.inf
    if w > 0:
        log_c = 0.5 * d * np.log(2 * np.pi * sigma2) + np.log(w / (1 - w)) + np.log(m / n)
    yy = (moved ** 2).sum(axis=1)[:, None]
    for start in range(0, n, chunk):
        x = target[start:start + chunk]
        d2 = np.maximum(yy + (x ** 2).sum(axis=1)[None, :] - 2.0 * moved @ x.T, 0.0)
        logits = d2
        logits *= -1.0 / (2.0 * sigma2)
        top = np.maximum(logits.max(axis=0), log_c)  # log-sum-exp with the outlier term
        total = np.exp(logits - top).sum(axis=0) + np.exp(log_c - top)
        logits -= top + np.log(total)
        out[:, start:start + chunk] = logits
    return out
