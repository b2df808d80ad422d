"""Moving a model by hand: the similarity transform that a mouse drag in a slice stands for.

A drag from world point ``a`` to ``b`` on a slice (both in the slice plane) moves the model
about its centre ``c`` (projected on the slice) in one of three ways, as the "transform" handles
of 3D Slicer and ITK-SNAP do:

- ``"translate"``: by ``b - a``;
- ``"rotate"``: about the slice normal ``n`` through ``c``, by the signed angle from
  ``a - c`` to ``b - c`` (right hand around ``n``);
- ``"scale"``: uniformly about ``c`` by ``|b - c| / |a - c|`` (clamped to [0.2, 5] per drag).

The result is a 4x4 world transform ``M`` (column vectors) to apply *after* the model's pose:
``pose' = M @ pose``. Rotation matrices come from ``core.geometry.toolkit.rodrigues``.
"""

from __future__ import annotations

import numpy as np

from core.geometry.toolkit import rodrigues

__all__ = ["MOVES", "drag_transform", "about_point"]

MOVES = ("translate", "rotate", "scale")
SCALE_LIMITS = (0.2, 5.0)


def about_point(center: np.ndarray, linear: np.ndarray) -> np.ndarray:
    """4x4 transform applying the 3x3 ``linear`` part about ``center``: x -> L (x - c) + c."""
    center = np.asarray(center, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = linear
    out[:3, 3] = center - np.asarray(linear) @ center
    return out


def drag_transform(kind: str, start: np.ndarray, end: np.ndarray, center: np.ndarray,
                   normal: np.ndarray) -> np.ndarray:
    """The world transform (4, 4) for a ``kind`` drag from ``start`` to ``end`` (world mm).

    ``center`` is the model's centre and ``normal`` the slice normal; both points are taken
    in the slice plane through ``center`` (their components along ``normal`` are ignored for
    rotation and scale). A drag too close to the centre to define an angle or a ratio
    (< 1e-6 mm) gives the identity.
    """
    if kind not in MOVES:
        msg = f"move must be one of {', '.join(MOVES)}; got {kind!r}"
        raise ValueError(msg)
    start = np.asarray(start, dtype=np.float64)
    end = np.asarray(end, dtype=np.float64)
    if kind == "translate":
        out = np.eye(4)
        out[:3, 3] = end - start
        return out
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    c = np.asarray(center, dtype=np.float64)
    a = (start - c) - ((start - c) @ n) * n
    b = (end - c) - ((end - c) @ n) * n
    la, lb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    if la < 1e-6 or lb < 1e-6:
        return np.eye(4)
    if kind == "rotate":
        angle = float(np.arctan2(np.cross(a, b) @ n, a @ b))
        return about_point(c, rodrigues(angle * n))
    factor = float(np.clip(lb / la, *SCALE_LIMITS))
    return about_point(c, factor * np.eye(3))
