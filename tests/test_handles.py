"""core.registration.handles: the transforms that drags in a slice stand for (known transforms recovered)."""

from __future__ import annotations

import numpy as np
import pytest

from core.registration.handles import about_point, drag_transform


def apply(m, x):
    return np.asarray(x) @ m[:3, :3].T + m[:3, 3]


def test_translate_rotate_and_scale_drags():
    c = np.array([10.0, -4.0, 30.0])
    n = np.array([0.0, 0.0, 1.0])
    t = drag_transform("translate", [1, 2, 30], [4, -2, 30], c, n)
    np.testing.assert_allclose(apply(t, c), c + [3, -4, 0])
    # a quarter turn: (1, 0) -> (0, 1) about +z (right hand)
    r = drag_transform("rotate", c + [5, 0, 0], c + [0, 2, 0], c, n)
    np.testing.assert_allclose(apply(r, c + [1, 0, 0]), c + [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(apply(r, c), c, atol=1e-12)  # about the centre
    np.testing.assert_allclose(r[:3, :3] @ r[:3, :3].T, np.eye(3), atol=1e-12)
    # the same drag seen with the opposite normal is the same rotation
    np.testing.assert_allclose(drag_transform("rotate", c + [5, 0, 0], c + [0, 2, 0], c, -n), r,
                               atol=1e-12)
    s = drag_transform("scale", c + [2, 0, 0], c + [0, 3, 0], c, n)
    np.testing.assert_allclose(apply(s, c + [1, 1, 1]), c + 1.5 * np.ones(3))
    # clamped, and undefined at the centre
    assert drag_transform("scale", c + [1, 0, 0], c + [100, 0, 0], c, n)[0, 0] == 5.0
    np.testing.assert_array_equal(drag_transform("rotate", c, c + [1, 0, 0], c, n), np.eye(4))
    with pytest.raises(ValueError, match="move must be one of"):
        drag_transform("shear", c, c, c, n)


def test_oblique_slice_rotation_is_about_its_normal():
    rng = np.random.default_rng(2)
    n = rng.standard_normal(3)
    n /= np.linalg.norm(n)
    c = rng.normal(0, 50, 3)
    a = np.cross(n, [1.0, 0, 0])
    b = np.cross(n, a)
    r = drag_transform("rotate", c + 3 * a + 0.7 * n, c + 2 * b, c, n)  # off-plane part ignored
    np.testing.assert_allclose(apply(r, c + n), c + n, atol=1e-12)   # the axis stays
    np.testing.assert_allclose(apply(r, c + a / np.linalg.norm(a)),
                               c + b / np.linalg.norm(b), atol=1e-12)
    m = about_point(c, 2 * np.eye(3))
    np.testing.assert_allclose(apply(m, c), c)
