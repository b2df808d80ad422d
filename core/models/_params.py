"""Parameter constraints declared as data, the scikit-learn way (``sklearn.utils._param_validation``).

Each estimator class maps parameter names to a list of accepted forms; a value is valid if it
matches any of them::

    _parameter_constraints = {"n_factors": [Interval(Integral, 1, None), None],
                              "graph": [StrOptions({"mesh", "euclidean"})],
                              "connectivity": ["array-like", "sparse matrix", None]}

Forms: an :class:`Interval` (``Integral`` or ``Real``, bounds, which ends are closed), a
:class:`StrOptions`, ``"boolean"``, ``"array-like"``, ``"sparse matrix"``, ``"random_state"``
(None or a non-negative int) and ``None`` (the value None). :func:`validate_params` checks
them at the top of ``fit``; :func:`editor_rule` summarises them for a parameter form.
"""

from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

import numpy as np
import scipy.sparse as sp


@dataclass(frozen=True)
class Interval:
    """Numbers of ``type`` (``Integral`` or ``Real``) between ``left`` and ``right``
    (None: unbounded); ``closed`` is "both", "left", "right" or "neither"."""

    type: type
    left: float | None
    right: float | None
    closed: str = "both"

    def __contains__(self, value: Any) -> bool:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (Real, np.number)):
            return False
        if self.type is Integral and not float(value).is_integer():
            return False
        v = float(value)
        if not np.isfinite(v):
            return False
        if self.left is not None:
            if v < self.left or (v == self.left and self.closed in ("right", "neither")):
                return False
        if self.right is not None:
            if v > self.right or (v == self.right and self.closed in ("left", "neither")):
                return False
        return True

    def __str__(self) -> str:
        lo = "-inf" if self.left is None else f"{self.left:g}"
        hi = "inf" if self.right is None else f"{self.right:g}"
        left = "[" if self.closed in ("both", "left") and self.left is not None else "("
        right = "]" if self.closed in ("both", "right") and self.right is not None else ")"
        kind = "an int" if self.type is Integral else "a float"
        return f"{kind} in the range {left}{lo}, {hi}{right}"


@dataclass(frozen=True)
class StrOptions:
    """One of a set of strings."""

    options: tuple

    def __init__(self, options):
        object.__setattr__(self, "options", tuple(options))  # ordered: the form lists them so

    def __contains__(self, value: Any) -> bool:
        return isinstance(value, str) and value in self.options

    def __str__(self) -> str:
        return "a str among {" + ", ".join(repr(o) for o in self.options) + "}"


def _matches(value: Any, form: Any) -> bool:
    if form is None:
        return value is None
    if isinstance(form, (Interval, StrOptions)):
        return value in form
    if form == "boolean":
        return isinstance(value, (bool, np.bool_))
    if form == "random_state":
        return value is None or value in Interval(Integral, 0, None)
    if form == "sparse matrix":
        return sp.issparse(value)
    if form == "array-like":
        return isinstance(value, (np.ndarray, list, tuple)) and not sp.issparse(value)
    raise TypeError(f"unknown constraint {form!r}")


def _describe(form: Any) -> str:
    if form is None:
        return "None"
    if form == "random_state":
        return "None or a non-negative int"
    if form == "boolean":
        return "True or False"
    return str(form) if isinstance(form, (Interval, StrOptions)) else f"an {form}" \
        if form.startswith("a") else f"a {form}"


def validate_params(constraints: dict[str, list], params: dict[str, Any], caller: str) -> None:
    """Raise ValueError naming the first parameter whose value matches none of its forms."""
    for name, forms in constraints.items():
        if name not in params:
            continue
        value = params[name]
        if any(_matches(value, form) for form in forms):
            continue
        allowed = " or ".join(_describe(f) for f in forms)
        raise ValueError(f"The {name!r} parameter of {caller} must be {allowed}; got {value!r}")


DATA_FORMS = ("array-like", "sparse matrix")


def is_data_parameter(forms: list | None) -> bool:
    """True for parameters holding data (e.g. a mesh graph) rather than a setting."""
    return forms is not None and any(isinstance(f, str) and f in DATA_FORMS for f in forms)


def editor_rule(forms: list | None) -> tuple | None:
    """A summary of a parameter's forms for an editor widget.

    ``("int"|"float", low, high, allow_none)``, ``("options", choices)``, ``("bool",)`` or None
    (no rule: free text).
    """
    if not forms:
        return None
    allow_none = any(f is None or f == "random_state" for f in forms)
    for form in forms:
        if isinstance(form, Interval):
            kind = "int" if form.type is Integral else "float"
            return (kind, form.left, form.right, allow_none)
        if form == "random_state":
            return ("int", 0, None, True)
        if isinstance(form, StrOptions):
            return ("options", tuple(form.options))
        if form == "boolean":
            return ("bool",)
    return None


__all__ = ["Interval", "StrOptions", "Integral", "Real", "validate_params", "editor_rule",
           "is_data_parameter"]
