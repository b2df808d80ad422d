"""Linear shape models x = mean + Phi a learnt from shapes in correspondence.

One model type, :class:`core.models.shape_model.ShapeModel`; one estimator interface that learns it
(:class:`core.models.base.ShapeModelEstimator`, scikit-learn's contract) for every method:

- ``pca``: principal component analysis (global support);
- ``lsf``: local-support factors by graph-based structured matrix factorisation (Bernard et
  al., CVPR 2016) -- the product's distinguishing model;
- ``splocs``: sparse localised deformation components (Neumann et al., SIGGRAPH Asia 2013);
- ``varimax``: varimax-rotated PCA.

``make_model(method, **params)`` builds an estimator by name; ``model_from_shape_model``
rebuilds a fitted one from a :class:`core.models.shape_model.ShapeModel` (e.g. a loaded model file);
:func:`clone` gives an unfitted copy with the same parameters.
"""

from __future__ import annotations

from typing import Any

from core.models.base import ShapeModelEstimator, clone
from core.models.lsf import LSF
from core.models.pca import PCA
from core.models.shape_model import ShapeModel
from core.models.splocs import SPLOCS
from core.models.varimax import Varimax

MODELS: dict[str, type[ShapeModelEstimator]] = {
    "pca": PCA,
    "lsf": LSF,
    "splocs": SPLOCS,
    "varimax": Varimax,
}
METHODS = tuple(MODELS)


def model_class(method: str) -> type[ShapeModelEstimator]:
    """The estimator class for a method name (case-insensitive)."""
    key = str(method).strip().lower()
    if key not in MODELS:
        raise ValueError(f"unknown model method {method!r} (use one of {', '.join(METHODS)})")
    return MODELS[key]


def make_model(method: str, **params: Any) -> ShapeModelEstimator:
    """An unfitted estimator of ``method`` with ``params`` (unknown names raise ValueError)."""
    cls = model_class(method)
    valid = cls._param_names()
    unknown = sorted(set(params) - set(valid))
    if unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)} for method '{cls.method}' "
                         f"(valid: {', '.join(valid)})")
    return cls(**params)


def model_from_shape_model(model: ShapeModel) -> ShapeModelEstimator:
    """A fitted estimator holding the mean, factors and prior of ``model``."""
    return model_class(model.method).from_shape_model(model)


__all__ = ["ShapeModelEstimator", "clone", "PCA", "LSF", "SPLOCS", "Varimax", "MODELS", "METHODS",
           "make_model", "model_class", "model_from_shape_model"]
