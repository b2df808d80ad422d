"""Plane/mesh intersection against analytic cross-sections (sphere, cube, torus)."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from core.geometry.slicing import intersect_plane, polylines, sample_polyline


def _arrays(poly: pv.PolyData) -> tuple[np.ndarray, np.ndarray]:
    poly = poly.triangulate().clean()
    return np.asarray(poly.points, dtype=np.float64), poly.faces.reshape(-1, 4)[:, 1:].astype(np.int64)


@pytest.fixture(scope="module")
def sphere():
    return _arrays(pv.Sphere(radius=2.0, theta_resolution=60, phi_resolution=60))


@pytest.fixture(scope="module")
def cube():
    return _arrays(pv.Cube(x_length=2.0, y_length=2.0, z_length=2.0).triangulate().subdivide(2))


def _signed_area(points: np.ndarray, normal: np.ndarray) -> float:
    return 0.5 * float(np.cross(points, np.roll(points, -1, axis=0)).sum(axis=0) @ normal)


def test_sphere_section_is_a_circle_on_the_plane(sphere):
    v, f = sphere
    normal = np.array([1.0, 2.0, 2.0]) / 3.0
    origin = 0.8 * normal
    seg = intersect_plane(v, f, origin, normal)
    assert seg.ndim == 3 and seg.shape[1:] == (2, 3) and len(seg) > 50
    assert np.abs((seg - origin) @ normal).max() < 1e-9          # on the plane
    radius = np.linalg.norm(seg.reshape(-1, 3) - origin, axis=1)
    expected = np.sqrt(2.0**2 - 0.8**2)
    assert np.abs(radius - expected).max() < 0.01 * expected     # on the circle (chord error)
    lines = polylines(v, f, origin, normal)
    assert len(lines) == 1 and lines[0].closed
    assert len(lines[0].points) == len(seg)
    assert lines[0].length == pytest.approx(2 * np.pi * expected, rel=0.01)
    # Counter-clockwise around the normal for an outward surface: positive signed area
    area = _signed_area(lines[0].points - origin, normal)
    assert area == pytest.approx(np.pi * expected**2, rel=0.02)


def test_cube_sections_exact_including_plane_through_vertices(cube):
    v, f = cube
    for height in (0.3, 0.0, 1.0):  # 0.0 and 1.0 pass exactly through vertices
        lines = polylines(v, f, [0.0, 0.0, height], [0.0, 0.0, 1.0])
        assert len(lines) == 1 and lines[0].closed, height
        assert lines[0].length == pytest.approx(8.0, abs=1e-9)
        assert _signed_area(lines[0].points, np.array([0.0, 0.0, 1.0])) == pytest.approx(4.0, abs=1e-9)


def test_torus_gives_two_loops_and_miss_gives_nothing():
    v, f = _arrays(pv.ParametricTorus(ringradius=2.0, crosssectionradius=0.5, u_res=60, v_res=30,
                                      w_res=30))
    lines = polylines(v, f, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])  # cuts the ring twice
    assert len(lines) == 2 and all(line.closed for line in lines)
    for line in lines:
        assert line.length == pytest.approx(2 * np.pi * 0.5, rel=0.02)
    assert intersect_plane(v, f, [0.0, 0.0, 5.0], [0.0, 0.0, 1.0]).shape == (0, 2, 3)
    with pytest.raises(ValueError, match="normal"):
        intersect_plane(v, f, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])


def test_sample_polyline_equal_steps(cube):
    v, f = cube
    line = polylines(v, f, [0.0, 0.0, 0.3], [0.0, 0.0, 1.0])[0]
    pts, tangents = sample_polyline(line, count=16)
    assert pts.shape == (16, 3)
    step = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
    # perimeter 8 in 16 steps: 0.5 along edges (chords across a corner are shorter)
    assert np.all(step <= 0.5 + 1e-9) and np.median(step) == pytest.approx(0.5)
    assert np.allclose(np.linalg.norm(tangents, axis=1), 1.0)
    assert np.allclose(tangents[:, 2], 0.0)


@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_simulated_user_draws_in_plane_contours_with_outward_normals(sphere, noise):
    from core.evaluation.simulated_user import simulate_user

    v, f = sphere
    user = simulate_user(v, f, 6, orientations="mixed", spacing=1.0, noise=noise,
                         rng=np.random.default_rng(0))
    assert len(user.planes) == 6 and set(np.unique(user.contour)) == set(range(6))
    normals_of_plane = np.array([n for _, n in user.planes])
    origins = np.array([o for o, _ in user.planes])
    # every point lies exactly in its slice plane (noise is in-plane)
    offset = np.einsum("ij,ij->i", user.points - origins[user.contour], normals_of_plane[user.contour])
    assert np.abs(offset).max() < 1e-9
    # on the sphere (up to chord error and noise); about 1 point per mm of contour
    r = np.linalg.norm(user.points, axis=1)
    assert np.abs(r - 2.0).max() < 0.02 + 4 * noise
    # unit, in-plane, outward normals: the in-plane radial direction
    assert np.allclose(np.linalg.norm(user.normals, axis=1), 1.0)
    assert np.abs(np.einsum("ij,ij->i", user.normals, normals_of_plane[user.contour])).max() < 1e-9
    radial = user.points - origins[user.contour]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    agreement = np.einsum("ij,ij->i", user.normals, radial)
    assert np.median(agreement) > (0.999 if noise == 0 else 0.8)
    assert agreement.min() > (0.99 if noise == 0 else -0.5)
