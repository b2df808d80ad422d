"""The DBS workflow headless, end to end, on a synthetic DICOM series with a known truth.

A "patient": the demo template's T1 around the basal ganglia, moved by a known rigid
transform M (template world -> patient world) and written as an axial DICOM series (pydicom,
1 x 1 x 1.5 mm). Then: read the series, place the library models automatically (registration
to the template), fit the left and right STN and the left GPi from contours drawn on their
true surfaces (a shape of each model moved by M), plan a trajectory with a Medtronic 3389 lead
through ``ssm-studio plan`` (contacts in AC-PC with their structure, warnings) and export
DICOM SEG + RTSTRUCT, read back independently (pydicom, highdicom, SimpleITK).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from core.cli import main as cli_main  # noqa: E402
from core.evaluation.simulated_user import simulate_user  # noqa: E402
from core.geometry.toolkit import rodrigues, symmetric_surface_distance  # noqa: E402
from core.io import load_model, load_volume  # noqa: E402
from core.io.model_library import structure_info  # noqa: E402
from core.planning.frames import ACPCFrame  # noqa: E402
from core.planning.report import model_target  # noqa: E402
from core.reconstruction import fit_points  # noqa: E402
from core.registration.placement import placement_through, register_to_template  # noqa: E402
from core.registration.volumes import default_template_path, resample  # noqa: E402
from core.session.document import Session, SessionStructure, save_session  # noqa: E402

MODELS = Path(__file__).resolve().parents[1] / "resources" / "models"
_LPS = np.array([-1.0, -1.0, 1.0])
# The patient's anatomy = the template's moved by M: 4 degrees about an oblique axis, 3 mm.
ROTATION = rodrigues(np.deg2rad(4.0) * np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93]))
M = np.eye(4)
M[:3, :3], M[:3, 3] = ROTATION, [2.0, -3.0, 1.5]
# Template (MNI) landmarks: the AC-PC frame of the plan, and a dorsal-anterior-lateral entry.
AC, PC, MIDLINE = np.array([0.0, 1.5, -4.0]), np.array([0.0, -25.0, -2.0]), np.array([0.0, -10.0, 40.0])


def _moved(points):
    return np.asarray(points) @ M[:3, :3].T + M[:3, 3]


def _individual(world: np.ndarray, rng) -> np.ndarray:
    """The patient's own nucleus (4x4, applied after M): where the template registration puts
    it, moved by a further 1.5 mm and turned by 5 degrees about its centroid (anatomy the
    registration cannot see)."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    rotation = rodrigues(np.deg2rad(5.0) * axis / np.linalg.norm(axis))
    centre = world.mean(axis=0)
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = centre - rotation @ centre + 1.5 * shift / np.linalg.norm(shift)
    return out


def _apply(matrix: np.ndarray, points) -> np.ndarray:
    return np.asarray(points) @ matrix[:3, :3].T + matrix[:3, 3]


def write_series(folder: Path, data: np.ndarray, spacing, origin_lps,
                 orientation=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)), reverse: bool = False
                 ) -> list[Path]:
    """An MR series, one file per slice: slice k of ``data`` (I columns, J rows, K slices);
    ``orientation`` (LPS) is the direction along a row and along a column (default axial:
    towards the patient's left, towards posterior); slice k at origin + k * spacing[2] * normal;
    ``reverse`` writes the files (and instance numbers) in the opposite order."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    folder.mkdir(parents=True)
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    files = []
    for k in range(data.shape[2]):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.4"
        meta.MediaStorageSOPInstanceUID = uid = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = meta.MediaStorageSOPClassUID, uid
        ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = "Test^Dbs", "DBS01", "", "O"
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.StudyDate, ds.StudyTime, ds.StudyID, ds.AccessionNumber = "20260101", "120000", "1", ""
        ds.ReferringPhysicianName = ""
        ds.Modality, ds.SeriesNumber = "MR", 3
        ds.InstanceNumber = data.shape[2] - k if reverse else k + 1
        ds.Manufacturer = "synthetic"
        along_row, along_col = (np.asarray(v, dtype=float) for v in orientation)
        normal = np.cross(along_row, along_col)
        ds.ImageOrientationPatient = [float(v) for v in (*along_row, *along_col)]
        ds.ImagePositionPatient = [float(v) for v in
                                   np.asarray(origin_lps) + k * spacing[2] * normal]
        ds.PixelSpacing = [float(spacing[1]), float(spacing[0])]
        ds.SliceThickness = float(spacing[2])
        ds.Rows, ds.Columns = data.shape[1], data.shape[0]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.PixelData = np.ascontiguousarray(data[:, :, k].T.astype(np.uint16)).tobytes()
        path = folder / f"slice{(data.shape[2] - 1 - k) if reverse else k:03d}.dcm"
        ds.save_as(str(path), enforce_file_format=True)
        files.append(path)
    return files


@pytest.fixture(scope="module")
def patient(tmp_path_factory):
    """The DICOM series of the moved template, its folder and its voxel -> world RAS matrix."""
    folder = tmp_path_factory.mktemp("dbs") / "series"
    template = load_volume(default_template_path())
    spacing = np.array([1.0, 1.0, 1.5])
    shape = (110, 120, 56)                    # x -55..55, y -70..50, z -40..44 mm (RAS)
    origin_lps = np.array([-55.0, -50.0, -40.0])  # first pixel: patient right, anterior
    affine = np.array([[-spacing[0], 0, 0, -origin_lps[0]], [0, -spacing[1], 0, -origin_lps[1]],
                       [0, 0, spacing[2], origin_lps[2]], [0, 0, 0, 1.0]])
    data = resample(template.data.astype(np.float32), template.affine, M, shape, affine)
    files = write_series(folder, np.clip(np.rint(data * 8), 0, 4095), spacing, origin_lps)
    return folder, files, affine


@pytest.mark.slow
def test_dbs_plan_from_a_dicom_series_end_to_end(patient, tmp_path, capsys):
    folder, files, affine = patient
    image = load_volume(folder)                       # the project's DICOM reader
    assert np.allclose(image.affine, affine, atol=1e-4)

    # automatic placement: image -> template; its inverse must be M where the STN is
    registration = register_to_template(image, levels_mm=(4.0, 2.0), random_state=0)
    template_to_image = np.linalg.inv(registration.transform)
    probe = np.array([[-12.0, -13.0, -8.0], [12.0, -13.0, -8.0]])
    placed_error = np.linalg.norm(_moved(probe) - (probe @ template_to_image[:3, :3].T
                                                   + template_to_image[:3, 3]), axis=1)
    assert placed_error.max() < 1.0, placed_error

    rng = np.random.default_rng(29)
    records, truths, fits = [], {}, {}
    for file_name in ("left_stn.npz", "right_stn.npz", "left_gpi.npz"):
        model = load_model(MODELS / file_name)
        info = structure_info(model)
        assert info.template_space == "MNI152NLin2009aSym" and info.target is not None
        coef = rng.standard_normal(model.n_factors) * np.sqrt(model.coef_var) * 2.0
        individual = _individual(_moved(model.world_instance(coef)), rng)
        true_world = _apply(individual, _moved(model.world_instance(coef)))
        truths[file_name] = (individual, model, coef)
        user = simulate_user(true_world, model.faces, 3, spacing=1.0, noise=0.1, rng=rng)
        placement = placement_through(model, registration.transform)
        placed = model.mean @ placement[:3, :3].T + placement[:3, 3]
        before = symmetric_surface_distance(placed, model.faces, true_world, model.faces)
        fit = fit_points(model, user.points, user.normals, placement=placement)
        error = symmetric_surface_distance(fit.vertices, model.faces, true_world, model.faces)
        assert before > 0.5 and error < 0.15, (file_name, before, error)
        fits[file_name] = fit
        records.append(SessionStructure(name=info.name, side=info.side, color=info.color,
                                        model_path=MODELS / file_name, points=user.points,
                                        normals=user.normals, coef=fit.coef, pose=fit.pose,
                                        placement=placement))

    # targets: each model's stored clinical target, carried by the fit
    targets = {}
    for file_name, fit in fits.items():
        individual, model, coef = truths[file_name]
        local = model_target(model.mean, model.faces, model.instance(fit.coef),
                             structure_info(model).target)
        targets[file_name] = local @ fit.pose[:3, :3].T + fit.pose[:3, 3]
        truth = model_target(model.mean, model.faces, model.instance(coef),
                             structure_info(model).target)
        truth = _apply(individual, _moved(_apply(model.world_transform, truth)))
        assert np.linalg.norm(targets[file_name] - truth) < 0.3, file_name

    # a plan: left STN on its target; right STN aimed 3 mm lateral of it (outside)
    frame_points = {k: _moved(v).tolist() for k, v in (("ac", AC), ("pc", PC), ("midline", MIDLINE))}
    frame = ACPCFrame.from_points(frame_points["ac"], frame_points["pc"], frame_points["midline"])
    up = frame.rotation.T @ np.array([0.0, 0.45, 0.89])          # anterior-superior
    left_target = targets["left_stn.npz"]
    right_target = targets["right_stn.npz"] + 4.0 * frame.rotation[0]  # more lateral (R)
    planning = {**frame_points, "structures": [
        {"structure": 0, "target": left_target.tolist(),
         "entry": (left_target + 65.0 * (up - 0.25 * frame.rotation[0])).tolist()},
        {"structure": 1, "target": right_target.tolist(),
         "entry": (right_target + 65.0 * (up + 0.25 * frame.rotation[0])).tolist()}]}
    session = Session(image=folder, structures=records, info={"planning": planning})
    save_session(tmp_path / "plan_session.json", session)

    out = tmp_path / "plan.json"
    export = tmp_path / "export"
    assert cli_main(["plan", "--session", str(tmp_path / "plan_session.json"), "--out", str(out),
                     "--lead", "medtronic-3389", "--export", str(export)]) == 0
    report = json.loads(out.read_text())
    printed = capsys.readouterr().out
    assert "contact   0: AC-PC (" in printed
    assert "WARNING (subthalamic nucleus (right)): the target lies" in printed
    # --json: the same report on stdout
    assert cli_main(["plan", "--session", str(tmp_path / "plan_session.json"), "--out",
                     str(tmp_path / "again.json"), "--lead", "medtronic-3389", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == report

    # contacts in AC-PC: the patient's AC-PC coordinates equal the template's (M is rigid)
    template_frame = ACPCFrame.from_points(AC, PC, MIDLINE)
    left = report["structures"][0]["trajectory"]
    contacts = left["lead"]["contacts"]
    assert [c["contact"] for c in contacts] == ["0", "1", "2", "3"]
    inverse_m = np.linalg.inv(M)
    for c in contacts:
        in_template = np.asarray(c["world"]) @ inverse_m[:3, :3].T + inverse_m[:3, 3]
        assert np.allclose(c["acpc"], template_frame.to_acpc(in_template), atol=1e-6)
        assert np.allclose(c["voxel"], image.world_to_voxel(np.asarray(c["world"])), atol=1e-9)
    # the lowest contact (2.25 mm above the target inside the dorsolateral STN) in the STN,
    # the structure decided from its signed distance to the fitted surface
    names = [r.name for r in records]
    left_stn_name = report["structures"][0]["name"]
    assert contacts[0]["structure"] == left_stn_name or \
        contacts[0]["signed_distance_mm"][left_stn_name] > 0
    assert contacts[0]["signed_distance_mm"][left_stn_name] < 1.5
    assert left_stn_name.startswith(names[0])
    kinds_left = {w["kind"] for w in left["warnings"]}
    assert "target_outside" not in kinds_left
    # the right trajectory's target is 4 mm lateral of the STN's dorsolateral target: outside
    right = report["structures"][1]["trajectory"]
    outside = [w for w in right["warnings"] if w["kind"] == "target_outside"]
    assert len(outside) == 1 and 0.5 < outside[0]["distance_mm"] < 4.0
    assert report["checked_surfaces"] == ["ventricles"]
    assert {r["structure"] for r in left["path_distances"]} >= {"ventricles"}

    # clinical exports, read back independently
    seg_path = export / "plan_structures.seg.dcm"
    rt_path = export / "plan_structures.rtstruct.dcm"
    assert seg_path.is_file() and rt_path.is_file() and (export / "plan_contacts.csv").is_file()
    label_map = load_volume(export / "plan_labels.nii.gz")
    _check_seg(seg_path, files, label_map, [s["name"] for s in report["structures"]])
    _check_rtstruct(rt_path, files, label_map, report)


def test_seg_and_rtstruct_sit_on_an_oblique_series_written_backwards(tmp_path):
    """An oblique series (20 degrees about an oblique axis, anisotropic voxels, files in
    reverse order): SEG and RTSTRUCT of two spheres read back at the label map's voxels."""
    from analytic import sphere as icosphere

    from core.planning.report import PlannedStructure, export_all_structures

    rotation = rodrigues(np.deg2rad(20.0) * np.array([0.6, 0.0, 0.8]))
    spacing = np.array([0.9, 1.1, 1.6])
    rng = np.random.default_rng(3)
    data = rng.integers(0, 1000, size=(40, 36, 18))
    folder = tmp_path / "oblique"
    files = write_series(folder, data, spacing, np.array([10.0, -20.0, 5.0]),
                         orientation=(rotation[:, 0], rotation[:, 1]), reverse=True)
    volume = load_volume(folder)
    centre = volume.voxel_to_world(np.array([20.0, 18.0, 9.0]))
    spheres = [PlannedStructure("subthalamic nucleus (left)", *icosphere(7.0, centre, 3),
                                (0.93, 0.68, 0.05)),
               PlannedStructure("red nucleus (left)", *icosphere(4.0, centre + [0, 0, 9.0], 3),
                                (0.86, 0.08, 0.24))]
    written = export_all_structures(tmp_path / "out", spheres, volume, dicom_series=files,
                                    meshes=False)
    names = [s.name for s in spheres]
    label_map = load_volume(tmp_path / "out" / "plan_labels.nii.gz")
    assert (tmp_path / "out" / "plan_structures.seg.dcm") in written
    _check_seg(tmp_path / "out" / "plan_structures.seg.dcm", files, label_map, names)
    _check_rtstruct(tmp_path / "out" / "plan_structures.rtstruct.dcm", files, label_map,
                    {"structures": [{"name": s.name, "color": s.color} for s in spheres]})


def test_a_series_without_frame_of_reference_gets_no_seg_but_the_rest(tmp_path):
    """SEG and RTSTRUCT must reference the series' frame of reference: a series that lacks it
    (non-conformant, some exporters drop it) gets a one-line note naming the file (or, without
    a notes list, an error), the label maps are written; the declared outputs match."""
    import pydicom
    from analytic import sphere as icosphere

    from core.errors import DataFileError
    from core.planning.report import PlannedStructure, all_structures_outputs, export_all_structures

    data = np.random.default_rng(4).integers(0, 1000, size=(20, 18, 12))
    files = write_series(tmp_path / "series", data, np.array([1.0, 1.0, 1.5]),
                         np.array([0.0, 0.0, 0.0]))
    volume = load_volume(tmp_path / "series")
    centre = volume.voxel_to_world(np.array([10.0, 9.0, 6.0]))
    spheres = [PlannedStructure("sphere", *icosphere(5.0, centre, 2), (0.9, 0.7, 0.1))]
    expected = all_structures_outputs(tmp_path / "ok", spheres, volume, dicom_series=files)
    assert sorted(export_all_structures(tmp_path / "ok", spheres, volume,
                                        dicom_series=files)) == sorted(expected)
    for f in files:
        ds = pydicom.dcmread(str(f))
        del ds.FrameOfReferenceUID
        ds.save_as(str(f))
    notes: list = []
    written = export_all_structures(tmp_path / "out", spheres, volume, dicom_series=files,
                                    meshes=False, notes=notes)
    assert {p.name for p in written} == {"plan_labels.seg.nrrd", "plan_labels.nii.gz",
                                         "plan_labels.txt"}
    assert len(notes) == 1 and "Frame of Reference UID" in notes[0] and files[0].name in notes[0]
    with pytest.raises(DataFileError, match="Frame of Reference UID"):
        export_all_structures(tmp_path / "again", spheres, volume, dicom_series=files,
                              meshes=False)


def _check_seg(seg_path, files, label_map, names):
    """Segment names, the source series referenced, and each segment rebuilt from the SEG's
    own frame geometry (per-frame positions, shared orientation and spacing) as a SimpleITK
    image, resampled onto the label map's grid: Dice >= 0.99 with the label map."""
    import SimpleITK as sitk

    seg = hd.seg.segread(str(seg_path))
    labels = [seg.get_segment_description(n).segment_label for n in seg.segment_numbers]
    assert labels == names
    source = [pydicom.dcmread(str(f)) for f in files]
    assert {uid[1] for uid in seg.get_source_image_uids()} == {source[0].SeriesInstanceUID}
    raw = pydicom.dcmread(str(seg_path))
    frames = raw.pixel_array.reshape(-1, int(raw.Rows), int(raw.Columns))
    shared = raw.SharedFunctionalGroupsSequence[0]
    iop = np.asarray(shared.PlaneOrientationSequence[0].ImageOrientationPatient, float)
    row_spacing, col_spacing = (float(v) for v in shared.PixelMeasuresSequence[0].PixelSpacing)
    normal = np.cross(iop[:3], iop[3:])
    truth = np.asarray(label_map.data)
    reference = _label_reference(label_map)
    for s, name in enumerate(names, start=1):
        rows = [(np.asarray(g.PlanePositionSequence[0].ImagePositionPatient, float), frames[i])
                for i, g in enumerate(raw.PerFrameFunctionalGroupsSequence)
                if g.SegmentIdentificationSequence[0].ReferencedSegmentNumber == s]
        rows.sort(key=lambda r: r[0] @ normal)
        positions = np.array([r[0] for r in rows])
        steps = np.diff(positions @ normal)
        assert np.allclose(steps, steps[0])
        image = sitk.GetImageFromArray(np.stack([r[1] for r in rows]).astype(np.uint8))
        image.SetOrigin(positions[0].tolist())
        image.SetSpacing([col_spacing, row_spacing, float(steps[0])])
        image.SetDirection(np.column_stack([iop[:3], iop[3:], normal]).reshape(-1).tolist())
        resampled = sitk.Resample(image, reference, sitk.Transform(), sitk.sitkNearestNeighbor,
                                  0, sitk.sitkUInt8)
        mask = sitk.GetArrayFromImage(resampled).transpose(2, 1, 0) > 0
        expected = truth == s
        dice = 2 * (mask & expected).sum() / (mask.sum() + expected.sum())
        assert dice >= 0.99, (name, dice)


def _label_reference(volume):
    """A SimpleITK image on the label map's grid (LPS direction and origin)."""
    import SimpleITK as sitk

    a = np.asarray(volume.affine)
    flip = np.diag([-1.0, -1.0, 1.0])
    spacing = np.linalg.norm(a[:3, :3], axis=0)
    image = sitk.Image([int(s) for s in volume.shape], sitk.sitkUInt8)
    image.SetSpacing(spacing.tolist())
    image.SetOrigin((flip @ a[:3, 3]).tolist())
    image.SetDirection((flip @ a[:3, :3] / spacing).reshape(-1).tolist())
    return image


def _check_rtstruct(rt_path, files, label_map, report):
    from matplotlib.path import Path as Polygon

    rt = pydicom.dcmread(str(rt_path))
    source = {d.SOPInstanceUID: d for d in (pydicom.dcmread(str(f)) for f in files)}
    assert rt.Modality == "RTSTRUCT"
    series = rt.ReferencedFrameOfReferenceSequence[0].RTReferencedStudySequence[0] \
        .RTReferencedSeriesSequence[0]
    assert series.SeriesInstanceUID == next(iter(source.values())).SeriesInstanceUID
    names = [roi.ROIName for roi in rt.StructureSetROISequence]
    assert names == [s["name"] for s in report["structures"]]
    colours = [list(c.ROIDisplayColor) for c in rt.ROIContourSequence]
    assert colours == [[int(round(255 * v)) for v in s["color"]] for s in report["structures"]]
    inverse = np.linalg.inv(label_map.affine)
    truth = np.asarray(label_map.data)
    for number, roi in enumerate(rt.ROIContourSequence, start=1):
        inside_fill, inside_truth = 0, 0
        for item in roi.ContourSequence:
            ds = source[item.ContourImageSequence[0].ReferencedSOPInstanceUID]
            lps = np.asarray(item.ContourData, dtype=float).reshape(-1, 3)
            # drawn on the image it references: in that image's plane (DICOM patient LPS)
            normal = np.cross(*np.asarray(ds.ImageOrientationPatient, dtype=float).reshape(2, 3))
            offset = (lps - np.asarray(ds.ImagePositionPatient, dtype=float)) @ normal
            np.testing.assert_allclose(offset, 0.0, atol=1e-3)
            pts = lps * _LPS
            ijk = pts @ inverse[:3, :3].T + inverse[:3, 3]
            k = int(round(ijk[0, 2]))
            assert np.allclose(ijk[:, 2], k, atol=1e-3)        # on its slice's plane
            plane = truth[:, :, k] == number
            # every contour point within half a voxel of the label map's boundary (the pixel
            # edges between an inside and an outside voxel centre)
            chebyshev, euclidean = _max_distance_to_boundary(ijk[:, :2], plane)
            assert chebyshev <= 0.5 and euclidean <= 0.5
            # independent rasterisation of the polygon vs the label map's slice
            grid = np.stack(np.meshgrid(np.arange(plane.shape[0]), np.arange(plane.shape[1]),
                                        indexing="ij"), -1).reshape(-1, 2)
            filled = Polygon(ijk[:, :2]).contains_points(grid).reshape(plane.shape)
            inside_fill += filled.sum()
            inside_truth += (plane & filled).sum()
        total_truth = (truth == number).sum()
        # the polygons filled (pixel centres inside) give back the label map's voxels
        assert inside_truth == total_truth == inside_fill


def _max_distance_to_boundary(points_ij: np.ndarray, plane: np.ndarray) -> tuple[float, float]:
    """Largest Chebyshev and Euclidean distances (voxels) from in-plane points to the label's
    pixel-edge boundary (axis-aligned edges: one closest point serves both norms)."""
    edges = []
    for axis in (0, 1):
        a, b = plane, np.roll(plane, -1, axis=axis)
        change = np.argwhere(a != b)
        change = change[change[:, axis] < plane.shape[axis] - 1]
        mid = change.astype(float)
        mid[:, axis] += 0.5                                 # the edge between the two centres
        other = 1 - axis
        start, end = mid.copy(), mid.copy()
        start[:, other] -= 0.5
        end[:, other] += 0.5
        edges.append(np.stack([start, end], 1))
    seg = np.concatenate(edges)                             # (E, 2, 2)
    a, d = seg[:, 0], seg[:, 1] - seg[:, 0]
    t = np.clip(np.einsum("pei,ei->pe", points_ij[:, None] - a[None], d) / (d ** 2).sum(1), 0, 1)
    offset = np.abs(points_ij[:, None] - (a[None] + t[..., None] * d[None]))
    return (float(offset.max(axis=2).min(axis=1).max()),
            float(np.linalg.norm(offset, axis=2).min(axis=1).max()))
