"""Voxelisation of closed surfaces: volume, position and oblique affines, against analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from core.io import Volume
from core.mesh import volume
from core.reconstruction import _rodrigues
from core.segmentation import mask_volume_mm3, voxelize


def _sphere(radius: float, centre, nsub: int = 5) -> tuple[np.ndarray, np.ndarray]:
    s = pv.Icosphere(radius=radius, center=centre, nsub=nsub)
    return np.asarray(s.points, dtype=np.float64), s.faces.reshape(-1, 4)[:, 1:].astype(np.int64)


def _oblique_affine(spacing, angle_deg: float, origin) -> np.ndarray:
    a = np.eye(4)
    a[:3, :3] = _rodrigues(np.deg2rad(angle_deg) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)) * spacing
    a[:3, 3] = origin
    return a


@pytest.mark.parametrize("spacing,angle", [((0.5, 0.5, 0.5), 0.0), ((0.6, 0.7, 0.9), 33.0)])
def test_sphere_mask_volume_and_position(spacing, angle):
    centre = np.array([10.0, -20.0, 5.0])
    vertices, faces = _sphere(8.0, centre)
    affine = _oblique_affine(np.array(spacing), angle, origin=centre - 15.0)
    shape = (70, 70, 70)
    # grid must cover the sphere: shift the origin so the centre maps to the grid's middle
    affine[:3, 3] += centre - (np.array(shape) / 2.0) @ affine[:3, :3].T - affine[:3, 3]
    mask = voxelize(vertices, faces, shape, affine)
    assert mask.dtype == np.uint8 and mask.shape == shape and set(np.unique(mask)) == {0, 1}
    # Volume matches the mesh volume within 2 %
    assert mask_volume_mm3(mask, affine) == pytest.approx(volume(vertices, faces), rel=0.02)
    # Every voxel centre clearly inside/outside the (polyhedral) sphere is labelled right
    ijk = np.indices(shape).reshape(3, -1).T
    world = ijk @ affine[:3, :3].T + affine[:3, 3]
    r = np.linalg.norm(world - centre, axis=1)
    labels = mask.reshape(-1)
    inner = 8.0 * np.cos(np.deg2rad(4.0))  # the icosphere's faces are within this of the sphere
    assert np.all(labels[r < inner - 1e-6] == 1)
    assert np.all(labels[r > 8.0 + 1e-6] == 0)


def test_volume_object_and_two_components_and_outside():
    a, fa = _sphere(4.0, (0.0, 0.0, 0.0), nsub=4)
    b, fb = _sphere(3.0, (12.0, 0.0, 0.0), nsub=4)
    vertices = np.vstack([a, b])
    faces = np.vstack([fa, fb + len(a)])
    affine = np.diag([0.4, 0.4, 0.4, 1.0])
    affine[:3, 3] = (-6.0, -6.0, -6.0)
    vol = Volume(np.zeros((60, 30, 30), np.int16), affine)
    mask = voxelize(vertices, faces, vol, label=3)
    assert set(np.unique(mask)) == {0, 3}
    expected = volume(a, fa) + volume(b, fb)
    assert mask_volume_mm3(mask, affine) == pytest.approx(expected, rel=0.03)
    # a surface entirely outside the grid gives an empty mask; partial overlap is clipped
    assert voxelize(vertices + 500.0, faces, vol).sum() == 0
    partial = voxelize(vertices + np.array([0.0, 0.0, 4.0]), faces, vol)
    assert 0 < np.count_nonzero(partial) < np.count_nonzero(mask)
    with pytest.raises(ValueError, match="affine"):
        voxelize(vertices, faces, (10, 10, 10))
