"""World-aligned slice sampling (core.geometry.planes): the pixel under a world point shows that voxel."""

from __future__ import annotations

import numpy as np
import pytest

from core.geometry.planes import (
    AXIAL,
    CORONAL,
    FRAMES,
    SAGITTAL,
    SliceSampler,
    auto_window,
    contour_normals,
    window_to_uint8,
)
from core.io import Volume


def _volume(affine_dir: np.ndarray, shape=(12, 14, 10), seed=0) -> Volume:
    rng = np.random.default_rng(seed)
    affine = np.eye(4)
    affine[:3, :3] = affine_dir
    affine[:3, 3] = [-7.0, 3.0, 11.0]
    return Volume(rng.normal(size=shape).astype(np.float32), affine)


PERMUTED_FLIPPED = np.array([[0.0, -2.0, 0.0], [0.0, 0.0, 1.5], [1.0, 0.0, 0.0]])
ROTATED = np.array([[np.cos(0.3), -np.sin(0.3), 0.0], [np.sin(0.3), np.cos(0.3), 0.0], [0, 0, 1.2]])


def _pixel_value(sampler, frame, xyz):
    sl = sampler.sample(frame, frame.depth(xyz))
    u, v, _ = frame.to_plane(xyz)
    col = (u - sl.u0) / sl.du
    row = (sl.v0 - v) / sl.dv
    return sl, col, row


@pytest.mark.parametrize("direction", [np.diag([1.0, 1.0, 1.0]), np.diag([-1.0, 2.0, 1.5]),
                                       PERMUTED_FLIPPED])
@pytest.mark.parametrize("frame", [AXIAL, CORONAL, SAGITTAL])
def test_aligned_slice_pixel_is_the_voxel(direction, frame):
    vol = _volume(direction)
    sampler = SliceSampler(vol)
    assert sampler.aligned
    rng = np.random.default_rng(1)
    for ijk in rng.integers(0, vol.shape, size=(20, 3)):
        xyz = vol.voxel_to_world(ijk)
        sl, col, row = _pixel_value(sampler, frame, xyz)
        assert sl.inside and abs(sl.depth - frame.depth(xyz)) < 1e-9
        assert np.allclose([col, row], np.rint([col, row]), atol=1e-9)
        assert sl.data[int(round(row)), int(round(col))] == pytest.approx(vol.data[tuple(ijk)])


@pytest.mark.parametrize("frame", [AXIAL, CORONAL, SAGITTAL])
def test_oblique_path_agrees_with_aligned(frame):
    vol = _volume(np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]]))
    fast = SliceSampler(vol)
    slow = SliceSampler(vol)
    slow.aligned = False
    ijk = np.array([5, 6, 4])
    xyz = vol.voxel_to_world(ijk)
    a = fast.sample(frame, frame.depth(xyz))
    b = slow.sample(frame, frame.depth(xyz))
    u, v, _ = frame.to_plane(xyz)
    ca, ra = (u - a.u0) / a.du, (a.v0 - v) / a.dv
    cb, rb = (u - b.u0) / b.du, (b.v0 - v) / b.dv
    assert np.isclose(cb, round(cb)) and np.isclose(rb, round(rb))
    assert b.data[int(round(rb)), int(round(cb))] == pytest.approx(a.data[int(round(ra)), int(round(ca))])


def test_oblique_volume_resamples_the_rotated_voxel():
    vol = _volume(ROTATED, shape=(20, 20, 8))
    sampler = SliceSampler(vol)
    assert not sampler.aligned
    ijk = np.array([9, 11, 3])
    xyz = vol.voxel_to_world(ijk)
    sl = sampler.sample(AXIAL, AXIAL.depth(xyz))
    u, v, _ = AXIAL.to_plane(xyz)
    col, row = (u - sl.u0) / sl.du, (sl.v0 - v) / sl.dv
    # trilinear value at the exact fractional pixel equals the voxel value
    from scipy import ndimage
    val = ndimage.map_coordinates(sl.data.astype(np.float64), [[row], [col]], order=1)[0]
    neighbours = sl.data[int(np.floor(row)):int(np.floor(row)) + 2, int(np.floor(col)):int(np.floor(col)) + 2]
    assert np.all(np.isfinite(neighbours))
    assert abs(val - vol.data[tuple(ijk)]) < 1.5 * np.abs(np.diff(neighbours.ravel())).max() + 1e-6


def test_edge_labels_radiological():
    assert AXIAL.edge_labels() == {"left": "R", "right": "L", "top": "A", "bottom": "P"}
    assert CORONAL.edge_labels() == {"left": "R", "right": "L", "top": "S", "bottom": "I"}
    assert SAGITTAL.edge_labels() == {"left": "A", "right": "P", "top": "S", "bottom": "I"}
    for frame in FRAMES.values():
        assert np.allclose(frame.axes @ frame.axes.T, np.eye(3))


def test_snap_depth_and_step():
    vol = _volume(np.diag([1.0, 2.0, 3.0]))
    sampler = SliceSampler(vol)
    assert sampler.step(AXIAL) == 3.0 and sampler.step(CORONAL) == 2.0
    assert sampler.snap_depth(AXIAL, 11.0 + 3.0 * 2 + 1.2) == pytest.approx(17.0)


def test_window_and_auto_window():
    values = np.array([[0.0, 50.0, 100.0, np.nan]])
    out = window_to_uint8(values, window=100.0, level=50.0)
    assert out.tolist() == [[0, 127, 255, 0]]
    w, lvl = auto_window(np.linspace(0, 100, 10001))
    assert 95 < w <= 100 and 45 < lvl < 55


def test_contour_normals_point_outwards():
    t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    circle = np.stack([10 * np.cos(t) + 3, 10 * np.sin(t) - 2, np.full_like(t, 5.0)], axis=1)
    for order in (circle, circle[::-1]):
        normals = contour_normals(order, [0, 0, 1])
        radial = (order - [3, -2, 5]) / 10
        assert np.all(np.einsum("ij,ij->i", normals, radial) > 0.95)
    assert np.isnan(contour_normals(circle[:1], [0, 0, 1])).all()


def test_slice_contour_normals_take_the_surface_side_for_open_strokes():
    """Two slices of a sphere, each an open quarter arc drawn in either direction: the normals
    take the side of the surface's normals at the nearest vertices."""
    from core.geometry.planes import slice_contour_normals

    t = np.linspace(0.0, np.pi / 2, 8)
    rows, ids = [], []
    for k, z in enumerate((-3.0, 4.0)):
        r = np.sqrt(100.0 - z * z)
        arc = np.stack([r * np.cos(t), r * np.sin(t), np.full_like(t, z)], axis=1)
        rows.append(arc if k == 0 else arc[::-1])        # drawn in either direction
        ids += [k] * len(t)
    points = np.vstack(rows)
    plane_normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    phi, theta = np.meshgrid(np.linspace(0, 2 * np.pi, 60), np.linspace(0.05, np.pi - 0.05, 30))
    sphere = 10 * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                            np.cos(theta)], axis=-1).reshape(-1, 3)
    got = slice_contour_normals(points, np.array(ids), plane_normals, (sphere, sphere / 10))
    radial = points.copy()
    radial[:, 2] = 0
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", got, radial) > 0.95)
    # the surface decides the side: with its normals turned inwards, so are the points'
    inward = slice_contour_normals(points, np.array(ids), plane_normals, (sphere, -sphere / 10))
    assert np.all(np.einsum("ij,ij->i", inward, radial) < -0.95)
    alone = slice_contour_normals(points[:1], np.array([0]), plane_normals[:1])
    assert np.isnan(alone).all()
