"""core.geometry.labelmap: manual edits of a label map (brush / eraser), kept apart from the model's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.datasets.factors import ellipsoid_surface
from core.geometry.labelmap import (
    ManualEdits,
    brush_voxels,
    mask_volume_mm3,
    structure_label_map,
)


def test_round_brush_covers_the_disc_on_one_slice():
    shape, affine = (30, 30, 30), np.eye(4)
    voxels = brush_voxels(shape, affine, [10.0, 10.0, 10.0], [0, 0, 1], 3.0, 1.0)
    ijk = np.array(np.unravel_index(voxels, shape)).T
    assert np.all(ijk[:, 2] == 10)  # one slice
    # lattice points of the disc of radius 3: i^2 + j^2 <= 9
    expected = sum(1 for i in range(-3, 4) for j in range(-3, 4) if i * i + j * j <= 9)
    assert len(voxels) == expected == 29
    # a brush smaller than a voxel paints the voxel under the cursor
    tiny = brush_voxels(shape, affine, [4.4, 5.2, 6.0], [0, 0, 1], 0.1, 1.0)
    assert np.array_equal(np.array(np.unravel_index(tiny, shape)).ravel(), [4, 5, 6])
    # outside the grid: nothing
    assert len(brush_voxels(shape, affine, [-50, 0, 0], [0, 0, 1], 2.0, 1.0)) == 0


def test_brush_on_an_oblique_anisotropic_grid_matches_brute_force():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    affine = np.eye(4)
    affine[:3, :3] = q @ np.diag([0.8, 1.1, 2.5])
    affine[:3, 3] = [-12.0, 7.0, 30.0]
    shape = (24, 20, 12)
    center = affine[:3, :3] @ [11.3, 9.6, 5.2] + affine[:3, 3]
    normal = np.array([0.3, -0.2, 0.93])
    normal /= np.linalg.norm(normal)
    got = np.sort(brush_voxels(shape, affine, center, normal, 4.0, 1.5))
    ijk = np.indices(shape).reshape(3, -1).T
    d = ijk @ affine[:3, :3].T + affine[:3, 3] - center
    along = d @ normal
    radial = np.sqrt(np.sum((d - along[:, None] * normal) ** 2, axis=1))
    truth = np.flatnonzero((np.abs(along) <= 0.75) & (radial <= 4.0))
    assert len(truth) > 10
    np.testing.assert_array_equal(got, truth)


def test_paint_and_erase_latest_stroke_wins_and_survives_the_session_file():
    shape = (8, 9, 10)
    edits = ManualEdits(shape)
    assert not edits
    edits = edits.paint([5, 6, 7, 100]).paint([7, 8], erase=True).paint([8])
    np.testing.assert_array_equal(edits.added, [5, 6, 8, 100])
    np.testing.assert_array_equal(edits.removed, [7])
    mask = np.zeros(shape, dtype=np.uint8)
    mask.reshape(-1)[[7, 50]] = 1
    out = edits.apply(mask)
    np.testing.assert_array_equal(np.flatnonzero(out), [5, 6, 8, 50, 100])
    marks = edits.edit_map().reshape(-1)
    assert marks[5] == 1 and marks[7] == 2 and marks[50] == 0
    data = json.loads(json.dumps(edits.to_json()))
    assert data["added"][0] == [5, 2]  # runs of consecutive voxels
    back = ManualEdits.from_json(data, shape)
    np.testing.assert_array_equal(back.added, edits.added)
    np.testing.assert_array_equal(back.removed, edits.removed)
    with pytest.raises(ValueError, match=r"painted on a \(8, 9, 10\) grid but the image is"):
        ManualEdits.from_json(data, (8, 9, 11))
    with pytest.raises(ValueError, match="outside the image grid"):
        ManualEdits.from_json({"shape": [2, 2, 2], "added": [[6, 5]]})
    with pytest.raises(ValueError, match="outside the image grid"):
        edits.paint([720])
    with pytest.raises(ValueError, match="label map of shape"):
        edits.apply(np.zeros((2, 2, 2)))


def test_label_map_of_a_sphere_with_edits_has_the_right_volume():
    vertices, faces = ellipsoid_surface(4, radii=(10.0, 10.0, 10.0))
    affine = np.diag([0.5, 0.5, 0.5, 1.0])
    affine[:3, 3] = -15.0
    shape = (60, 60, 60)
    mask = structure_label_map(vertices, faces, shape, affine)
    volume = mask_volume_mm3(mask, affine)
    # the icosphere is inscribed in the sphere: its volume is a little under 4/3 pi r^3
    assert abs(volume / (4 / 3 * np.pi * 1000) - 1) < 0.02
    # a brush stroke outside the sphere adds exactly its voxels' volume
    stroke = brush_voxels(shape, affine, [0.0, 0.0, 13.0], [0, 0, 1], 2.0, 0.5)
    edits = ManualEdits(shape).paint(stroke)
    edited = structure_label_map(vertices, faces, shape, affine, edits)
    assert np.count_nonzero(edited) - np.count_nonzero(mask) == len(stroke)
    erased = structure_label_map(vertices, faces, shape, affine, edits.paint(stroke, erase=True))
    np.testing.assert_array_equal(erased, mask)
    assert structure_label_map(None, None, shape, affine).sum() == 0
