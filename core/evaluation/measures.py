"""The measures of shape-model quality (Bernard et al., CVPR 2016, section 3.1), as functions
of a fitted model and shapes, like scikit-learn's ``metrics``: no fitting, no folds, no plots.

Per shape, the average and maximum per-vertex Euclidean error in mm:

- reconstruction e: a training shape against its projection onto the model;
- generalisation g: a left-out shape against its projection (the folds are
  :mod:`core.evaluation.protocol`'s job);
- specificity s: random shapes drawn from the model's coefficient distribution -- the full
  covariance of the training coefficients (local factors' coefficients are correlated) --
  against the closest training shape (closest by average vertex distance);
- sparse reconstruction g0.05: a left-out shape fitted from a subset of its vertices (known
  correspondence) by prior-regularised least squares, compared on all vertices;
- compactness: cumulative fraction of the training variance explained by the span of the
  first m factors, in the model's order.
"""

from __future__ import annotations

import numpy as np

from core.models.base import ShapeModelEstimator
from core.runtime.progress import ProgressCallback, report


def vertex_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Average and maximum per-vertex Euclidean distance per shape: (K,), (K,) from (K, N, 3)."""
    d = np.linalg.norm(np.asarray(estimate) - np.asarray(truth), axis=-1)
    return d.mean(axis=-1), d.max(axis=-1)


def reconstruction_errors(model: ShapeModelEstimator, shapes: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Avg and max error (K,) of each shape against its least-squares projection on the model
    (reconstruction e for training shapes, generalisation g for left-out ones)."""
    shapes = np.asarray(shapes, dtype=np.float64)
    return vertex_errors(model.inverse_transform(model.transform(shapes)), shapes)


def residual_variance(model: ShapeModelEstimator, shapes: np.ndarray) -> float:
    """Mean squared residual per coordinate of the model's projection of ``shapes``."""
    rec = model.inverse_transform(model.transform(shapes))
    return float(np.mean((rec - shapes) ** 2))


def sparse_fit(model: ShapeModelEstimator, points: np.ndarray, indices: np.ndarray,
               noise_var: float) -> np.ndarray:
    """Shape (N, 3) from known vertices ``points`` (S, 3) at ``indices`` (S,) with the prior.

    Solves (Phi_S^T Phi_S + noise_var diag(1 / coef_var)) a = Phi_S^T (points - mean_S): the
    MAP estimate under a ~ N(0, diag(coef_var)) and isotropic noise of variance noise_var (mm^2).
    """
    phi = model.factors_[:, indices, :].reshape(model.n_factors_, -1).T  # (3S, M)
    d = (points - model.mean_[indices]).reshape(-1)
    lhs = phi.T @ phi + noise_var * np.diag(1.0 / model.coef_var_)
    coef = np.linalg.solve(lhs, phi.T @ d)
    return model.inverse_transform(coef)


def compactness(model: ShapeModelEstimator, shapes: np.ndarray) -> np.ndarray:
    """Cumulative fraction (M,) of the variance of ``shapes`` about the model mean explained by
    the span of the first m factors."""
    d = (shapes - model.mean_).reshape(len(shapes), -1).T  # (3N, K)
    total = float(np.sum(d * d))
    q, r = np.linalg.qr(model.basis_)
    # Dependent factors add nothing: zero their direction.
    dependent = np.abs(np.diag(r)) <= 1e-10 * max(float(np.abs(np.diag(r)).max(initial=0)), 1e-300)
    proj = (q.T @ d) ** 2
    proj[dependent] = 0.0
    return np.cumsum(proj.sum(axis=1)) / max(total, 1e-300)


def specificity(model: ShapeModelEstimator, shapes: np.ndarray, n_samples: int,
                random_state: int | None, chunk: int = 16, covariance: str = "full",
                progress: ProgressCallback | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Avg and max error (n_samples,) of random model instances to their closest training shape.

    The instances' coefficients are drawn from N(0, coef_cov_) (``covariance="full"``, the
    training coefficients' real distribution) or N(0, diag(coef_var_)) (``"diag"``).
    ``progress`` is called once per chunk (a cancel point: 1000 samples take seconds).
    """
    samples = model.sample(n_samples, random_state, covariance=covariance)
    avg = np.empty(n_samples)
    mx = np.empty(n_samples)
    for start in range(0, n_samples, chunk):  # chunks bound the (c, K, N) distance array
        report(progress, start / max(n_samples, 1), "specificity")
        s = samples[start:start + chunk]
        d = np.linalg.norm(s[:, None] - shapes[None], axis=-1)  # (c, K, N)
        mean_d = d.mean(axis=2)
        best = np.argmin(mean_d, axis=1)
        rows = np.arange(len(s))
        avg[start:start + chunk] = mean_d[rows, best]
        mx[start:start + chunk] = d[rows, best].max(axis=1)
    return avg, mx


__all__ = ["vertex_errors", "reconstruction_errors", "residual_variance", "sparse_fit",
           "compactness", "specificity"]
