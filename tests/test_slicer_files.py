"""3D Slicer's own files (issue 28, item 4): segmentations with one and two layers, an LPS CT
and a fiducial list, read exactly.

Truth is taken from the files' text headers by hand (numbers copied from the header lines,
the voxels decoded here with gzip + numpy), never from the reader under test, and world
coordinates are checked point by point: Slicer writes LPS (``space:
left-posterior-superior``), SSM Studio works in RAS, (x, y, z)_RAS = (-x, -y, z)_LPS.
"""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("SimpleITK")

DATA = Path(__file__).resolve().parent / "data" / "real" / "slicer"
# ../shared beside the clone (CI), or beside the folder of worktrees
SHARED = next((p / "shared" / "data" / "real" / "slicer" for p in Path(__file__).resolve().parents[2:4]
               if (p / "shared" / "data" / "real" / "slicer").is_dir()),
              Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "slicer")
ONE_LAYER = DATA / "Segmentation.seg.nrrd"
TWO_LAYERS = DATA / "SegmentationOverlapping.seg.nrrd"

# The header lines of both segmentations (and of CTChest4.nrrd), as Slicer wrote them:
#   space directions: (-3.04687595367432,0,0) (0,-3.04687595367432,0) (0,0,9.9999999999999964)
#   space origin: (193.09599304199222,216.39599609374994,-340.24999999999994)
DIRECTIONS_LPS = np.array([[-3.04687595367432, 0, 0], [0, -3.04687595367432, 0],
                           [0, 0, 9.9999999999999964]])  # one row per voxel axis i, j, k
ORIGIN_LPS = np.array([193.09599304199222, 216.39599609374994, -340.24999999999994])
SEGMENT_NAMES = ["ribs", "cervical vertebral column", "thoracic vertebral column",
                 "lumbar vertebral column", "right lung", "left lung", "tissue"]


def _world_ras_by_hand(ijk) -> np.ndarray:
    lps = ORIGIN_LPS + np.asarray(ijk, float) @ DIRECTIONS_LPS
    return lps * [-1.0, -1.0, 1.0]


def _voxels_by_hand(path: Path, dtype: str, sizes: tuple[int, ...]) -> np.ndarray:
    """The gzip payload after the header's blank line, i fastest (NRRD's order)."""
    raw = path.read_bytes()
    payload = gzip.decompress(raw[raw.index(b"\n\n") + 2:])
    return np.frombuffer(payload, dtype=dtype).reshape(sizes, order="F")


VOXELS = [(0, 0, 0), (127, 127, 33), (10, 20, 5), (64, 3, 17)]


@pytest.mark.parametrize("path", [ONE_LAYER, TWO_LAYERS], ids=["one layer", "two layers"])
def test_segmentation_geometry_is_the_header_in_ras(path):
    from core.io.nrrd import read_segmentation

    seg = read_segmentation(path)
    for ijk in VOXELS:
        np.testing.assert_allclose(seg.affine @ [*ijk, 1.0], [*_world_ras_by_hand(ijk), 1.0],
                                   rtol=0, atol=1e-9)
    # the first voxel's centre in RAS, from the origin line alone: (-193.096, -216.396, -340.25)
    np.testing.assert_allclose(seg.affine[:3, 3], [-193.09599304199222, -216.39599609374994,
                                                   -340.24999999999994], rtol=0, atol=1e-12)


def test_one_layer_segmentation_reads_its_segments_and_voxels():
    from core.io import load_volume
    from core.io.nrrd import read_segmentation

    seg = read_segmentation(ONE_LAYER)
    assert [s.name for s in seg.segments] == SEGMENT_NAMES
    assert [(s.label_value, s.layer) for s in seg.segments] == [(v, 0) for v in range(1, 8)]
    assert seg.segments[0].id == "Segment_1"
    np.testing.assert_allclose(seg.segments[4].color, (0.0862745, 0.772549, 0.278431))
    truth = _voxels_by_hand(ONE_LAYER, "u1", (128, 128, 34))
    assert seg.layers.shape == (1, 128, 128, 34)
    np.testing.assert_array_equal(seg.layers[0], truth)
    volume = load_volume(ONE_LAYER)  # as a label map: the values as stored
    np.testing.assert_array_equal(volume.data, truth)
    np.testing.assert_allclose(volume.affine, seg.affine, rtol=0, atol=0)


def test_two_layer_segmentation_reads_each_segment_whole():
    """Before: refused ("a Segmentation with overlapping segments (2 layers)")."""
    from core.io.nrrd import read_segmentation

    seg = read_segmentation(TWO_LAYERS)
    truth = _voxels_by_hand(TWO_LAYERS, "u1", (2, 128, 128, 34))
    np.testing.assert_array_equal(seg.layers, truth)
    assert [s.name for s in seg.segments] == SEGMENT_NAMES + ["overlapping sphere"]
    sphere = seg.find("overlapping sphere")
    assert (sphere.index, sphere.layer, sphere.label_value) == (7, 1, 1)
    assert seg.find("2.25.256098691398322583637751658535111585949") == sphere  # by its ID
    mask = seg.mask(sphere)
    np.testing.assert_array_equal(mask, truth[1] == 1)
    # Segment7_Extent:=16 64 61 109 16 30 (min/max i, j, k of its voxels, written by Slicer)
    inside = np.argwhere(mask)
    assert inside.min(0).tolist() == [16, 61, 16] and inside.max(0).tolist() == [64, 109, 30]
    ribs = seg.find("ribs")
    overlap = int(np.count_nonzero(seg.mask(ribs) & mask))
    assert overlap > 0  # the point of a second layer: the sphere covers rib voxels too
    # layer 0 of the layered file is the one-layer file's label map
    np.testing.assert_array_equal(seg.layers[0], read_segmentation(ONE_LAYER).layers[0])
    with pytest.raises(ValueError, match="label value 1 is ambiguous.*'ribs'.*'overlapping sphere'"):
        seg.find(1)
    assert seg.find(5).name == "right lung"  # a value only one layer has


def test_two_layer_segmentation_opens_as_one_label_map_with_a_note():
    from core.errors import DataFileWarning
    from core.io import load_volume
    from core.io.nrrd import read_segmentation

    with pytest.warns(DataFileWarning, match="8 segments in 2 overlapping layers"):
        volume = load_volume(TWO_LAYERS)
    seg = read_segmentation(TWO_LAYERS)
    sphere = seg.mask(seg.find("overlapping sphere"))
    assert np.all(volume.data[sphere] == 8)  # Segment7 -> 8, the later segment on top
    lung = seg.mask(seg.find("right lung")) & ~sphere
    assert np.all(volume.data[lung] == 5)


def _mesh_labels(tmp_path, capsys, path, *options):
    from core.cli import main

    capsys.readouterr()
    rc = main(["mesh-labels", str(path), *options, "--vertices", "600",
               "--out", str(tmp_path / "out")])
    return rc, capsys.readouterr()


@pytest.mark.parametrize("path", [ONE_LAYER, TWO_LAYERS], ids=["one layer", "two layers"])
def test_mesh_labels_takes_a_segment_by_name_from_either_file(tmp_path, capsys, path):
    from core.io import load_mesh
    from core.io.nrrd import read_segmentation

    rc, out = _mesh_labels(tmp_path, capsys, path, "--segment", "Right Lung")
    assert rc == 0, out.err
    stem = path.name.split(".")[0]
    mesh = load_mesh(tmp_path / "out" / f"{stem}_right_lung.vtk")
    seg = read_segmentation(path)
    mask = seg.mask(seg.find("right lung"))
    # the lung is the largest piece of the segment (specks are dropped): the surface spans
    # that piece's voxel box in world RAS, to within three voxels (3.05 mm in-plane, 10 mm slices)
    from scipy import ndimage

    pieces, n = ndimage.label(mask)
    largest = pieces == 1 + int(np.argmax(ndimage.sum(mask, pieces, range(1, n + 1))))
    ijk = np.argwhere(largest)
    box = np.array([_world_ras_by_hand(ijk.min(0)), _world_ras_by_hand(ijk.max(0))])
    low, high = box.min(0), box.max(0)
    slack = 3 * np.array([3.05, 3.05, 10.0])  # smoothing rounds thin tips off
    assert np.all(np.abs(mesh.vertices.min(0) - low) < slack), (mesh.vertices.min(0), low)
    assert np.all(np.abs(mesh.vertices.max(0) - high) < slack), (mesh.vertices.max(0), high)
    # the right lung lies at positive x in RAS (+x: the patient's right; Slicer's LPS file
    # has it at negative x)
    assert _world_ras_by_hand(ijk.mean(0))[0] > 40 and mesh.vertices[:, 0].mean() > 40
    assert (ORIGIN_LPS + ijk.mean(0) @ DIRECTIONS_LPS)[0] < -40


def test_mesh_labels_takes_an_overlapping_segment_whole(tmp_path, capsys):
    from core.geometry import mesh as meshops
    from core.io import load_mesh
    from core.io.nrrd import read_segmentation

    rc, out = _mesh_labels(tmp_path, capsys, TWO_LAYERS, "--segment", "overlapping sphere")
    assert rc == 0, out.err
    mesh = load_mesh(tmp_path / "out" / "SegmentationOverlapping_overlapping_sphere.vtk")
    seg = read_segmentation(TWO_LAYERS)
    mask = seg.mask(seg.find("overlapping sphere"))
    voxel_mm3 = abs(np.linalg.det(DIRECTIONS_LPS))
    volume = meshops.volume(mesh.vertices, mesh.faces)
    assert meshops.is_closed(mesh.faces)
    assert 0.9 < volume / (mask.sum() * voxel_mm3) < 1.1
    # centre of Segment7_Extent (16-64, 61-109, 16-30) in RAS, by hand
    np.testing.assert_allclose(mesh.vertices.mean(0), _world_ras_by_hand([40, 85, 23]), atol=8.0)


def test_mesh_labels_segment_choice_errors_name_the_file(tmp_path, capsys):
    rc, out = _mesh_labels(tmp_path, capsys, TWO_LAYERS, "--label", "1")
    assert rc == 1 and "SegmentationOverlapping.seg.nrrd: label value 1 is ambiguous" in out.err
    rc, out = _mesh_labels(tmp_path, capsys, ONE_LAYER, "--segment", "overlapping sphere")
    assert rc == 1
    assert "Segmentation.seg.nrrd: no segment named 'overlapping sphere' (segments: 'ribs'" \
        in out.err
    nii = tmp_path / "a.nii.gz"
    nii.write_bytes(b"x")
    rc, out = _mesh_labels(tmp_path, capsys, nii, "--segment", "ribs")
    assert rc == 2 and "a.nii.gz: --segment takes a segment of a 3D Slicer .seg.nrrd" in out.err
    assert len(out.err.strip().splitlines()) == 1


def test_fcsv_fiducials_are_read_in_ras():
    from core.io import load_points

    points = load_points(DATA / "F_1.fcsv").points
    assert points.shape == (12, 3)
    # rows 1 and 12 of the file (# CoordinateSystem = LPS): x, y negated
    np.testing.assert_allclose(points[0], [6.282824184397157, 51.06216973995272, -10.2143],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(points[-1], [-77.41355846390559, 17.021116613493888,
                                            -10.214302062988281], rtol=0, atol=1e-12)


@pytest.mark.parametrize("system, sign", [("0", 1.0), ("RAS", 1.0), ("1", -1.0), (None, 1.0)])
def test_fcsv_coordinate_system_variants(tmp_path, system, sign):
    """Slicer 4.11+ writes LPS/RAS or 0/1; older files have no CoordinateSystem line (RAS)."""
    from core.io import load_points

    lines = ["# Markups fiducial file version = 4.10"]
    if system is not None:
        lines.append(f"# CoordinateSystem = {system}")
    lines += ["# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID",
              "vtkMRMLMarkupsFiducialNode_0,1.5,-2.5,3.5,0,0,0,1,1,1,0,F-1,,"]
    path = tmp_path / "f.fcsv"
    path.write_text("\n".join(lines) + "\n")
    np.testing.assert_allclose(load_points(path).points[0], [1.5 * sign, -2.5 * sign, 3.5])


@pytest.mark.skipif(not (SHARED / "CTChest4.nrrd").is_file(), reason="../shared absent")
def test_lps_integer_ct_reads_exactly():
    from core.io import load_volume

    path = SHARED / "CTChest4.nrrd"
    volume = load_volume(path)
    truth = _voxels_by_hand(path, "<i4", (128, 128, 34))  # type: int, endian: little
    assert volume.data.dtype == np.int32
    np.testing.assert_array_equal(volume.data, truth)
    assert (int(truth.min()), int(truth.max())) == (-3024, 3070)
    for ijk in VOXELS:
        np.testing.assert_allclose(volume.affine @ [*ijk, 1.0], [*_world_ras_by_hand(ijk), 1.0],
                                   rtol=0, atol=1e-9)
