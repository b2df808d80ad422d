"""Plan report and exports on analytic structures (spheres) with known answers."""

from __future__ import annotations

import json

import numpy as np
import pytest
from analytic import sphere as icosphere

from core.io import Volume, load_points, load_volume
from core.io.nrrd import segmentation_fields
from core.planning.frames import ACPCFrame
from core.planning.report import (
    PlannedStructure,
    export_plan,
    itksnap_label_description,
    model_target,
    multi_label_map,
    plan_report,
)


@pytest.fixture
def plan():
    frame = ACPCFrame.from_points([0, 12, 0], [0, -12, 0], [0, 0, 40])
    va, fa = icosphere(6.0, [-12, 0, 0], 4)
    vb, fb = icosphere(4.0, [-12, 0, 14], 4)
    target = np.array([-12.0, 0.0, 0.0])
    a = PlannedStructure("sphere A", va, fa, (1.0, 0.0, 0.0), target=target,
                         entry=target + [0, 0, 70.0])
    b = PlannedStructure("sphere B", vb, fb, (0.0, 0.5, 1.0))
    return [a, b], frame


def test_report_gives_volumes_centroids_and_crossings(plan):
    structures, frame = plan
    report = plan_report(structures, frame, image="t1.nii.gz")
    a, b = report["structures"]
    assert a["volume_mm3"] == pytest.approx(4 / 3 * np.pi * 6 ** 3, rel=0.01)
    np.testing.assert_allclose(a["centroid_acpc"], [-12, 0, 0], atol=1e-6)
    traj = a["trajectory"]
    assert traj["length_mm"] == pytest.approx(70)
    assert traj["ring_deg"] == pytest.approx(90) and traj["arc_deg"] == pytest.approx(90)
    crossings = {(c["structure"]): (c["enter_mm"], c["leave_mm"]) for c in traj["crossings"]}
    # from the entry at z = 70: sphere B spans z 10..18 (depth 52..60), sphere A z -6..6
    # (depth 64..76, searched 10 mm past the target)
    np.testing.assert_allclose(crossings["sphere B"], [52, 60], atol=0.05)
    np.testing.assert_allclose(crossings["sphere A"], [64, 76], atol=0.05)
    assert "trajectory" not in b
    assert report["acpc"]["ac_pc_distance_mm"] == pytest.approx(24)


def test_label_map_has_one_label_per_structure_with_analytic_volumes(plan):
    structures, _ = plan
    affine = np.diag([0.5, 0.5, 0.5, 1.0])
    affine[:3, 3] = [-25, -12, -10]
    vol = Volume(np.zeros((60, 50, 70), dtype=np.float32), affine)
    labels = multi_label_map(structures, vol)
    voxel = 0.125
    assert (labels == 1).sum() * voxel == pytest.approx(4 / 3 * np.pi * 6 ** 3, rel=0.03)
    assert (labels == 2).sum() * voxel == pytest.approx(4 / 3 * np.pi * 4 ** 3, rel=0.03)
    # overlapping structures: the earlier one keeps its voxels
    bigger = PlannedStructure("overlap", *icosphere(8.0, [-12, 0, 0], 3))
    labels2 = multi_label_map([structures[0], bigger], vol)
    assert ((labels2 == 1) == (labels == 1)).all()


def test_itksnap_label_file_lists_names_and_colours(plan):
    structures, _ = plan
    text = itksnap_label_description(structures)
    rows = [line.split(None, 7) for line in text.splitlines() if not line.startswith("#")]
    assert rows[1][:4] == ["1", "255", "0", "0"] and rows[1][7] == '"sphere A"'
    assert rows[2][:4] == ["2", "0", "128", "255"]


def test_export_writes_everything_and_markups_read_back_in_ras(plan, tmp_path):
    structures, frame = plan
    affine = np.eye(4)
    affine[:3, 3] = [-25, -12, -10]
    vol = Volume(np.zeros((30, 25, 35), dtype=np.float32), affine)
    written = export_plan(tmp_path, structures, vol, frame)
    assert all(p.exists() for p in written)
    markups = json.loads((tmp_path / "plan.mrk.json").read_text())
    assert [m["type"] for m in markups["markups"]] == ["Fiducial", "Line"]
    assert markups["markups"][0]["coordinateSystem"] == "LPS"
    pts = load_points(tmp_path / "plan.mrk.json").points
    np.testing.assert_allclose(pts[0], frame.ac, atol=1e-9)  # LPS on disk, RAS back
    np.testing.assert_allclose(pts[3], structures[0].target, atol=1e-9)
    labels = load_volume(tmp_path / "plan_labels.nii.gz")
    np.testing.assert_allclose(labels.affine, affine)
    assert set(np.unique(labels.data)) == {0, 1, 2}
    segments = segmentation_fields(tmp_path / "plan_labels.seg.nrrd")
    assert [(seg["Name"], seg["LabelValue"]) for seg in segments] == [("sphere A", "1"),
                                                                    ("sphere B", "2")]
    seg_labels = load_volume(tmp_path / "plan_labels.seg.nrrd")
    np.testing.assert_allclose(seg_labels.affine, affine, atol=1e-9)
    np.testing.assert_array_equal(seg_labels.data, labels.data)
    table = (tmp_path / "plan_structures.csv").read_text().splitlines()
    assert table[0].startswith("name,volume_mm3") and table[1].startswith("sphere A,")


def test_model_target_moves_with_the_fitted_shape():
    v, f = icosphere(10.0, [0, 0, 0], 3)
    stretched = v * [1.5, 1.0, 1.0] + [3, 0, 0]
    np.testing.assert_allclose(model_target(v, f, stretched), [3, 0, 0], atol=1e-6)
    stored = np.array([4.0, 2.0, -1.0])
    np.testing.assert_allclose(model_target(v, f, stretched, stored), [9.0, 2.0, -1.0], atol=0.02)
