"""The estimator contract shared by every shape-model building method.

A model approximates shapes in correspondence (K, N, 3) as ``x = mean + sum_m a_m * factor_m``.
All methods (PCA, LSF, SPLOCS, Varimax) follow the scikit-learn conventions: parameters are
stored unchanged by ``__init__``, ``fit(X, faces=None)`` validates its input and returns
``self``, fitted attributes end in ``_``:

- ``mean_`` (N, 3): mean shape;
- ``factors_`` (M, N, 3): deformation factors (same layout as :class:`core.shape_model.ShapeModel`),
  ordered by decreasing variance they explain (``coef_var_[m] * ||factor_m||^2``), each with a
  deterministic sign (its largest-magnitude coordinate is positive);
- ``coef_var_`` (M,): the (ddof = 1) variance of the least-squares coefficients of the training
  shapes, > 0: the Gaussian prior a ~ N(0, diag(coef_var_)) used by fitting and sampling;
- ``n_iter_`` / ``converged_`` for the iterative methods.

Coefficients are least-squares coefficients: for non-orthogonal factors :meth:`transform` solves
the normal equations (through the pseudo-inverse of the basis, which also copes with factors
that are numerically dependent).
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np

from core.progress import ProgressCallback
from core.shape_model import ShapeModel


def check_shapes(X: np.ndarray, name: str = "X", min_shapes: int = 2) -> np.ndarray:
    """Validate a stack of shapes in correspondence; return it as float64 (K, N, 3)."""
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"{name} must be a (K, N, 3) array of K shapes with N vertices, "
                         f"got shape {X.shape}")
    if X.shape[0] < min_shapes:
        raise ValueError(f"{name} needs at least {min_shapes} shapes, got {X.shape[0]}")
    if X.shape[1] < 4:
        raise ValueError(f"{name} needs at least 4 vertices per shape, got {X.shape[1]}")
    if not np.all(np.isfinite(X)):
        raise ValueError(f"{name} contains NaN or infinite coordinates")
    return X


def check_faces(faces: np.ndarray | None, n_vertices: int, method: str) -> np.ndarray:
    """Validate mesh faces (F, 3) for ``n_vertices`` vertices (needed by graph-based methods)."""
    if faces is None:
        raise ValueError(f"method '{method}' needs the mesh faces (F, 3) to build its vertex "
                         "graph: call fit(X, faces=...)")
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"faces must be an (F, 3) array of triangles, got shape {faces.shape}")
    if not np.issubdtype(faces.dtype, np.integer):
        if not np.all(faces == np.round(faces)):
            raise ValueError("faces must contain integer vertex indices")
    faces = faces.astype(np.int64)
    if faces.min() < 0 or faces.max() >= n_vertices:
        raise ValueError(f"faces index vertices outside 0..{n_vertices - 1}")
    return faces


def _check_param(name: str, value: Any, rule: tuple) -> None:
    kind = rule[0]
    if kind == "options":
        if value not in rule[1]:
            raise ValueError(f"{name} must be one of {', '.join(map(repr, rule[1]))}; got {value!r}")
        return
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"{name} must be True or False; got {value!r}")
        return
    low, high, allow_none = rule[1], rule[2], (len(rule) > 3 and rule[3])
    if value is None:
        if allow_none:
            return
        raise ValueError(f"{name} must be a number; got None")
    if kind == "int" and (isinstance(value, bool) or not float(value).is_integer()):
        raise ValueError(f"{name} must be an integer; got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number; got {value!r}") from None
    if not np.isfinite(v) or (low is not None and v < low) or (high is not None and v > high):
        rng = f"[{low if low is not None else '-inf'}, {high if high is not None else 'inf'}]"
        raise ValueError(f"{name} must be in {rng}; got {value!r}")


class DeformationModel:
    """Base class: a linear shape model ``x = mean + Phi a`` learnt from shapes (K, N, 3).

    Subclasses set :attr:`method`, declare ``_parameter_constraints`` (name -> rule) and
    implement ``_fit(X, faces, progress) -> (mean (N, 3), factors (M, N, 3))``; this class
    validates input, computes the coefficient prior, orders and signs the factors.
    """

    method: ClassVar[str] = ""
    needs_faces: ClassVar[bool] = False
    _parameter_constraints: ClassVar[dict[str, tuple]] = {}

    # ---- scikit-learn style parameter handling -----------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values() if p.name != "self"]

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor parameters, by name."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params: Any) -> DeformationModel:
        """Set constructor parameters; unknown names raise ValueError."""
        valid = self._param_names()
        for name, value in params.items():
            if name not in valid:
                raise ValueError(f"unknown parameter {name!r} for {type(self).__name__} "
                                 f"(valid: {', '.join(valid)})")
            setattr(self, name, value)
        return self

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"

    def _validate_params(self) -> None:
        for name, rule in self._parameter_constraints.items():
            _check_param(name, getattr(self, name), rule)

    # ---- fitting ------------------------------------------------------------------------
    def fit(self, X: np.ndarray, faces: np.ndarray | None = None, *,
            progress: ProgressCallback | None = None) -> DeformationModel:
        """Learn the model from shapes in correspondence, aligned.

        Parameters
        ----------
        X : (K, N, 3) float array
            Training shapes (vertex k of every shape corresponds).
        faces : (F, 3) int array, optional
            Mesh triangles (required by the graph-based methods LSF and SPLOCS).
        progress : callable(fraction, message), optional
            Called at least once per outer iteration; may raise ``core.progress.Cancelled``.

        Returns
        -------
        self
        """
        self._validate_params()
        X = check_shapes(X)
        if faces is not None or self.needs_faces:
            faces = check_faces(faces, X.shape[1], self.method)
        mean, factors = self._fit(X, faces, progress)
        self._set_model(mean, factors, X)
        return self

    def _fit(self, X: np.ndarray, faces: np.ndarray | None,
             progress: ProgressCallback | None) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _set_model(self, mean: np.ndarray, factors: np.ndarray, X: np.ndarray) -> None:
        """Store mean/factors, drop zero factors, compute the prior, sort and sign factors."""
        n = mean.shape[0]
        factors = np.asarray(factors, dtype=np.float64).reshape(-1, n, 3)
        norms = np.linalg.norm(factors.reshape(len(factors), -1), axis=1)
        keep = norms > 1e-12 * max(float(norms.max(initial=0.0)), 1e-300)
        factors = factors[keep]
        if len(factors) == 0:
            raise ValueError(f"{type(self).__name__} found no deformation factor (all factors "
                             "are zero); lower the regularisation or check the shapes vary")
        self.mean_ = np.asarray(mean, dtype=np.float64)
        self.factors_ = factors
        self._cache_basis()
        coef = self.transform(X)
        var = coef.var(axis=0, ddof=1) if len(X) > 1 else np.ones(len(factors))
        explained = var * np.linalg.norm(factors.reshape(len(factors), -1), axis=1) ** 2
        order = np.argsort(-explained, kind="stable")
        factors = factors[order]
        var = var[order]
        # Deterministic sign: the largest-magnitude coordinate of each factor is positive.
        flat = factors.reshape(len(factors), -1)
        signs = np.sign(flat[np.arange(len(flat)), np.argmax(np.abs(flat), axis=1)])
        signs[signs == 0] = 1.0
        self.factors_ = factors * signs[:, None, None]
        floor = 1e-12 * max(float(var.max(initial=0.0)), 1e-300)
        self.coef_var_ = np.maximum(var, max(floor, 1e-300))
        self._cache_basis()

    def _cache_basis(self) -> None:
        basis = self.factors_.reshape(len(self.factors_), -1).T  # (3N, M)
        # Normal equations: pinv(Phi) = (Phi^T Phi)^+ Phi^T, the (M, M) Gram matrix inverted
        # by eigendecomposition with a relative cut-off for (numerically) dependent factors.
        gram = basis.T @ basis
        w, v = np.linalg.eigh(gram)
        cutoff = 1e-12 * max(float(w[-1]), 1e-300)
        inv_w = np.where(w > cutoff, 1.0 / np.where(w > cutoff, w, 1.0), 0.0)
        self._pinv = (v * inv_w) @ v.T @ basis.T

    # ---- using a fitted model ----------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "factors_"):
            raise ValueError(f"this {type(self).__name__} is not fitted yet: call fit(X) first")

    @property
    def n_factors_(self) -> int:
        self._check_fitted()
        return int(self.factors_.shape[0])

    @property
    def basis_(self) -> np.ndarray:
        """Factors as the (3N, M) matrix Phi (vec(x) = vec(mean) + Phi a)."""
        self._check_fitted()
        return self.factors_.reshape(len(self.factors_), -1).T

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Least-squares coefficients (K, M) of shapes X (K, N, 3) (or one shape (N, 3) -> (M,))."""
        self._check_fitted()
        X = np.asarray(X, dtype=np.float64)
        single = X.ndim == 2
        X = X[None] if single else X
        if X.shape[1:] != self.mean_.shape:
            raise ValueError(f"shapes must be (K, {self.mean_.shape[0]}, 3), got {X.shape}")
        d = (X - self.mean_).reshape(len(X), -1)
        coef = d @ self._pinv.T
        return coef[0] if single else coef

    def inverse_transform(self, A: np.ndarray) -> np.ndarray:
        """Shapes (K, N, 3) for coefficients A (K, M) (or one vector (M,) -> (N, 3))."""
        self._check_fitted()
        A = np.asarray(A, dtype=np.float64)
        single = A.ndim == 1
        A = A[None] if single else A
        if A.shape[1] != self.n_factors_:
            raise ValueError(f"expected {self.n_factors_} coefficients per shape, got {A.shape[1]}")
        X = self.mean_ + np.tensordot(A, self.factors_, axes=(1, 0))
        return X[0] if single else X

    def sample(self, n: int = 1, random_state: int | np.random.Generator | None = None) -> np.ndarray:
        """Draw ``n`` shapes (n, N, 3) with coefficients from N(0, diag(coef_var_))."""
        self._check_fitted()
        rng = np.random.default_rng(random_state)
        coef = rng.standard_normal((int(n), self.n_factors_)) * np.sqrt(self.coef_var_)
        return self.inverse_transform(coef)

    def to_shape_model(self, faces: np.ndarray, world_transform: np.ndarray | None = None,
                       source_meshes: Sequence[str] = (), info: dict | None = None) -> ShapeModel:
        """The fitted model as a :class:`ShapeModel` (saved with ``core.io.save_model``)."""
        self._check_fitted()
        params = {k: _jsonable(v) for k, v in self.get_params().items()}
        return ShapeModel(mean=self.mean_.copy(), factors=self.factors_.copy(),
                          coef_var=self.coef_var_.copy(), faces=np.asarray(faces),
                          world_transform=np.eye(4) if world_transform is None else world_transform,
                          method=self.method, params=params, source_meshes=list(source_meshes),
                          info=dict(info or {}))

    @classmethod
    def from_shape_model(cls, model: ShapeModel) -> DeformationModel:
        """Rebuild a fitted estimator from a :class:`ShapeModel` (e.g. one loaded from file)."""
        params = {k: v for k, v in model.params.items() if k in cls._param_names()}
        est = cls(**params)
        est.mean_ = model.mean.copy()
        est.factors_ = model.factors.copy()
        est.coef_var_ = model.coef_var.copy()
        est._cache_basis()
        return est


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value
