"""The linear shape model x = mean + sum_m a_m * factor_m, as plain data.

Every model-building method (PCA, LSF, SPLOCS, Varimax; see ``core.models``) produces a
:class:`ShapeModel`; the reconstruction engine, the evaluation code, the model file format
(``core.io.save_model`` / ``load_model``) and the GUI all consume it. Conventions:

- shapes are (N, 3) arrays of vertex positions in mm; vectorised shapes are ``X.reshape(-1)``,
  i.e. vertex-major interleaved ``[x0, y0, z0, x1, ...]`` (length 3N);
- ``factors`` is (M, N, 3): factor m displaces vertex i by ``a_m * factors[m, i]``;
- ``coef_var`` is (M,): the variance of each coefficient over the training shapes, i.e. the
  Gaussian prior a ~ N(0, diag(coef_var)) used by fitting and sampling;
- ``world_transform`` (4, 4) maps the model frame to world (RAS, mm): the placement of the
  model's mean where its training shapes were (e.g. on the structure in the MRI).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


def _frozen(array: np.ndarray) -> np.ndarray:
    """A read-only version of ``array`` (the array itself if no one can write to it)."""
    base: np.ndarray | None = array
    while isinstance(base, np.ndarray):
        if base.flags.writeable:
            array = array.copy()
            array.setflags(write=False)
            return array
        base = base.base
    return array


@dataclass
class ShapeModel:
    """A point distribution model with its mesh topology and world placement.

    Attributes
    ----------
    mean : (N, 3) float ndarray
        Mean shape in the model frame (mm).
    factors : (M, N, 3) float ndarray
        Deformation factors.
    coef_var : (M,) float ndarray
        Prior variance of each coefficient (> 0).
    faces : (F, 3) int ndarray
        Triangles indexing the N vertices; (0, 3) for a point model learnt without a mesh
        (an estimator fitted without ``connectivity``), which cannot be saved or shown.
    world_transform : (4, 4) float ndarray
        Model frame -> world (RAS, mm), homogeneous, column-vector convention.
    method : str
        Name of the building method ("pca", "lsf", "splocs", "varimax", ...).
    params : dict
        The method's parameters (JSON-serialisable).
    source_meshes : list of str
        Names of the training meshes.
    info : dict
        Extra metadata kept with the model file (timings, evaluation, ground-truth links).
    """

    mean: np.ndarray
    factors: np.ndarray
    coef_var: np.ndarray
    faces: np.ndarray
    world_transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    method: str = "pca"
    params: dict[str, Any] = field(default_factory=dict)
    source_meshes: list[str] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.mean = np.asarray(self.mean, dtype=np.float64)
        self.factors = np.asarray(self.factors, dtype=np.float64)
        self.coef_var = np.asarray(self.coef_var, dtype=np.float64).reshape(-1)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        self.world_transform = np.asarray(self.world_transform, dtype=np.float64)
        problem = self.validate()
        if problem:
            raise ValueError(problem)
        # The geometry is immutable (read-only copies): whoever caches work on the model
        # (the fit's snapshot, core.reconstruction) can trust that an array it saw is unchanged.
        # To change a model, assign new arrays (or build a new ShapeModel).
        for name in ("mean", "factors", "coef_var", "faces"):
            setattr(self, name, _frozen(getattr(self, name)))

    def validate(self) -> str | None:
        """Return a description of the first inconsistency found, or None if consistent."""
        if self.mean.ndim != 2 or self.mean.shape[1] != 3 or self.mean.shape[0] < 4:
            return f"mean must be (N, 3) with N >= 4, got shape {self.mean.shape}"
        n = self.mean.shape[0]
        if self.factors.ndim != 3 or self.factors.shape[1:] != (n, 3):
            return f"factors must be (M, {n}, 3), got shape {self.factors.shape}"
        m = self.factors.shape[0]
        if self.coef_var.shape != (m,):
            return f"coef_var must have {m} entries (one per factor), got {self.coef_var.shape[0]}"
        if self.faces.size == 0:
            self.faces = self.faces.reshape(0, 3)  # a point model without a mesh (see faces)
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            return f"faces must be (F, 3) triangles, got shape {self.faces.shape}"
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= n):
            return f"faces index vertices outside 0..{n - 1}"
        if self.world_transform.shape != (4, 4):
            return f"world_transform must be 4x4, got {self.world_transform.shape}"
        for name in ("mean", "factors", "coef_var", "world_transform"):
            if not np.all(np.isfinite(getattr(self, name))):
                return f"{name} contains NaN or infinite values"
        if np.any(self.coef_var <= 0):
            return "coef_var must be positive"
        return None

    @property
    def n_vertices(self) -> int:
        return int(self.mean.shape[0])

    @property
    def n_factors(self) -> int:
        return int(self.factors.shape[0])

    @property
    def basis(self) -> np.ndarray:
        """Factors as a (3N, M) matrix Phi, so that vec(x) = vec(mean) + Phi @ a."""
        return self.factors.reshape(self.n_factors, -1).T

    def instance(self, coef: np.ndarray | None = None) -> np.ndarray:
        """Shape for coefficients ``coef`` (M,) in the model frame, (N, 3)."""
        if coef is None or self.n_factors == 0:
            return self.mean.copy()
        coef = np.asarray(coef, dtype=np.float64).reshape(-1)
        if coef.shape != (self.n_factors,):
            raise ValueError(f"expected {self.n_factors} coefficients, got {coef.shape[0]}")
        return self.mean + np.tensordot(coef, self.factors, axes=1)

    def project(self, shapes: np.ndarray) -> np.ndarray:
        """Least-squares coefficients (K, M) of shapes (K, N, 3) (or (M,) for one (N, 3)).

        Solves the normal equations through the pseudo-inverse of the (M, M) Gram matrix with a
        relative eigenvalue cut-off, so numerically dependent factors (e.g. more local factors
        than training shapes) get the minimum-norm coefficients.
        """
        shapes = np.asarray(shapes, dtype=np.float64)
        single = shapes.ndim == 2
        shapes = shapes[None] if single else shapes
        if shapes.shape[1:] != self.mean.shape:
            raise ValueError(f"shapes must be (K, {self.n_vertices}, 3), got {shapes.shape}")
        basis = self.basis
        w, v = np.linalg.eigh(basis.T @ basis)
        cutoff = 1e-12 * max(float(w[-1]) if len(w) else 0.0, 1e-300)
        inv_w = np.where(w > cutoff, 1.0 / np.where(w > cutoff, w, 1.0), 0.0)
        coef = ((shapes - self.mean).reshape(len(shapes), -1) @ basis) @ (v * inv_w) @ v.T
        return coef[0] if single else coef

    def instances(self, coef: np.ndarray) -> np.ndarray:
        """Shapes (K, N, 3) for coefficient rows (K, M), in the model frame."""
        coef = np.asarray(coef, dtype=np.float64)
        if coef.ndim != 2 or coef.shape[1] != self.n_factors:
            raise ValueError(f"expected (K, {self.n_factors}) coefficients, got {coef.shape}")
        return self.mean + np.tensordot(coef, self.factors, axes=(1, 0))

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Map (N, 3) model-frame points to world coordinates with ``world_transform``."""
        t = self.world_transform
        return np.asarray(points, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]

    def world_instance(self, coef: np.ndarray | None = None) -> np.ndarray:
        """Shape for ``coef`` placed in world coordinates, (N, 3)."""
        return self.to_world(self.instance(coef))

    # ---- read-outs shared by the views (kept here so that app/ does no maths) ---------------
    def factor_magnitudes(self, sd: float = 1.0) -> np.ndarray:
        """(M, N) length of each vertex's displacement at ``sd`` standard deviations of each
        factor's coefficient, ``|sd| * sqrt(coef_var_m) * ||factors[m, i]||`` (mm)."""
        return abs(float(sd)) * np.linalg.norm(self.factors, axis=2) * \
            np.sqrt(self.coef_var)[:, None]

    def explained_variance(self) -> np.ndarray:
        """(M,) shape variance along each factor, ``coef_var_m * ||factor_m||^2`` (mm^2)."""
        return self.coef_var * np.sum(self.factors ** 2, axis=(1, 2))

    def explained_variance_share(self) -> np.ndarray:
        """(M,) each factor's share of the training shapes' variance about the mean.

        The fraction stored at build time (``info["explained_variance_ratio"]``: variance of the
        training shapes along each factor over their total variance, which sums to less than 1
        when the factors do not span the shapes) when the file has it; otherwise each factor's
        share of the model's own variance, :meth:`explained_variance` normalised to sum 1.
        """
        stored = self.info.get("explained_variance_ratio")
        if stored is not None and len(stored) == self.n_factors:
            return np.asarray(stored, dtype=np.float64)
        explained = self.explained_variance()
        total = float(explained.sum())
        return explained / total if total > 0 else np.zeros_like(explained)

    def world_factor_matrix(self) -> np.ndarray:
        """(3N, M) matrix B of world displacements, ``factors`` through ``world_transform``
        times ``sqrt(coef_var)``: the world shapes' covariance is ``B B^T`` whatever the
        factors' normalisation, order or sign."""
        lin = self.world_transform[:3, :3]
        world = np.einsum("mnj,ij->mni", self.factors, lin).reshape(self.n_factors, -1).T
        return world * np.sqrt(self.coef_var)

    def sample(self, n: int = 1, random_state: int | np.random.Generator | None = None
               ) -> np.ndarray:
        """``n`` random shapes (n, N, 3) in the model frame, coefficients ~ N(0, diag(coef_var))."""
        rng = np.random.default_rng(random_state)
        coef = rng.standard_normal((int(n), self.n_factors)) * np.sqrt(self.coef_var)
        return self.mean[None] + np.tensordot(coef, self.factors, axes=1)

    def distance_to_mean(self, shapes: np.ndarray) -> np.ndarray:
        """Per-vertex distance (K, N) of shapes (K, N, 3) (or (N,) for one (N, 3)) to the mean."""
        return np.linalg.norm(np.asarray(shapes, dtype=np.float64) - self.mean, axis=-1)


def covariance_gap(a: ShapeModel, b: ShapeModel) -> float:
    """``||C_a - C_b||_F / ||C_a||_F`` for the two models' world-shape covariances
    ``C = B B^T`` (:meth:`ShapeModel.world_factor_matrix`), computed from the small Gram
    matrices (``||B1 B1^T - B2 B2^T||_F^2 = ||B1^T B1||^2 + ||B2^T B2||^2 - 2 ||B1^T B2||^2``),
    never the 3N x 3N covariances: 0 when both describe the same Gaussian about their means
    (e.g. a model and its statismo PCA form)."""
    b1, b2 = a.world_factor_matrix(), b.world_factor_matrix()
    if b1.shape[0] != b2.shape[0]:
        raise ValueError(f"models of {a.n_vertices} and {b.n_vertices} vertices")
    g11, g22, g12 = b1.T @ b1, b2.T @ b2, b1.T @ b2
    norm = float(np.sum(g11 ** 2))
    gap = norm + float(np.sum(g22 ** 2)) - 2 * float(np.sum(g12 ** 2))
    return float(np.sqrt(max(gap, 0.0) / norm)) if norm > 0 else float(np.sqrt(max(gap, 0.0)))
