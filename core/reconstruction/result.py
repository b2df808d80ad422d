"""The result of a fit (:class:`FitResult`), with the plain-data plausibility read-out."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.geometry.toolkit import rotation_vector
from core.reconstruction.pose import Similarity


@dataclass
class FitResult:
    """The result of :func:`core.reconstruction.fit_points`.

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
        and after each accepted EM step; non-increasing.
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
    placement : (4, 4) float ndarray or None
        The placement the fit started from and its pose prior was centred on.
    model_size_mm : float
        RMS distance of the model's mean-shape vertices from their centroid (mm), the length
        the fit's defaults are relative to.
    coef_sd : (M,) float ndarray or None
        sqrt of the prior variances (so ``coef / coef_sd`` are the coefficients in SD).
    coef_precision : (M, M) float ndarray or None
        Posterior precision of the coefficients at the last M-step (Laplace approximation
        with the responsibilities and the pose fixed: (sum_j w_j Phi_j^T W_j Phi_j +
        lambda s2 diag(1/var)) / s2, model frame); None when no shape step ran.
        ``coef_covariance`` is its inverse.
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
    placement: np.ndarray | None = None
    model_size_mm: float = float("nan")
    coef_sd: np.ndarray | None = None
    coef_precision: np.ndarray | None = None
    centre_offset_mm: np.ndarray | None = None  # fitted centre minus placed centre (world)
    residual_correlation: float = 0.0  # neighbouring points' normal residuals (fit_points)
    prior_inflation: float = 1.0       # (1 + rho) / (1 - rho), the shape prior's weight factor
    prior_weight: float = 1.0          # lambda the fit was run with (before the inflation)
    warnings: list[str] = field(default_factory=list)  # e.g. points far from the placement
    placement_source: str = "stored"   # "stored", "given" (a matrix) or "points" (Place here)
    mirror_restart: str = ""          # "fit" / "mirror": which start won (fit_points); "": none
    mirror_key: tuple | None = None   # the parallel slices the mirror was looked at for
    mirror_gap: float = float("nan")  # the other start's objective minus the kept one's

    @property
    def coef_covariance(self) -> np.ndarray | None:
        """(M, M) posterior covariance of the coefficients (inverse of ``coef_precision``)."""
        if self.coef_precision is None:
            return None
        return np.linalg.inv(self.coef_precision)

    @property
    def scale(self) -> float:
        """Isotropic scale of ``pose`` (cube root of |det| of its linear part)."""
        return float(abs(np.linalg.det(self.pose[:3, :3])) ** (1.0 / 3.0))

    def plausibility(self) -> dict:
        """Plain numbers for a safety net (issue 17): how far the fit went, and how well.

        ``residual_relative``: mean point-to-surface residual over the model size;
        ``max_abs_coef_sd`` and ``n_coef_beyond_3sd``: the coefficients in prior SD;
        ``placement_shift_mm``, ``placement_rotation_deg``, ``placement_scale_ratio``: the
        fitted pose against the placement (shift of the model's centre).
        """
        out = {"residual_mm": float(self.residual_mm), "model_size_mm": float(self.model_size_mm),
               "residual_relative": float(self.residual_mm / self.model_size_mm)
               if self.model_size_mm > 0 else float("nan"),
               "converged": bool(self.converged)}
        if self.coef_sd is not None and len(self.coef):
            z = np.abs(np.asarray(self.coef) / np.asarray(self.coef_sd))
            out.update(max_abs_coef_sd=float(z.max()), n_coef_beyond_3sd=int((z > 3.0).sum()))
        else:
            out.update(max_abs_coef_sd=0.0, n_coef_beyond_3sd=0)
        if self.placement is not None:
            d = Similarity.from_matrix(self.pose @ np.linalg.inv(self.placement))
            shift = (np.linalg.norm(self.centre_offset_mm) if self.centre_offset_mm is not None
                     else float("nan"))
            out.update(placement_shift_mm=float(shift),
                       placement_rotation_deg=float(np.rad2deg(np.linalg.norm(rotation_vector(d.rot)))),
                       placement_scale_ratio=float(d.scale))
        return out

    def to_dict(self) -> dict:
        """JSON-friendly summary (no vertices)."""
        out = {
            "method": self.method, "pose_mode": self.pose_mode, "coef": self.coef.tolist(),
            "pose": self.pose.tolist(), "objective": [float(v) for v in self.objective],
            "n_iter": self.n_iter, "converged": self.converged, "stop_reason": self.stop_reason,
            "residual_mm": self.residual_mm, "sigma2": self.sigma2, "anisotropy": self.anisotropy,
            "n_points": self.n_points,
            "elapsed_s": self.elapsed_s,
            "residual_correlation": self.residual_correlation,
            "prior_inflation": self.prior_inflation,
            "prior_weight": self.prior_weight,
            "warnings": list(self.warnings),
            "mirror_restart": self.mirror_restart,
            "mirror_gap": None if not np.isfinite(self.mirror_gap) else self.mirror_gap,
        }
        if self.placement is not None:
            out["placement"] = np.asarray(self.placement).tolist()
            out["plausibility"] = self.plausibility()
        return out
