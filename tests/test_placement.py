"""Automatic placement: segment --auto-place on the template moved by a known affine."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("SimpleITK")

from core.cli import main as cli_main  # noqa: E402
from core.io import Volume, load_mesh, load_model, load_points, load_volume, save_points, save_volume  # noqa: E402
from core.reconstruction import surface_distance  # noqa: E402
from core.registration.placement import placement_through  # noqa: E402
from core.registration.volumes import resample  # noqa: E402


@pytest.fixture(scope="module")
def moved_case(tmp_path_factory, resources_dir):
    """A 2 mm copy of the template, and the same image moved by a known affine A."""
    tmp = tmp_path_factory.mktemp("autoplace")
    t1 = load_volume(resources_dir / "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz")
    small = Volume(t1.data[::2, ::2, ::2].astype(np.float32), t1.affine @ np.diag([2, 2, 2, 1.0]))
    save_volume(tmp / "template.nii.gz", small.data, small.affine)
    a = np.eye(4)
    a[:3, :3] = Rotation.from_euler("xyz", [8, -6, 10], degrees=True).as_matrix() * 1.06
    a[:3, 3] = [12.0, -9.0, 7.0]  # template world -> patient world
    # the patient image: the template seen through A (output at y takes the template at A^-1 y)
    data = resample(small.data, small.affine, a, small.shape, small.affine)
    rng = np.random.default_rng(0)
    data = data + rng.normal(scale=2.0, size=data.shape).astype(np.float32)
    save_volume(tmp / "patient.nii.gz", data, small.affine)
    pts = load_points(resources_dir / "demo" / "contour_points.csv")
    moved_pts = pts.points @ a[:3, :3].T + a[:3, 3]
    moved_normals = pts.normals @ a[:3, :3].T
    moved_normals /= np.linalg.norm(moved_normals, axis=1, keepdims=True)
    save_points(tmp / "points.csv", moved_pts, moved_normals)
    truth = load_mesh(resources_dir / "demo" / "heldout_caudate.vtk")
    truth_v = truth.vertices @ a[:3, :3].T + a[:3, 3]
    return tmp, a, truth_v, truth.faces


def test_placement_through_maps_the_model_with_the_inverse_transform(resources_dir):
    model = load_model(resources_dir / "demo" / "model.npz")
    t = np.eye(4)
    t[:3, 3] = [5, 0, -2]  # image world -> template world
    placed = placement_through(model, t)
    np.testing.assert_allclose(placed[:3, 3], model.world_transform[:3, 3] - [5, 0, -2])
    with pytest.raises(ValueError, match="invertible"):
        placement_through(model, np.zeros((4, 4)))


def test_segment_auto_place_recovers_the_moved_anatomy(moved_case, resources_dir, capsys):
    tmp, a, truth_v, truth_f = moved_case
    common = ["segment", "--model", str(resources_dir / "demo" / "model.npz"),
              "--points", str(tmp / "points.csv"), "--image", str(tmp / "patient.nii.gz")]
    assert cli_main(common + ["--out", str(tmp / "auto.nii.gz"), "--mesh-out",
                              str(tmp / "auto.vtk"), "--auto-place",
                              "--template", str(tmp / "template.nii.gz")]) == 0
    assert "registered" in capsys.readouterr().err
    auto = load_mesh(tmp / "auto.vtk")
    err_auto = surface_distance(auto.vertices, truth_v, truth_f).mean()
    assert err_auto < 0.5, err_auto
    # the model's stored placement is ~15 mm and 10 degrees off: the same fit from there is worse
    assert cli_main(common + ["--out", str(tmp / "stored.nii.gz"), "--mesh-out",
                              str(tmp / "stored.vtk")]) == 0
    stored = load_mesh(tmp / "stored.vtk")
    err_stored = surface_distance(stored.vertices, truth_v, truth_f).mean()
    assert err_stored > err_auto


def test_auto_place_option_errors_are_one_line(moved_case, resources_dir, capsys):
    tmp, *_ = moved_case
    code = cli_main(["segment", "--model", str(resources_dir / "demo" / "model.npz"),
                     "--points", str(tmp / "points.csv"), "--image", str(tmp / "patient.nii.gz"),
                     "--out", str(tmp / "x.nii.gz"), "--auto-place", "--placement", "1,2,3"])
    assert code == 2
    assert "exclude each other" in capsys.readouterr().err


def test_a_nudge_reads_back_as_the_shift_and_turn_it_made():
    """nudge_of inverts nudged: a registration T with a known hand move (turn about the
    structures' centre, then shift) reads back that shift at the centre and that angle,
    whatever T itself does."""
    from core.registration.placement import nudge_of, nudged

    rng = np.random.default_rng(4)
    t = np.eye(4)
    t[:3, :3] = 1.04 * Rotation.from_rotvec(rng.normal(scale=0.3, size=3)).as_matrix()
    t[:3, 3] = rng.normal(scale=20.0, size=3)
    centre = np.array([-12.0, 8.0, 15.0])
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    moved = nudged(t, np.deg2rad(7.0) * axis, np.array([1.5, -2.0, 0.5]), centre)
    shift, angle = nudge_of(t, moved, centre)
    assert shift == pytest.approx(np.linalg.norm([1.5, -2.0, 0.5]), abs=1e-9)
    assert angle == pytest.approx(7.0, abs=1e-9)
