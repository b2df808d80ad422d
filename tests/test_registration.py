"""The image registration engine (core.registration.volumes) and ``ssm-studio register``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.cli import main as cli_main
from core.datasets.images import downsample, moved_copy, random_affine
from core.io import load_mesh, load_volume, save_volume
from core.registration.volumes import itk_to_ras, ras_to_itk, register, resample, sitk_affine, volume_to_sitk
from core.runtime.progress import Cancelled

TEMPLATE = "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz"


@pytest.fixture(scope="module")
def small_template(resources_dir):
    """The MNI T1 at 4 mm (about 50 x 58 x 47 voxels)."""
    t = load_volume(resources_dir / TEMPLATE)
    return downsample(t.data, t.affine, 4.0)


@pytest.fixture(scope="module")
def caudate(resources_dir):
    return np.asarray(load_mesh(resources_dir / "demo" / "caudate_base.vtk").vertices, float)


def _apply(t, x):
    return x @ t[:3, :3].T + t[:3, 3]


def test_sitk_geometry_round_trip_oblique_and_flipped():
    rng = np.random.default_rng(3)
    from scipy.spatial.transform import Rotation

    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_euler("xyz", [20, -10, 35], degrees=True).as_matrix() \
        @ np.diag([-1.2, 0.9, 2.5])  # flipped first axis, anisotropic voxels
    affine[:3, 3] = [12.0, -40.0, 7.5]
    data = rng.random((5, 6, 7)).astype(np.float32)
    img = volume_to_sitk(data, affine)
    np.testing.assert_allclose(sitk_affine(img), affine, atol=1e-9)
    # Voxel (i, j, k) of the array is ITK index (i, j, k); its ITK point is the LPS of RAS.
    ijk = (3, 1, 5)
    assert img[ijk] == pytest.approx(float(data[ijk]))
    ras = _apply(affine, np.array(ijk, float))
    np.testing.assert_allclose(img.TransformIndexToPhysicalPoint(ijk), ras * [-1, -1, 1], atol=1e-9)


def test_itk_ras_conversion_is_exact():
    rng = np.random.default_rng(0)
    t = random_affine(rng, center=np.array([10.0, 20.0, -5.0]))
    itk = ras_to_itk(t)
    np.testing.assert_allclose(itk_to_ras(itk), t, atol=1e-10)
    # ITK maps fixed (LPS) -> moving (LPS): that is inv(t) in RAS, seen through the flip.
    p_ras = np.array([3.0, -7.0, 11.0])
    fixed_lps = p_ras * [-1, -1, 1]
    moving_lps = np.array(itk.TransformPoint(fixed_lps.tolist()))
    np.testing.assert_allclose(moving_lps * [-1, -1, 1], _apply(np.linalg.inv(t), p_ras), atol=1e-9)


def test_resample_moves_a_blob_where_the_transform_says():
    shape = (40, 40, 40)
    affine = np.diag([2.0, 2.0, 2.0, 1.0])
    affine[:3, 3] = -40.0
    world = np.stack(np.meshgrid(*[np.arange(n) * 2.0 - 40 for n in shape], indexing="ij"), -1)
    centre = np.array([5.0, -8.0, 3.0])
    blob = np.exp(-((world - centre) ** 2).sum(-1) / (2 * 4.0 ** 2)).astype(np.float32)
    t = np.eye(4)
    t[:3, 3] = [6.0, 4.0, -10.0]
    out = resample(blob, affine, t, shape, affine)
    w = out / out.sum()
    moved_centre = (world * w[..., None]).reshape(-1, 3).sum(0)
    np.testing.assert_allclose(moved_centre, centre + t[:3, 3], atol=0.1)


@pytest.mark.parametrize("seed", [0, 1])
def test_affine_registration_recovers_known_transform(small_template, caudate, seed):
    """Template moved by a random affine (+-15 deg, +-20 mm, +-10 %), noise and bias field:
    the caudate placed through the recovered transform lands within 2 mm of the truth."""
    data, affine = small_template
    rng = np.random.default_rng(seed)
    truth = random_affine(rng, center=np.array([0.0, -18.0, 18.0]))
    moved = moved_copy(data, affine, truth, rng)
    res = register(moved.data, moved.affine, data, affine, "affine", levels_mm=(8.0, 4.0),
                   n_samples=8000, threads=1)
    placed = _apply(np.linalg.inv(res.transform), caudate)
    err = np.linalg.norm(placed - _apply(moved.truth, caudate), axis=1)
    assert err.max() < 2.0, err.max()
    assert res.metric < res.initial_metric
    start_err = np.linalg.norm(caudate - _apply(moved.truth, caudate), axis=1).mean()
    assert start_err > 20.0  # the test starts far from the answer


@pytest.mark.parametrize("kind", ["rigid", "similarity"])
def test_constrained_classes_return_their_class(small_template, kind):
    data, affine = small_template
    rng = np.random.default_rng(5)
    truth = random_affine(rng, scale=0.0, center=np.array([0.0, -18.0, 18.0]))
    if kind == "similarity":
        truth[:3, :3] *= 1.07
    moved = moved_copy(data, affine, truth, rng)
    res = register(moved.data, moved.affine, data, affine, kind, levels_mm=(8.0, 4.0),
                   n_samples=6000, threads=1)
    lin = res.transform[:3, :3]
    s = np.linalg.svd(lin, compute_uv=False)
    assert s.max() - s.min() < 1e-8
    assert np.linalg.det(lin) > 0
    expected = 1.0 if kind == "rigid" else 1 / 1.07
    assert s[0] == pytest.approx(expected, abs=0.02)
    np.testing.assert_allclose(res.transform @ moved.truth, np.eye(4), atol=2.0)


def test_cancel_stops_the_registration(small_template):
    data, affine = small_template
    calls = []

    def progress(fraction, message):
        calls.append(fraction)
        if len(calls) >= 3:
            raise Cancelled()

    with pytest.raises(Cancelled):
        register(data, affine, data, affine, "affine", levels_mm=(8.0, 4.0), progress=progress)
    assert len(calls) == 3  # no iteration ran after the cancel


def test_constant_image_is_refused(small_template):
    data, affine = small_template
    with pytest.raises(ValueError, match="constant"):
        register(np.zeros_like(data), affine, data, affine)


def test_register_cli_writes_transform_json(tmp_path, small_template):
    data, affine = small_template
    rng = np.random.default_rng(2)
    truth = random_affine(rng, center=np.array([0.0, -18.0, 18.0]))
    moved = moved_copy(data, affine, truth, rng)
    save_volume(tmp_path / "img.nii.gz", moved.data, moved.affine)
    save_volume(tmp_path / "tpl.nii.gz", data, affine)
    out = tmp_path / "t.json"
    code = cli_main(["register", "--image", str(tmp_path / "img.nii.gz"), "--template",
                     str(tmp_path / "tpl.nii.gz"), "--out", str(out), "--levels", "8,4",
                     "--samples", "6000"])
    assert code == 0
    doc = json.loads(out.read_text())
    t = np.array(doc["transform"])
    assert doc["image"].endswith("img.nii.gz") and doc["template"].endswith("tpl.nii.gz")
    assert doc["metric"] < doc["initial_metric"] < 0
    # image world -> template world: composing with the truth gives the identity (mm scale).
    probe = np.array([[0.0, -18.0, 18.0], [20, 0, 10], [-20, -40, 30]])
    np.testing.assert_allclose(_apply(t @ moved.truth, probe), probe, atol=1.5)


def test_register_cli_bad_image_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.nii.gz"
    bad.write_bytes(b"not an image")
    code = cli_main(["register", "--image", str(bad), "--out", str(tmp_path / "t.json")])
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "bad.nii.gz" in lines[0], lines
    assert not (tmp_path / "t.json").exists()
