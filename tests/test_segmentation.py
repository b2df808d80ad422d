"""Voxelisation of closed surfaces: volume, position and oblique affines, against analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from core.geometry.mesh import volume
from core.geometry.segmentation import mask_volume_mm3, voxelize
from core.geometry.toolkit import rodrigues
from core.io import Volume


def _sphere(radius: float, centre, nsub: int = 5) -> tuple[np.ndarray, np.ndarray]:
    s = pv.Icosphere(radius=radius, center=centre, nsub=nsub)
    return np.asarray(s.points, dtype=np.float64), s.faces.reshape(-1, 4)[:, 1:].astype(np.int64)


def _oblique_affine(spacing, angle_deg: float, origin) -> np.ndarray:
    a = np.eye(4)
    a[:3, :3] = rodrigues(np.deg2rad(angle_deg) * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)) * spacing
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


def test_segment_cli_writes_an_aligned_mask(tmp_path):
    """ssm-studio segment: fit a model to contour points, voxelise on an oblique image grid."""
    import nibabel as nib

    from core.cli import main
    from core.evaluation.simulated_user import pca_model, simulate_user, synthetic_shapes
    from core.io import load_mesh, load_volume, save_model, save_points, save_volume

    shapes, faces = synthetic_shapes(12, subdivisions=3, seed=2)
    model = pca_model(shapes[1:], faces)
    save_model(tmp_path / "model.npz", model)
    user = simulate_user(shapes[0], faces, 6, rng=np.random.default_rng(0))
    save_points(tmp_path / "pts.csv", user.points, user.normals)
    affine = _oblique_affine(np.array([0.5, 0.6, 0.7]), 20.0, origin=(0.0, 0.0, 0.0))
    shape = (60, 60, 60)
    affine[:3, 3] = -(np.array(shape) / 2.0) @ affine[:3, :3].T  # grid centred on the shape
    save_volume(tmp_path / "image.nii.gz", np.zeros(shape, np.int16), affine)
    out = tmp_path / "mask.nii.gz"
    rc = main(["segment", "--model", str(tmp_path / "model.npz"), "--points",
               str(tmp_path / "pts.csv"), "--image", str(tmp_path / "image.nii.gz"),
               "--out", str(out), "--mesh-out", str(tmp_path / "fit.vtk"),
               "--json", str(tmp_path / "fit.json")])
    assert rc == 0
    img = nib.load(str(out))
    assert img.get_data_dtype() == np.uint8
    assert np.allclose(img.affine, affine) and int(img.header["sform_code"]) == 1
    mask = load_volume(out)
    mesh = load_mesh(tmp_path / "fit.vtk")
    mesh_volume = volume(mesh.vertices, mesh.faces)
    # tolerance: 3 % of the volume (voxel discretisation on a ~1000 mm^3 shape, 0.2 mm^3 voxels)
    assert mask_volume_mm3(mask.data, mask.affine) == pytest.approx(mesh_volume, rel=0.03)
    centroid_vox = np.argwhere(mask.data > 0).mean(axis=0)
    tri = mesh.vertices[mesh.faces]  # solid centroid: tetrahedra to the origin
    tet = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    solid_centroid = (tet[:, None] * tri.sum(axis=1) / 4.0).sum(axis=0) / tet.sum()
    assert np.linalg.norm(mask.voxel_to_world(centroid_vox) - solid_centroid) < 0.1


def test_segment_cli_bad_points_is_a_one_line_error(tmp_path, capsys):
    from core.cli import main
    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import save_model, save_volume

    shapes, faces = synthetic_shapes(6, subdivisions=2, seed=2)
    save_model(tmp_path / "model.npz", pca_model(shapes, faces))
    save_volume(tmp_path / "image.nii.gz", np.zeros((10, 10, 10), np.int16), np.eye(4))
    (tmp_path / "far.csv").write_text("x,y,z\n500,0,0\n501,0,0\n500,1,0\n")
    rc = main(["segment", "--model", str(tmp_path / "model.npz"), "--points",
               str(tmp_path / "far.csv"), "--image", str(tmp_path / "image.nii.gz"),
               "--out", str(tmp_path / "mask.nii.gz")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "far.csv" in err and "far outside the model" in err
    assert not (tmp_path / "mask.nii.gz").exists()
