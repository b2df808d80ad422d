"""Images in every format at the same place in the world; label maps and markups out.

The reference geometry comes from SimpleITK itself (the independent writer):
``TransformIndexToPhysicalPoint`` gives each voxel's LPS position, flipped to RAS here.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import formats_synth as synth  # noqa: E402

sitk = pytest.importorskip("SimpleITK")

SIZE = (28, 22, 12)
SPACING = (0.9, 1.3, 2.5)


def _truth_world(image) -> tuple[np.ndarray, np.ndarray]:
    """(voxel indices (V, 3), RAS world positions (V, 3)) of every voxel, from SimpleITK."""
    ijk = np.argwhere(np.ones(image.GetSize(), dtype=bool))
    lps = np.array([image.TransformIndexToPhysicalPoint(tuple(int(v) for v in idx))
                    for idx in ijk])
    return ijk, lps * np.array([-1.0, -1.0, 1.0])


def _write_all(tmp_path: Path, image) -> dict[str, Path]:
    paths = {}
    for name in ("image.nii.gz", "image.nrrd", "image.mha"):
        sitk.WriteImage(image, str(tmp_path / name))
        paths[name.split(".", 1)[1]] = tmp_path / name
    files = synth.write_series(tmp_path / "dicom", image)
    paths["dicom folder"] = tmp_path / "dicom"
    paths["dicom file"] = files[5]
    return paths


@pytest.fixture(scope="module")
def oblique(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("oblique")
    image = synth.oblique_image(SIZE, SPACING)
    return image, _write_all(tmp, image)


def test_every_format_puts_every_voxel_at_the_same_world_place(oblique):
    """NIfTI, NRRD, MetaImage and DICOM (folder or one file): <= 1e-3 mm, same intensities."""
    from core.io import load_volume

    image, paths = oblique
    ijk, world = _truth_world(image)
    truth_values = sitk.GetArrayFromImage(image).T
    direction = np.asarray(image.GetDirection()).reshape(3, 3)
    assert abs(np.abs(direction).max(axis=0) - 1).max() > 0.01  # really oblique
    assert direction[0, 0] > 0.9 and direction[1, 1] > 0.9      # axes in LPS order
    for kind, path in paths.items():
        vol = load_volume(path)
        assert vol.shape == SIZE, kind
        got = vol.voxel_to_world(ijk)
        err = np.linalg.norm(got - world, axis=1).max()
        assert err <= 1e-3, f"{kind}: {err} mm"
        assert np.array_equal(vol.data, truth_values), kind
        assert np.allclose(vol.spacing, SPACING, atol=1e-5), kind


def _placed_model_and_points(centre: np.ndarray):
    from core.evaluation.simulated_user import pca_model, simulate_user, synthetic_shapes
    from core.models.shape_model import ShapeModel

    shapes, faces = synthetic_shapes(10, subdivisions=3, seed=4, size=(4.0, 3.5, 7.0))
    base = pca_model(shapes[1:], faces)
    placed = np.eye(4)
    placed[:3, 3] = centre
    model = ShapeModel(base.mean, base.factors, base.coef_var, faces, placed, method="pca")
    user = simulate_user(shapes[0] + centre, faces, 5, rng=np.random.default_rng(1))
    return model, user


def test_segment_gives_the_same_label_region_in_world_for_every_format(oblique, tmp_path):
    from core.cli import main
    from core.io import load_volume, save_model, save_points

    image, paths = oblique
    centre = load_volume(paths["nii.gz"]).voxel_to_world((np.array(SIZE) - 1) / 2.0)
    model, user = _placed_model_and_points(centre)
    save_model(tmp_path / "model.npz", model)
    save_points(tmp_path / "pts.csv", user.points, user.normals)
    masks = {}
    for kind, path in paths.items():
        out = tmp_path / f"mask-{kind.replace(' ', '-')}.nii.gz"
        rc = main(["segment", "--model", str(tmp_path / "model.npz"), "--points",
                   str(tmp_path / "pts.csv"), "--image", str(path), "--out", str(out)])
        assert rc == 0, kind
        masks[kind] = load_volume(out)
    reference = masks["nii.gz"]
    n_inside = int(np.count_nonzero(reference.data))
    assert n_inside > 100  # a real structure (~0.4 cm^3 of 2.9 mm^3 voxels)
    for kind, mask in masks.items():
        world = mask.voxel_to_world(np.argwhere(mask.data > 0))  # labelled voxel centres
        ref_ijk = reference.world_to_voxel(world)
        assert np.abs(ref_ijk - np.rint(ref_ijk)).max() * max(SPACING) < 1e-3, kind
        assert len(world) == n_inside, kind
        assert np.all(reference.data[tuple(np.rint(ref_ijk).astype(int).T)] > 0), kind


def test_nrrd_and_mha_writers_keep_the_exact_geometry(tmp_path):
    """Our NRRD writer (also with a sheared affine) and MHA writer, read back by SimpleITK."""
    from core.io import load_volume, save_volume

    rng = np.random.default_rng(3)
    data = rng.integers(0, 200, size=(7, 6, 5)).astype(np.int16)
    affine = np.eye(4)
    affine[:3, :3] = synth.rotation((1, 2, 3), 25.0) @ np.diag([0.7, 1.1, 3.0])
    affine[:3, 3] = (12.5, -230.0, 41.0)
    for name in ("a.nrrd", "a.mha"):
        save_volume(tmp_path / name, data, affine)
        back = sitk.ReadImage(str(tmp_path / name))
        origin_lps = np.asarray(back.GetOrigin())
        assert np.allclose(origin_lps, affine[:3, 3] * [-1, -1, 1], atol=1e-9), name
        vol = load_volume(tmp_path / name)
        assert np.allclose(vol.affine, affine, atol=1e-9), name
        assert np.array_equal(vol.data, data) and vol.data.dtype == np.int16, name
    sheared = affine.copy()
    sheared[:3, 2] += 0.4 * sheared[:3, 0]  # NRRD space directions need not be orthogonal
    save_volume(tmp_path / "s.nrrd", data, sheared)
    text = (tmp_path / "s.nrrd").read_bytes().split(b"\n\n", 1)[0].decode()
    assert "space: left-posterior-superior" in text
    directions = text.split("space directions: ")[1].splitlines()[0]
    cols = [np.array([float(v) for v in c.strip("()").split(",")]) for c in directions.split()]
    assert np.allclose(np.stack(cols, axis=1), np.diag([-1, -1, 1]) @ sheared[:3, :3], atol=1e-12)


def test_seg_nrrd_carries_slicer_segment_fields(oblique, tmp_path):
    """segment --out x.seg.nrrd: Slicer's Segmentation fields with name, colour, extent."""
    from core.cli import main
    from core.io import load_volume, save_model, save_points
    from core.io.nrrd import segmentation_fields

    image, paths = oblique
    ref = load_volume(paths["dicom folder"])
    model, user = _placed_model_and_points(ref.voxel_to_world((np.array(SIZE) - 1) / 2.0))
    save_model(tmp_path / "caudate.npz", model)
    save_points(tmp_path / "pts.mrk.json", user.points)
    out = tmp_path / "caudate.seg.nrrd"
    rc = main(["segment", "--model", str(tmp_path / "caudate.npz"), "--points",
               str(tmp_path / "pts.mrk.json"), "--image", str(paths["dicom folder"]),
               "--out", str(out), "--label", "3", "--name", "Left caudate",
               "--color", "#1e90ff", "--no-normals"])
    assert rc == 0
    header = out.read_bytes().split(b"\n\n", 1)[0].decode()
    for line in ("Segmentation_MasterRepresentation:=Binary labelmap",
                 "Segmentation_ContainedRepresentationNames:=Binary labelmap|",
                 "Segment0_Layer:=0", "Segment0_LabelValue:=3", "Segment0_Name:=Left caudate",
                 "space: left-posterior-superior", "kinds: domain domain domain"):
        assert line in header
    (seg,) = segmentation_fields(out)
    assert np.allclose([float(v) for v in seg["Color"].split()], (30 / 255, 144 / 255, 1.0),
                       atol=1e-5)
    labels = load_volume(out)
    assert np.allclose(labels.affine, ref.affine, atol=1e-9)
    inside = np.argwhere(labels.data == 3)
    extent = [int(v) for v in seg["Extent"].split()]
    assert extent == [v for lo, hi in zip(inside.min(0), inside.max(0)) for v in (lo, hi)]
    assert set(np.unique(labels.data)) == {0, 3}


def test_dicom_series_choice_by_uid_or_most_files(tmp_path, capsys):
    from core.cli import main
    from core.io import load_volume

    big = synth.oblique_image((10, 9, 8), (1.0, 1.0, 2.0))
    small = synth.oblique_image((6, 5, 4), (1.0, 1.0, 3.0), seed=1)
    synth.write_series(tmp_path / "mixed", big, uid=synth.UID_ROOT + ".21", description="T1 big")
    synth.write_series(tmp_path / "mixed", small, uid=synth.UID_ROOT + ".22",
                       description="scout", name="S{:04d}.dcm")
    notes = []
    assert load_volume(tmp_path / "mixed", notify=notes.append).shape == (10, 9, 8)
    assert len(notes) == 1 and synth.UID_ROOT + ".21" in notes[0] and "8 files" in notes[0]
    assert "DOE" not in notes[0] and "PID-12345" not in notes[0]  # never patient tags
    vol = load_volume(tmp_path / "mixed", series=synth.UID_ROOT + ".22")
    assert vol.shape == (6, 5, 4) and np.array_equal(vol.data, sitk.GetArrayFromImage(small).T)
    # one file names its own series
    assert load_volume(tmp_path / "mixed" / "S0002.dcm").shape == (6, 5, 4)
    rc = main(["segment", "--model", "m.npz", "--points", "p.csv", "--image",
               str(tmp_path / "mixed"), "--series", "1.2.3.4", "--out", str(tmp_path / "o.nii")])
    err = capsys.readouterr().err
    assert rc == 2 and "no series 1.2.3.4" in err and synth.UID_ROOT + ".22" in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("system", ["LPS", "RAS", ""])
def test_markups_in_lps_or_ras_read_at_the_same_world_place(tmp_path, system):
    """Files written exactly per Slicer's markups schema (v1.0.3), both coordinate systems."""
    import json

    from core.io import load_points, save_points

    ras = np.array([[10.0, -20.0, 30.0], [-5.5, 7.25, -1.0]])
    flip = np.array([-1.0, -1.0, 1.0]) if system in ("LPS", "") else np.ones(3)
    doc = {
        "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                   "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
        "markups": [{
            "type": "Fiducial", "coordinateSystem": system, "coordinateUnits": "mm",
            "locked": False, "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d",
            "lastUsedControlPointNumber": 3,
            "controlPoints": [
                {"id": str(i + 1), "label": f"F-{i + 1}", "description": "", "associatedNodeID": "",
                 "position": list(p * flip), "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0,
                                                             0.0, 0.0, 1.0],
                 "selected": True, "locked": False, "visibility": True,
                 "positionStatus": "defined"} for i, p in enumerate(ras)
            ],
            "measurements": [],
        }],
    }
    if system == "":
        del doc["markups"][0]["coordinateSystem"]  # absent: Slicer reads LPS
    (tmp_path / "f.mrk.json").write_text(json.dumps(doc))
    pts = load_points(tmp_path / "f.mrk.json")
    assert np.allclose(pts.points, ras)
    save_points(tmp_path / "out.mrk.json", pts)
    written = json.loads((tmp_path / "out.mrk.json").read_text())["markups"][0]
    declared = np.array([-1.0, -1.0, 1.0]) if written["coordinateSystem"] == "LPS" else np.ones(3)
    assert np.allclose([cp["position"] for cp in written["controlPoints"]], ras * declared)


@pytest.mark.parametrize("compressor, syntax", [("JPEG2000", "1.2.840.10008.1.2.4.90"),
                                                ("JPEG", "1.2.840.10008.1.2.4.70")])
def test_compressed_series_gdcm_decodes_open_identically(tmp_path, compressor, syntax):
    """Lossless JPEG 2000 and JPEG series: same voxels and geometry as the uncompressed one."""
    from core.io import load_volume
    from core.io.dicom import read_file_meta

    image = synth.oblique_image((12, 10, 6), (0.9, 1.3, 2.5), seed=5)
    files = synth.write_series(tmp_path / "c", image, compressor=compressor)
    assert read_file_meta(files[0])["0002|0010"] == syntax
    plain = synth.write_series(tmp_path / "p", image)
    a, b = load_volume(tmp_path / "c"), load_volume(plain[0])
    assert np.array_equal(a.data, sitk.GetArrayFromImage(image).T)
    assert np.allclose(a.affine, b.affine, atol=1e-9)
