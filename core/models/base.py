"""The estimator contract shared by every shape-model building method.

One model, one type: the model is a :class:`core.models.shape_model.ShapeModel` (mean, factors,
coefficient prior, mesh; the type the model file, the fit and the GUI use). The classes here are
its *learners* (scikit-learn estimators): ``fit`` learns a ShapeModel from shapes in
correspondence and keeps it as ``model_``; ``mean_``, ``factors_`` and ``coef_var_`` are that
model's arrays, and ``transform`` / ``inverse_transform`` are the model's own maths.

Conventions (scikit-learn's estimator contract, ``sklearn.base.BaseEstimator``):

- every parameter is a keyword of ``__init__``, stored unchanged; no work or validation there;
  ``get_params`` / ``set_params`` read the signature and :func:`clone` rebuilds an unfitted
  copy;
- the mesh graph is a parameter, ``connectivity`` (as scikit-learn's
  ``AgglomerativeClustering(connectivity=...)``): mesh triangles (F, 3) or a sparse (N, N)
  vertex adjacency; ``fit(X, y=None)`` takes only the shapes;
- parameter constraints are declared as data (``_parameter_constraints``, see
  :mod:`core.models._params`) and checked at the top of ``fit``;
- fitted attributes end in ``_``:

  - ``model_`` : ShapeModel; ``mean_`` (N, 3), ``factors_`` (M, N, 3), ``coef_var_`` (M,);
    factors ordered by decreasing variance they explain (``coef_var_[m] * ||factor_m||^2``),
    each with a deterministic sign (its largest-magnitude coordinate is positive);
  - ``coef_var_``: the (ddof = 1) variance of the least-squares coefficients of the training
    shapes (the diagonal prior a ~ N(0, diag(coef_var_)) the fit uses), ``coef_cov_`` (M, M)
    their full covariance (local factors' coefficients are correlated; :meth:`sample` and the
    specificity measure use it);
  - ``explained_variance_ratio_`` (M,): each factor's variance over the training shapes' total
    variance, computed from the current factors (it cannot fall out of step with them);
  - ``n_iter_`` / ``converged_`` for the iterative methods.
"""

from __future__ import annotations

import copy
import inspect
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import scipy.sparse as sp

from core.geometry.mesh import edges as mesh_edges
from core.models._params import editor_rule, is_data_parameter, validate_params
from core.models.shape_model import ShapeModel
from core.runtime.progress import ProgressCallback


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


def check_faces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Validate mesh triangles (F, 3) indexing ``n_vertices`` vertices; int64 copy."""
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


def check_connectivity(connectivity: Any, n_vertices: int, method: str,
                       required: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The mesh graph as (edges (E, 2) with i < j, faces (F, 3) or None).

    ``connectivity`` is mesh triangles (F, 3) or an (N, N) vertex adjacency (sparse or dense;
    nonzero entries are edges). None gives (None, None), or a ValueError if ``required``.
    """
    if connectivity is None:
        if required:
            raise ValueError(f"method '{method}' needs the mesh graph: pass the mesh triangles "
                             "(F, 3) or an (N, N) vertex adjacency as connectivity=...")
        return None, None
    if sp.issparse(connectivity) or (np.ndim(connectivity) == 2
                                     and np.shape(connectivity) == (n_vertices, n_vertices)
                                     and n_vertices != 3):
        adj = sp.coo_matrix(connectivity)
        if adj.shape != (n_vertices, n_vertices):
            raise ValueError(f"connectivity must be ({n_vertices}, {n_vertices}) for "
                             f"{n_vertices} vertices, got {adj.shape}")
        keep = (adj.data != 0) & (adj.row != adj.col)
        pairs = np.sort(np.stack([adj.row[keep], adj.col[keep]], axis=1), axis=1)
        edges = np.unique(pairs, axis=0).astype(np.int64)
        if len(edges) == 0:
            raise ValueError("connectivity has no edges")
        return edges, None
    faces = check_faces(connectivity, n_vertices)
    return mesh_edges(faces), faces


def edge_adjacency(edges: np.ndarray, n_vertices: int,
                   weights: np.ndarray | None = None) -> sp.csr_matrix:
    """Symmetric (N, N) adjacency of undirected ``edges`` (E, 2), entries ``weights`` (or 1)."""
    w = np.ones(len(edges)) if weights is None else np.asarray(weights, dtype=np.float64)
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    return sp.csr_matrix((np.concatenate([w, w]), (rows, cols)), shape=(n_vertices, n_vertices))


def clone(estimator: ShapeModelEstimator) -> ShapeModelEstimator:
    """An unfitted estimator with the same parameters (deep copies), like ``sklearn.clone``."""
    params = {k: copy.deepcopy(v) for k, v in estimator.get_params(deep=False).items()}
    return type(estimator)(**params)


class ShapeModelEstimator:
    """Base class of the learners of a linear shape model ``x = mean + Phi a``.

    Subclasses set :attr:`method`, declare ``_parameter_constraints`` and implement
    ``_fit(X, progress) -> (mean (N, 3), factors (M, N, 3))``; the graph-based ones set
    ``needs_graph`` and read ``self._graph_edges()`` (E, 2). This class validates the input, computes
    the coefficient prior, orders and signs the factors and builds ``model_``.
    """

    method: ClassVar[str] = ""
    needs_graph: ClassVar[bool] = False
    _parameter_constraints: ClassVar[dict[str, list]] = {}
    # Values of parameters added later, for model files saved before they existed (their
    # models were built with the old behaviour, not with today's default).
    _legacy_params: ClassVar[dict[str, Any]] = {}

    # ---- scikit-learn style parameter handling -----------------------------------------
    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p.name for p in sig.parameters.values() if p.name != "self"]

    @classmethod
    def setting_names(cls) -> list[str]:
        """The parameters that are settings (everything except data such as the mesh graph)."""
        return [n for n in cls._param_names()
                if not is_data_parameter(cls._parameter_constraints.get(n))]

    @classmethod
    def parameter_rule(cls, name: str) -> tuple | None:
        """A summary of parameter ``name``'s constraints for an editor widget
        (see :func:`core.models._params.editor_rule`)."""
        return editor_rule(cls._parameter_constraints.get(name))

    def get_params(self, deep: bool = True) -> dict[str, Any]:
        """The constructor parameters, by name."""
        return {name: getattr(self, name) for name in self._param_names()}

    def set_params(self, **params: Any) -> ShapeModelEstimator:
        """Set constructor parameters; unknown names raise ValueError."""
        valid = self._param_names()
        for name, value in params.items():
            if name not in valid:
                raise ValueError(f"unknown parameter {name!r} for {type(self).__name__} "
                                 f"(valid: {', '.join(valid)})")
            setattr(self, name, value)
        return self

    def __repr__(self) -> str:
        args = []
        for k, v in self.get_params().items():
            if isinstance(v, np.ndarray) or sp.issparse(v):
                v = f"<{type(v).__name__} {v.shape}>"
                args.append(f"{k}={v}")
            else:
                args.append(f"{k}={v!r}")
        return f"{type(self).__name__}({', '.join(args)})"

    def _validate_params(self) -> None:
        validate_params(self._parameter_constraints, self.get_params(), type(self).__name__)

    # ---- fitting ------------------------------------------------------------------------
    def fit(self, X: np.ndarray, y: None = None, *,
            progress: ProgressCallback | None = None) -> ShapeModelEstimator:
        """Learn the model from shapes in correspondence, aligned.

        Parameters
        ----------
        X : (K, N, 3) float array
            Training shapes (vertex k of every shape corresponds).
        y : None
            Ignored (scikit-learn convention). The mesh graph is the ``connectivity``
            parameter, not an argument of ``fit``.
        progress : callable(fraction, message), optional
            Called at least once per outer iteration; may raise ``core.runtime.progress.Cancelled``.

        Returns
        -------
        self
        """
        if y is not None:
            raise ValueError(f"{type(self).__name__}.fit takes only the shapes: pass the mesh "
                             "as connectivity=... when creating the estimator")
        self._validate_params()
        X = check_shapes(X)
        self._edges, self._faces = check_connectivity(
            getattr(self, "connectivity", None), X.shape[1], self.method, self.needs_graph)
        mean, factors = self._fit(X, progress)
        self._set_model(mean, factors, X)
        return self

    def _fit(self, X: np.ndarray, progress: ProgressCallback | None
             ) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _graph_edges(self) -> np.ndarray:
        """The mesh graph's edges (E, 2) of a graph-based method (``needs_graph``), set by fit."""
        if self._edges is None:
            raise ValueError(f"method '{self.method}' needs the mesh graph: pass connectivity=...")
        return self._edges

    def _set_model(self, mean: np.ndarray, factors: np.ndarray, X: np.ndarray) -> None:
        """Drop zero factors, compute the prior, sort and sign factors, build ``model_``."""
        n = mean.shape[0]
        factors = np.asarray(factors, dtype=np.float64).reshape(-1, n, 3)
        norms = np.linalg.norm(factors.reshape(len(factors), -1), axis=1)
        factors = factors[norms > 1e-12 * max(float(norms.max(initial=0.0)), 1e-300)]
        if len(factors) == 0:
            raise ValueError(f"{type(self).__name__} found no deformation factor (all factors "
                             "are zero); lower the regularisation or check the shapes vary")
        draft = self._shape_model(mean, factors, np.ones(len(factors)))
        coef = draft.project(X)
        var = coef.var(axis=0, ddof=1)
        explained = var * np.sum(factors ** 2, axis=(1, 2))
        order = np.argsort(-explained, kind="stable")
        flat = factors[order].reshape(len(order), -1)
        # Deterministic sign: the largest-magnitude coordinate of each factor is positive.
        signs = np.sign(flat[np.arange(len(flat)), np.argmax(np.abs(flat), axis=1)])
        signs[signs == 0] = 1.0
        coef = coef[:, order] * signs
        var = var[order]
        floor = max(1e-12 * float(var.max(initial=0.0)), 1e-300)
        self.total_variance_ = float(np.sum(X.var(axis=0, ddof=1)))
        self.coef_cov_ = np.atleast_2d(np.cov(coef, rowvar=False, ddof=1))
        self.model_ = self._shape_model(mean, factors[order] * signs[:, None, None],
                                        np.maximum(var, floor))

    def _shape_model(self, mean, factors, coef_var) -> ShapeModel:
        return ShapeModel(mean=mean, factors=factors, coef_var=coef_var,
                          faces=self._faces if self._faces is not None else np.zeros((0, 3)),
                          method=self.method)

    # ---- the fitted model ----------------------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "model_"):
            raise ValueError(f"this {type(self).__name__} is not fitted yet: call fit(X) first")

    @property
    def mean_(self) -> np.ndarray:
        """(N, 3) mean shape."""
        self._check_fitted()
        return self.model_.mean

    @property
    def factors_(self) -> np.ndarray:
        """(M, N, 3) deformation factors."""
        self._check_fitted()
        return self.model_.factors

    @property
    def coef_var_(self) -> np.ndarray:
        """(M,) prior variance of each coefficient."""
        self._check_fitted()
        return self.model_.coef_var

    @property
    def n_factors_(self) -> int:
        self._check_fitted()
        return self.model_.n_factors

    @property
    def basis_(self) -> np.ndarray:
        """Factors as the (3N, M) matrix Phi (vec(x) = vec(mean) + Phi a)."""
        self._check_fitted()
        return self.model_.basis

    @property
    def explained_variance_ratio_(self) -> np.ndarray:
        """(M,) variance along each factor (``coef_var_ * ||factor||^2``) over the training
        shapes' total variance (for PCA: the eigenvalue ratios)."""
        self._check_fitted()
        explained = self.coef_var_ * np.sum(self.factors_ ** 2, axis=(1, 2))
        return explained / max(getattr(self, "total_variance_", explained.sum()), 1e-300)

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Least-squares coefficients (K, M) of shapes X (K, N, 3) (or one shape (N, 3) -> (M,))."""
        self._check_fitted()
        return self.model_.project(X)

    def inverse_transform(self, A: np.ndarray) -> np.ndarray:
        """Shapes (K, N, 3) for coefficients A (K, M) (or one vector (M,) -> (N, 3))."""
        self._check_fitted()
        A = np.asarray(A, dtype=np.float64)
        if A.ndim == 1:
            return self.model_.instance(A)
        return self.model_.instances(A)

    def sample(self, n: int = 1, random_state: int | np.random.Generator | None = None,
               covariance: str = "full") -> np.ndarray:
        """Draw ``n`` shapes (n, N, 3) with coefficients from the fitted distribution.

        ``covariance="full"``: N(0, coef_cov_), the training coefficients' covariance (the
        model's real coefficient distribution); ``"diag"``: N(0, diag(coef_var_)), the prior
        the fit uses and the model file keeps.
        """
        self._check_fitted()
        rng = np.random.default_rng(random_state)
        z = rng.standard_normal((int(n), self.n_factors_))
        if covariance == "diag" or not hasattr(self, "coef_cov_"):
            return self.inverse_transform(z * np.sqrt(self.coef_var_))
        if covariance != "full":
            raise ValueError(f"covariance must be 'full' or 'diag'; got {covariance!r}")
        w, v = np.linalg.eigh(self.coef_cov_)
        root = v * np.sqrt(np.maximum(w, 0.0))  # coef_cov_ = root root^T (PSD, maybe singular)
        return self.inverse_transform(z @ root.T)

    def to_shape_model(self, faces: np.ndarray | None = None,
                       world_transform: np.ndarray | None = None,
                       source_meshes: Sequence[str] = (), info: dict | None = None) -> ShapeModel:
        """The fitted model with its mesh, placement and metadata (saved with
        ``core.io.save_model``). ``faces`` defaults to the triangles given as connectivity."""
        self._check_fitted()
        faces = self.model_.faces if faces is None else np.asarray(faces)
        if len(faces) == 0:
            raise ValueError("the model needs mesh triangles: pass faces=... (it was fitted "
                             "without connectivity triangles)")
        params = {k: _jsonable(v) for k, v in self.get_params().items()
                  if k in self.setting_names()}
        meta = {"explained_variance_ratio": [float(r) for r in self.explained_variance_ratio_],
                "total_variance": self.total_variance_} if hasattr(self, "total_variance_") else {}
        meta.update(info or {})
        return ShapeModel(mean=self.mean_.copy(), factors=self.factors_.copy(),
                          coef_var=self.coef_var_.copy(), faces=faces,
                          world_transform=np.eye(4) if world_transform is None else world_transform,
                          method=self.method, params=params, source_meshes=list(source_meshes),
                          info=meta)

    @classmethod
    def from_shape_model(cls, model: ShapeModel) -> ShapeModelEstimator:
        """A fitted estimator holding ``model`` (e.g. one loaded from file)."""
        params = {k: v for k, v in model.params.items() if k in cls.setting_names()}
        if model.params:
            params = {**cls._legacy_params, **params}
        est = cls(**params)
        est.model_ = model
        if "total_variance" in model.info:
            est.total_variance_ = float(model.info["total_variance"])
        return est


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


__all__ = ["ShapeModelEstimator", "clone", "check_shapes", "check_faces", "check_connectivity",
           "edge_adjacency"]
