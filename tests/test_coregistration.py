"""A second image (other contrast, moved) brought onto the first image's grid
(core.registration.coregistration).

Known truth: the second image is the demo T1 with its contrast inverted and remapped (like a
T2: white matter dark, CSF bright), moved by a known rigid transform into scanner coordinates
far away, with noise and a bias field. The rigid registration must recover that motion, and
the resampled second image must then be the remapped T1 voxel for voxel (up to noise).
"""

from __future__ import annotations

import numpy as np
import pytest

from core.datasets.images import moved_copy, random_affine
from core.geometry.planes import FRAMES, SliceSampler
from core.io import Volume, load_mesh, load_volume
from core.registration.coregistration import blend, checkerboard_mask, coregister, same_grid
from core.runtime.progress import Cancelled

TEMPLATE = "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz"


@pytest.fixture(scope="module")
def t1(resources_dir):
    """The demo T1 at 3 mm (every third voxel: 66 x 78 x 63; the registration pyramid smooths)."""
    image = load_volume(resources_dir / TEMPLATE)
    data = np.ascontiguousarray(np.asarray(image.data, dtype=np.float32)[::3, ::3, ::3])
    return Volume(data, np.asarray(image.affine, float) @ np.diag([3.0, 3.0, 3.0, 1.0]))


@pytest.fixture(scope="module")
def caudate(resources_dir):
    return np.asarray(load_mesh(resources_dir / "demo" / "caudate_base.vtk").vertices, float)


def remap(data: np.ndarray) -> np.ndarray:
    """Inverted, non-linear contrast inside the head; background stays dark."""
    top = float(np.max(data))
    head = data > 0.05 * top
    return np.where(head, ((top - data) / top) ** 1.5 * top, 0.0).astype(np.float32)


def _apply(t, x):
    return x @ t[:3, :3].T + t[:3, 3]


def test_rigid_registration_recovers_the_motion_of_an_other_contrast_image(t1, caudate):
    rng = np.random.default_rng(7)
    truth = random_affine(rng, rotation_deg=10.0, translation_mm=12.0, scale=0.0,
                          center=np.array([0.0, -18.0, 18.0]))
    moved = moved_copy(remap(t1.data), t1.affine, truth, rng, noise=0.02, bias=0.2)
    second = Volume(moved.data, moved.affine)
    assert not same_grid(t1, second)
    seen = []
    result = coregister(t1, second, progress=lambda f, m="": seen.append(f),
                        levels_mm=(8.0, 4.0), n_samples=8000, threads=1)
    assert result.registered and seen[-1] == 1.0
    # transform: second world -> first world, i.e. the inverse of the known motion
    start = np.linalg.norm(_apply(moved.truth, caudate) - caudate, axis=1).mean()
    err = np.linalg.norm(_apply(result.transform @ moved.truth, caudate) - caudate, axis=1)
    assert start > 50.0                       # far away in scanner coordinates
    print(f"caudate error after registration: mean {err.mean():.2f}, max {err.max():.2f} mm")
    assert err.max() < 1.5, err.max()        # voxels are 3 mm
    np.testing.assert_allclose(result.transform[:3, :3].T @ result.transform[:3, :3], np.eye(3),
                               atol=1e-6)     # rigid
    # on the first grid, the second image is the remapped T1 (up to noise and bias)
    assert result.volume.shape == t1.shape
    np.testing.assert_allclose(result.volume.affine, t1.affine)
    head = t1.data > 0.2 * float(t1.data.max())
    inner = head & np.isfinite(result.volume.data)
    assert inner.mean() > 0.95 * head.mean()
    r = np.corrcoef(result.volume.data[inner], remap(t1.data)[inner])[0, 1]
    print(f"correlation with the remapped T1: {r:.3f}")
    assert r > 0.8, r                         # noise, bias field, two interpolations
    # a given transform (a saved session) is used as is, without registering again; the
    # unregistered placement (identity) does not match: the check above can fail
    again = coregister(t1, second, transform=result.transform)
    assert not again.registered
    np.testing.assert_allclose(again.volume.data, result.volume.data, equal_nan=True)
    off = coregister(t1, second, transform=truth).volume.data  # scanner offset left in
    both = head & np.isfinite(off)
    assert both.sum() < 0.05 * head.sum() or \
        np.corrcoef(off[both], remap(t1.data)[both])[0, 1] < 0.5


def test_same_grid_needs_no_registration_and_cancel_stops_it(t1):
    second = Volume(remap(t1.data), t1.affine.copy())
    result = coregister(t1, second)
    assert not result.registered
    np.testing.assert_array_equal(result.transform, np.eye(4))
    np.testing.assert_array_equal(result.volume.data, second.data)
    moved_grid = t1.affine.copy()
    moved_grid[0, 3] += 4.0                  # another grid: registration needed
    shifted = Volume(second.data, moved_grid)
    assert not same_grid(t1, shifted)

    def cancel(fraction, message=""):
        raise Cancelled()

    with pytest.raises(Cancelled):
        coregister(t1, shifted, progress=cancel, levels_mm=(8.0,), threads=1)


def test_checkerboard_squares_are_fixed_in_mm_and_blend_weights_the_top_image(t1):
    sl = SliceSampler(t1).sample(FRAMES["axial"], 0.0)
    mask = checkerboard_mask(sl, 9.0)        # 3 mm pixels: squares of 3 x 3 pixels
    u, v = sl.pixel_to_plane(np.arange(mask.shape[1]), np.arange(mask.shape[0]))
    expected = ((np.floor(v / 9.0)[:, None] + np.floor(u / 9.0)[None, :]) % 2) == 0
    np.testing.assert_array_equal(mask, expected)
    assert 0.4 < mask.mean() < 0.6
    col_runs = np.flatnonzero(np.diff(mask[0].astype(int)))
    assert np.all(np.diff(col_runs) == 3)
    bottom = np.full((2, 2), 200, np.uint8)
    top = np.full((2, 2), 100, np.uint8)
    assert blend(bottom, top, 0.0)[0, 0] == 200 and blend(bottom, top, 1.0)[0, 0] == 100
    assert blend(bottom, top, 0.25)[0, 0] == 175
    with pytest.raises(ValueError):
        checkerboard_mask(sl, 0.0)


def test_other_field_of_view_in_the_same_scanner_frame_stays_in_place(t1, caudate):
    """A FLAIR-like series of the same session: other contrast, coarser voxels and only the
    upper part of the head, already aligned in world space. The registration starts from the
    centres of mass, which differ here, and must still leave the image where it is."""
    from core.registration.volumes import resample

    grid = t1.affine @ np.diag([4.0 / 3.0, 4.0 / 3.0, 4.0 / 3.0, 1.0])
    shape = tuple(int(s * 3 / 4) for s in t1.shape)
    grid[:3, 3] += t1.affine[:3, :3] @ np.array([0.0, 0.0, 0.35 * t1.shape[2]])
    shape = (shape[0], shape[1], int(0.55 * shape[2]))   # top of the head only
    data = resample(remap(t1.data), t1.affine, np.eye(4), shape, grid)
    flair = Volume(data, grid)
    assert not same_grid(t1, flair)
    result = coregister(t1, flair, levels_mm=(8.0, 4.0), n_samples=8000, threads=1)
    err = np.linalg.norm(_apply(result.transform, caudate) - caudate, axis=1)
    print(f"caudate moved by {err.max():.2f} mm")
    assert err.max() < 1.5, err.max()
