"""Label maps -> training surfaces (core.correspondence.mesh_labels, ssm-studio mesh-labels)
against analytic truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.correspondence.mesh_labels import LabelError, label_map_surface, label_surface, resolve_label
from core.geometry import mesh as meshops
from core.geometry.toolkit import random_rotation
from core.types import Volume

RADII = np.array([12.0, 9.0, 7.0])  # mm


def _ellipsoid_map(spacing: float, oblique: bool, value: int = 11, seed: int = 0):
    """Label map of an ellipsoid (centre ``c``, axes rotated by ``rot``) on a grid of
    ``spacing`` mm voxels, itself rotated (oblique) and far from the origin."""
    rng = np.random.default_rng(seed)
    rot = random_rotation(rng) if oblique else np.eye(3)      # ellipsoid axes in the world
    grid_rot = random_rotation(rng) if oblique else np.eye(3)  # voxel axes in the world
    centre = np.array([-20.0, 130.0, 45.0])
    n = int(2 * RADII.max() / spacing) + 8
    affine = np.eye(4)
    affine[:3, :3] = grid_rot * spacing
    affine[:3, 3] = (centre - grid_rot @ np.full(3, (n - 1) / 2 * spacing)
                     + rng.uniform(-0.5, 0.5, 3) * spacing)
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    world = ijk @ affine[:3, :3].T + affine[:3, 3]
    local = (world - centre) @ rot  # ellipsoid frame
    data = np.where(((local / RADII) ** 2).sum(axis=1) <= 1.0, value, 0).reshape(n, n, n)
    data[:3, :3, :3] = 3  # another label in a corner
    return Volume(data.astype(np.int16), affine), centre, rot


def _distance_to_ellipsoid(points, centre, rot):
    """Distance to the analytic ellipsoid, first order in the level-set value (exact to
    O(d^2 curvature), far below the tolerances here)."""
    x = (points - centre) @ rot
    f = np.sqrt(((x / RADII) ** 2).sum(axis=1))
    grad = np.linalg.norm(x / RADII ** 2, axis=1) / f
    return np.abs(f - 1.0) / grad


@pytest.mark.parametrize("spacing", [0.5, 1.0, 2.0])
@pytest.mark.parametrize("oblique", [False, True])
def test_label_surface_is_accurate_on_an_analytic_ellipsoid(spacing, oblique):
    volume, centre, rot = _ellipsoid_map(spacing, oblique)
    mesh = label_surface(volume, 11, n_vertices=1000)
    assert meshops.is_closed(mesh.faces) and meshops.n_components(mesh.faces, mesh.n_vertices) == 1
    assert meshops.is_consistently_oriented(mesh.faces)
    assert 900 <= mesh.n_vertices <= 1100
    true_volume = 4.0 / 3.0 * np.pi * RADII.prod()
    assert meshops.volume(mesh.vertices, mesh.faces) == pytest.approx(true_volume, rel=0.02)
    assert _distance_to_ellipsoid(mesh.vertices, centre, rot).mean() < spacing / 4


def test_labels_by_freesurfer_and_slicer_names_and_clear_errors(tmp_path):
    from core.io import save_volume
    from core.io.nrrd import Segment, write_segmentation

    volume, _, _ = _ellipsoid_map(2.0, False)
    nii = tmp_path / "aseg.nii.gz"
    save_volume(nii, volume.data, volume.affine)
    assert resolve_label(nii, "Left-Caudate") == (11, "Left-Caudate")
    assert resolve_label(nii, "left-thalamus-proper")[0] == 10
    mesh = label_map_surface(nii, "Left-Caudate", n_vertices=300)
    assert mesh.name == "aseg_Left-Caudate" and meshops.is_closed(mesh.faces)
    seg = tmp_path / "caudate.seg.nrrd"
    write_segmentation(seg, volume.data, volume.affine,
                       [Segment(11, "caudate right"), Segment(3, "corner")])
    assert resolve_label(seg, "Caudate Right") == (11, "caudate right")
    with pytest.raises(LabelError, match="caudate.seg.nrrd.*no segment named 'putamen'"):
        resolve_label(seg, "putamen")
    with pytest.raises(LabelError, match=r"aseg.nii.gz: label Left-Putamen \(value 12\) has no voxel"):
        label_map_surface(nii, "Left-Putamen")
    with pytest.raises(LabelError, match="aseg.nii.gz: 'nonsense' is neither"):
        resolve_label(nii, "nonsense")


def test_cli_mesh_labels_writes_surfaces_and_reports_failures(tmp_path):
    from core.cli import main
    from core.io import load_mesh, save_volume

    good, _, _ = _ellipsoid_map(2.0, True)
    empty = Volume(np.zeros((8, 8, 8), np.int16), np.eye(4))
    save_volume(tmp_path / "a.nii.gz", good.data, good.affine)
    save_volume(tmp_path / "b.nii.gz", empty.data, empty.affine)
    out = tmp_path / "surfaces"
    code = main(["mesh-labels", str(tmp_path / "a.nii.gz"), str(tmp_path / "b.nii.gz"),
                 str(tmp_path / "missing.nii.gz"), "--label", "11", "--vertices", "400",
                 "--out", str(out)])
    assert code == 1
    report = json.loads((out / "mesh_labels.json").read_text())
    ok, empty_entry, missing = report["inputs"]
    assert ok["ok"] and ok["vertices"] == load_mesh(ok["output"]).n_vertices
    assert not empty_entry["ok"] and "label" in empty_entry["error"] and "b.nii.gz" in empty_entry["error"]
    assert not missing["ok"] and "missing.nii.gz" in missing["error"]


def test_builder_engine_adds_label_maps_as_entries(tmp_path):
    from app.panels.builder_engine import load_label_entries
    from core.io import save_volume

    good, _, _ = _ellipsoid_map(2.0, False)
    save_volume(tmp_path / "a.nii.gz", good.data, good.affine)
    entries = load_label_entries([tmp_path / "a.nii.gz", tmp_path / "nope.nii.gz"], "Left-Caudate")
    assert entries[0].mesh is not None and entries[0].name == "a_Left-Caudate"
    assert entries[0].included and not entries[0].problems
    assert entries[1].mesh is None and "nope.nii.gz" in entries[1].problems[0]
