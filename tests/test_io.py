"""Tests for core.io: every format round-trips, every broken file gives a clear error.

The bad-input table generates each broken file in ``tmp_path`` and checks that the loader
raises :class:`DataFileError` whose message names the file and says what is wrong. The
world-coordinate tests use an oblique affine whose voxel -> RAS mapping is worked out by hand.
"""

from __future__ import annotations

import gzip
import json
import math
import os
import stat
import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import pyvista as pv
import vtk

from core import io
from core.io import DataFileError, PointSet, TriMesh
from core.models.shape_model import ShapeModel

NIBABEL_DATA = Path(nib.__file__).parent / "tests" / "data"
GIFTI_DATA = Path(nib.__file__).parent / "gifti" / "tests" / "data"


# --------------------------------------------------------------------------------------
# Helpers that build valid data
# --------------------------------------------------------------------------------------


def sphere_mesh() -> TriMesh:
    return TriMesh.from_polydata(pv.Sphere(radius=7.0, theta_resolution=10, phi_resolution=8,
                                           center=(12.0, -30.0, 5.0)))


def small_model(n_factors: int = 3) -> ShapeModel:
    mesh = sphere_mesh()
    rng = np.random.default_rng(1)
    factors = rng.normal(size=(n_factors, mesh.n_vertices, 3))
    return ShapeModel(mean=mesh.vertices, factors=factors,
                      coef_var=np.array([4.0, 2.0, 0.5][:n_factors]), faces=mesh.faces,
                      world_transform=_oblique_affine(), method="lsf",
                      params={"n_components": n_factors, "sparsity": 0.3},
                      source_meshes=["a.vtk", "b.vtk"], info={"build_seconds": 1.5})


def _oblique_affine() -> np.ndarray:
    """Voxel sizes (2, 1, 3) mm, rotated 30 degrees about z, origin (10, -20, 5)."""
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    return np.array([[2 * c, -1 * s, 0.0, 10.0],
                     [2 * s, 1 * c, 0.0, -20.0],
                     [0.0, 0.0, 3.0, 5.0],
                     [0.0, 0.0, 0.0, 1.0]])


def _save_raw_nifti(path: Path, data: np.ndarray, affine=np.eye(4)) -> Path:
    nib.save(nib.Nifti1Image(data, affine), str(path))
    return path


def _triangle_set(vertices: np.ndarray, faces: np.ndarray, decimals: int = 4) -> set:
    """The triangles as sets of rounded corner coordinates (independent of vertex order)."""
    corners = np.round(vertices[faces], decimals) + 0.0  # + 0.0 turns -0.0 into 0.0
    return {tuple(sorted(map(tuple, tri))) for tri in corners}


def _write_markups(path: Path, doc: object) -> Path:
    path.write_text(json.dumps(doc))
    return path


# --------------------------------------------------------------------------------------
# Bad inputs: (builder(tmp_path) -> file, loader, phrases the message must contain)
# --------------------------------------------------------------------------------------


def _bad_missing(tmp: Path) -> Path:
    return tmp / "missing.nii.gz"


def _bad_empty(tmp: Path) -> Path:
    (tmp / "empty.nii.gz").write_bytes(b"")
    return tmp / "empty.nii.gz"


def _bad_truncated_gz(tmp: Path) -> Path:
    good = _save_raw_nifti(tmp / "good.nii.gz", np.arange(1000, dtype=np.float32).reshape(10, 10, 10))
    raw = good.read_bytes()
    (tmp / "truncated.nii.gz").write_bytes(raw[: len(raw) // 2])
    return tmp / "truncated.nii.gz"


def _bad_truncated_nii(tmp: Path) -> Path:
    good = _save_raw_nifti(tmp / "good.nii", np.zeros((10, 10, 10), np.float32))
    (tmp / "cut.nii").write_bytes(good.read_bytes()[:600])
    return tmp / "cut.nii"


def _bad_random_nii(tmp: Path) -> Path:
    (tmp / "random.nii").write_bytes(np.random.default_rng(0).bytes(2000))
    return tmp / "random.nii"


def _bad_random_niigz(tmp: Path) -> Path:
    (tmp / "random.nii.gz").write_bytes(np.random.default_rng(1).bytes(2000))
    return tmp / "random.nii.gz"


def _bad_gz_of_text(tmp: Path) -> Path:
    with gzip.open(tmp / "text.nii.gz", "wb") as fh:
        fh.write(b"this is gzip-compressed text, not a NIfTI header\n" * 20)
    return tmp / "text.nii.gz"


def _bad_2d(tmp: Path) -> Path:
    return _save_raw_nifti(tmp / "flat.nii", np.zeros((8, 9), np.float32))


def _bad_4d(tmp: Path) -> Path:
    return _save_raw_nifti(tmp / "series.nii.gz", np.zeros((6, 7, 8, 3), np.int16))


def _bad_nan_affine(tmp: Path) -> Path:
    path = _save_raw_nifti(tmp / "nan_affine.nii", np.zeros((5, 6, 7), np.float32))
    raw = bytearray(path.read_bytes())
    raw[280:284] = np.float32(np.nan).tobytes()  # srow_x[0]; sform_code is 2 (aligned)
    path.write_bytes(bytes(raw))
    return path


def _bad_singular_affine(tmp: Path) -> Path:
    path = _save_raw_nifti(tmp / "flat_affine.nii", np.zeros((5, 6, 7), np.float32))
    raw = bytearray(path.read_bytes())
    raw[280:296] = np.zeros(4, np.float32).tobytes()  # srow_x = 0: no extent along x
    path.write_bytes(bytes(raw))
    return path


def _bad_nifti_pair_header(tmp: Path) -> Path:
    img = nib.Nifti1Pair(np.zeros((4, 4, 4), np.float32), np.eye(4))
    nib.save(img, str(tmp / "pair.hdr"))
    (tmp / "pair_header.nii").write_bytes((tmp / "pair.hdr").read_bytes())
    return tmp / "pair_header.nii"


def _bad_complex(tmp: Path) -> Path:
    return _save_raw_nifti(tmp / "complex.nii", np.zeros((4, 4, 4), np.complex64))


def _bad_volume_suffix(tmp: Path) -> Path:
    _save_raw_nifti(tmp / "scan.nii", np.zeros((4, 4, 4), np.float32))
    os.replace(tmp / "scan.nii", tmp / "scan.img")
    return tmp / "scan.img"


def _bad_mesh_nan(tmp: Path) -> Path:
    poly = pv.Sphere(theta_resolution=8, phi_resolution=6)
    points = poly.points.copy()
    points[[2, 5]] = np.nan
    poly.points = points
    poly.save(str(tmp / "nan_vertices.vtk"))
    return tmp / "nan_vertices.vtk"


def _bad_mesh_empty(tmp: Path) -> Path:
    pv.PolyData().save(str(tmp / "empty_mesh.vtp"))
    return tmp / "empty_mesh.vtp"


def _bad_mesh_lines(tmp: Path) -> Path:
    pv.Line((0, 0, 0), (1, 2, 3), resolution=6).save(str(tmp / "lines_only.vtk"))
    return tmp / "lines_only.vtk"


def _bad_mesh_points_ply(tmp: Path) -> Path:
    (tmp / "points_only.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    return tmp / "points_only.ply"


def _bad_stl(tmp: Path) -> Path:
    (tmp / "garbage.stl").write_bytes(np.random.default_rng(2).bytes(1000))
    return tmp / "garbage.stl"


def _bad_vtk(tmp: Path) -> Path:
    (tmp / "garbage.vtk").write_text("hello\nthis is not a VTK file\n")
    return tmp / "garbage.vtk"


def _bad_vtk_truncated(tmp: Path) -> Path:
    pv.Sphere().save(str(tmp / "full.vtk"), binary=True)
    raw = (tmp / "full.vtk").read_bytes()
    (tmp / "cut.vtk").write_bytes(raw[: int(len(raw) * 0.7)])
    return tmp / "cut.vtk"


def _bad_vtp_truncated(tmp: Path) -> Path:
    pv.Sphere().save(str(tmp / "full.vtp"))
    raw = (tmp / "full.vtp").read_bytes()
    (tmp / "cut.vtp").write_bytes(raw[: len(raw) // 2])
    return tmp / "cut.vtp"


def _bad_ply_truncated(tmp: Path) -> Path:
    pv.Sphere().save(str(tmp / "full.ply"), binary=True)
    raw = (tmp / "full.ply").read_bytes()
    (tmp / "cut.ply").write_bytes(raw[: len(raw) // 2])
    return tmp / "cut.ply"


def _bad_ply_garbage(tmp: Path) -> Path:
    (tmp / "garbage.ply").write_bytes(np.random.default_rng(3).bytes(500))
    return tmp / "garbage.ply"


def _bad_obj(tmp: Path) -> Path:
    (tmp / "garbage.obj").write_text("this is not\na wavefront file\n")
    return tmp / "garbage.obj"


def _bad_obj_index(tmp: Path) -> Path:
    (tmp / "bad_index.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    return tmp / "bad_index.obj"


def _bad_gifti_no_triangles(tmp: Path) -> Path:
    img = nib.gifti.GiftiImage(darrays=[nib.gifti.GiftiDataArray(
        np.zeros((10, 3), np.float32), intent="NIFTI_INTENT_POINTSET")])
    nib.save(img, str(tmp / "points.gii"))
    return tmp / "points.gii"


def _bad_gifti_data_only(tmp: Path) -> Path:
    img = nib.gifti.GiftiImage(darrays=[nib.gifti.GiftiDataArray(
        np.zeros(10, np.float32), intent="NIFTI_INTENT_SHAPE")])
    nib.save(img, str(tmp / "thickness.gii"))
    return tmp / "thickness.gii"


def _bad_gifti_garbage(tmp: Path) -> Path:
    (tmp / "garbage.gii").write_text("<GIFTI><DataArray>")
    return tmp / "garbage.gii"


def _bad_mesh_suffix(tmp: Path) -> Path:
    (tmp / "surface.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    return tmp / "surface.off"


def _bad_csv_header(tmp: Path) -> Path:
    (tmp / "header.csv").write_text("a,b,c\n1,2,3\n")
    return tmp / "header.csv"


def _bad_csv_text(tmp: Path) -> Path:
    (tmp / "words.csv").write_text("x,y,z\n1,2,3\n4,abc,6\n")
    return tmp / "words.csv"


def _bad_csv_nan(tmp: Path) -> Path:
    (tmp / "nan.csv").write_text("x,y,z\n1,2,3\nnan,5,6\n")
    return tmp / "nan.csv"


def _bad_csv_short_row(tmp: Path) -> Path:
    (tmp / "short.csv").write_text("x,y,z,nx,ny,nz\n1,2,3,0,0,1\n4,5,6,0\n")
    return tmp / "short.csv"


def _bad_csv_no_points(tmp: Path) -> Path:
    (tmp / "header_only.csv").write_text("x,y,z\n")
    return tmp / "header_only.csv"


def _bad_csv_binary(tmp: Path) -> Path:
    (tmp / "binary.csv").write_bytes(b"\xff\xfe\x00\x81" * 50)
    return tmp / "binary.csv"


def _bad_markups_json(tmp: Path) -> Path:
    (tmp / "broken.mrk.json").write_text('{"markups": [ {"controlPoints": ')
    return tmp / "broken.mrk.json"


def _bad_markups_missing(tmp: Path) -> Path:
    return _write_markups(tmp / "no_markups.mrk.json", {"@schema": "x", "points": []})


def _bad_markups_position(tmp: Path) -> Path:
    return _write_markups(tmp / "text_position.mrk.json", {"markups": [{
        "coordinateSystem": "LPS", "controlPoints": [{"label": "F-1", "position": ["a", 1, 2]}]}]})


def _bad_markups_system(tmp: Path) -> Path:
    return _write_markups(tmp / "ijk.mrk.json", {"markups": [{
        "coordinateSystem": "IJK", "controlPoints": [{"position": [1, 2, 3]}]}]})


def _bad_markups_2d(tmp: Path) -> Path:
    return _write_markups(tmp / "flat.mrk.json", {"markups": [{
        "coordinateSystem": "RAS", "controlPoints": [{"label": "A", "position": [1, 2]}]}]})


def _bad_points_suffix(tmp: Path) -> Path:
    (tmp / "points.txt").write_text("x,y,z\n1,2,3\n")
    return tmp / "points.txt"


def _write_model_npz(path: Path, header: dict | None = None, **overrides) -> Path:
    model = small_model()
    arrays = {"mean": model.mean, "factors": model.factors, "coef_var": model.coef_var,
              "faces": model.faces, "world_transform": model.world_transform}
    head = {"format": io.MODEL_FORMAT, "format_version": io.MODEL_FORMAT_VERSION, "units": "mm",
            "method": "pca", "params": {}, "source_meshes": []}
    head.update(header or {})
    arrays.update(overrides)
    np.savez(path, header=np.array(json.dumps(head)), **arrays)
    return path


def _bad_model_version(tmp: Path) -> Path:
    return _write_model_npz(tmp / "future.npz", {"format_version": 99})


def _bad_model_no_version(tmp: Path) -> Path:
    head = {"format": io.MODEL_FORMAT}
    np.savez(tmp / "no_version.npz", header=np.array(json.dumps(head)))
    return tmp / "no_version.npz"


def _bad_model_shapes(tmp: Path) -> Path:
    model = small_model()
    return _write_model_npz(tmp / "shapes.npz", factors=model.factors[:, :-5])


def _bad_model_coef_var(tmp: Path) -> Path:
    return _write_model_npz(tmp / "variances.npz", coef_var=np.ones(7))


def _bad_model_nan(tmp: Path) -> Path:
    model = small_model()
    mean = model.mean.copy()
    mean[3, 1] = np.nan
    return _write_model_npz(tmp / "nan_model.npz", mean=mean)


def _bad_model_count(tmp: Path) -> Path:
    return _write_model_npz(tmp / "count.npz", {"n_vertices": 5})


def _bad_model_plain_npz(tmp: Path) -> Path:
    np.savez(tmp / "arrays.npz", a=np.zeros(3), b=np.ones((2, 2)))
    return tmp / "arrays.npz"


def _bad_model_other_format(tmp: Path) -> Path:
    return _write_model_npz(tmp / "other.npz", {"format": "someone-elses-model"})


def _bad_model_garbage(tmp: Path) -> Path:
    (tmp / "garbage.npz").write_bytes(np.random.default_rng(4).bytes(300))
    return tmp / "garbage.npz"


def _bad_model_truncated(tmp: Path) -> Path:
    io.save_model(tmp / "full.npz", small_model())
    raw = (tmp / "full.npz").read_bytes()
    (tmp / "cut.npz").write_bytes(raw[: len(raw) // 2])
    return tmp / "cut.npz"


def _bad_model_pickle(tmp: Path) -> Path:
    np.savez(tmp / "pickled.npz", header=np.array([{"format": "x"}], dtype=object))
    return tmp / "pickled.npz"


def _bad_model_header_json(tmp: Path) -> Path:
    np.savez(tmp / "header.npz", header=np.array("{format: nope"), mean=np.zeros((4, 3)))
    return tmp / "header.npz"


BAD_INPUTS = [
    # volumes
    (_bad_missing, io.load_volume, ["file not found"]),
    (_bad_empty, io.load_volume, ["file is empty"]),
    (_bad_truncated_gz, io.load_volume, ["truncated or corrupt gzip"]),
    (_bad_truncated_nii, io.load_volume, ["image data are truncated"]),
    (_bad_random_nii, io.load_volume, ["not a NIfTI file", "header size field"]),
    (_bad_random_niigz, io.load_volume, ["not gzip-compressed"]),
    (_bad_gz_of_text, io.load_volume, ["not a NIfTI file"]),
    (_bad_2d, io.load_volume, ["3D image is needed", "2D"]),
    (_bad_4d, io.load_volume, ["3D image is needed", "4D", "3 volumes"]),
    (_bad_nan_affine, io.load_volume, ["affine", "NaN or infinite"]),
    (_bad_singular_affine, io.load_volume, ["affine", "singular"]),
    (_bad_nifti_pair_header, io.load_volume, [".hdr/.img pair"]),
    (_bad_complex, io.load_volume, ["unsupported voxel type"]),
    (_bad_volume_suffix, io.load_volume, ["not an image file name"]),
    # meshes
    (_bad_mesh_nan, io.load_mesh, ["2 vertices have NaN"]),
    (_bad_mesh_empty, io.load_mesh, ["empty mesh"]),
    (_bad_mesh_lines, io.load_mesh, ["no triangles", "lines only"]),
    (_bad_mesh_points_ply, io.load_mesh, ["no triangles"]),
    (_bad_stl, io.load_mesh, ["corrupt .stl file"]),
    (_bad_vtk, io.load_mesh, ["corrupt .vtk file", "Unrecognized file type"]),
    (_bad_vtk_truncated, io.load_mesh, ["corrupt .vtk file"]),
    (_bad_vtp_truncated, io.load_mesh, ["corrupt .vtp file", "XML"]),
    (_bad_ply_truncated, io.load_mesh, ["truncated PLY file"]),
    (_bad_ply_garbage, io.load_mesh, ["not a PLY file"]),
    (_bad_obj, io.load_mesh, ["empty mesh"]),
    (_bad_obj_index, io.load_mesh, ["faces index vertices that do not exist"]),
    (_bad_gifti_no_triangles, io.load_mesh, ["no triangles", "no TRIANGLE array"]),
    (_bad_gifti_data_only, io.load_mesh, ["no surface"]),
    (_bad_gifti_garbage, io.load_mesh, ["not a readable GIfTI file"]),
    (_bad_mesh_suffix, io.load_mesh, ["unsupported mesh format '.off'"]),
    # point sets
    (_bad_csv_header, io.load_points, ["header must start with x,y,z", "a,b,c"]),
    (_bad_csv_text, io.load_points, ["non-numeric value 'abc' on line 3"]),
    (_bad_csv_nan, io.load_points, ["NaN or infinite"]),
    (_bad_csv_short_row, io.load_points, ["line 3 has 4 values", "needs 6"]),
    (_bad_csv_no_points, io.load_points, ["no points"]),
    (_bad_csv_binary, io.load_points, ["not a text CSV file"]),
    (_bad_markups_json, io.load_points, ["not valid JSON"]),
    (_bad_markups_missing, io.load_points, ["no 'markups' list"]),
    (_bad_markups_position, io.load_points, ["F-1", "non-numeric position"]),
    (_bad_markups_system, io.load_points, ["unknown coordinateSystem 'IJK'"]),
    (_bad_markups_2d, io.load_points, ["control point A has no 3D position"]),
    (_bad_points_suffix, io.load_points, ["unsupported point-set format '.txt'"]),
    # shape models
    (_bad_model_version, io.load_model, ["format version 99 is not supported"]),
    (_bad_model_no_version, io.load_model, ["no format_version"]),
    (_bad_model_shapes, io.load_model, ["inconsistent model", "factors must be"]),
    (_bad_model_coef_var, io.load_model, ["coef_var must have 3 entries"]),
    (_bad_model_nan, io.load_model, ["mean contains NaN"]),
    (_bad_model_count, io.load_model, ["n_vertices=5"]),
    (_bad_model_plain_npz, io.load_model, ["not a shape model file (no header)"]),
    (_bad_model_other_format, io.load_model, ["not an SSM Studio model"]),
    (_bad_model_garbage, io.load_model, ["not an .npz archive"]),
    (_bad_model_truncated, io.load_model, ["truncated or corrupt .npz archive"]),
    (_bad_model_pickle, io.load_model, ["not a shape model file", "allow_pickle"]),
    (_bad_model_header_json, io.load_model, ["header is not valid JSON"]),
]


@pytest.mark.parametrize("make_file, load, phrases", BAD_INPUTS,
                         ids=[b[0].__name__.removeprefix("_bad_") for b in BAD_INPUTS])
def test_bad_input_gives_clear_error(tmp_path, capfd, make_file, load, phrases):
    path = make_file(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(DataFileError) as info:
            load(path)
    assert [str(w.message) for w in caught] == []  # no library warnings on the way
    message = str(info.value)
    assert path.name in message
    assert info.value.path == str(path)
    for phrase in phrases:
        assert phrase in message, f"{phrase!r} not in {message!r}"
    assert "\n" not in message
    # VTK's own error printing is captured, not dumped on stderr.
    assert capfd.readouterr().err == ""


def test_bad_input_table_is_large_and_distinct():
    names = {make.__name__ for make, _, _ in BAD_INPUTS}
    assert len(names) == len(BAD_INPUTS) >= 15


def test_directory_is_refused(tmp_path):
    (tmp_path / "folder.nii").mkdir()
    with pytest.raises(DataFileError, match="is a folder"):
        io.load_volume(tmp_path / "folder.nii")


# --------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
@pytest.mark.parametrize("dtype", [np.int16, np.float32, np.uint8])
def test_volume_round_trip(tmp_path, suffix, dtype):
    rng = np.random.default_rng(5)
    data = (rng.random((7, 9, 5)) * 100).astype(dtype)
    affine = _oblique_affine()
    io.save_volume(tmp_path / f"vol{suffix}", data, affine)
    vol = io.load_volume(tmp_path / f"vol{suffix}")
    assert vol.shape == (7, 9, 5)
    assert vol.data.dtype == dtype
    np.testing.assert_array_equal(vol.data, data)
    np.testing.assert_allclose(vol.affine, affine, atol=1e-5)
    np.testing.assert_allclose(vol.spacing, [2.0, 1.0, 3.0], atol=1e-6)


def test_volume_save_converts_bool_and_int64(tmp_path):
    labels = np.zeros((4, 5, 6), np.int64)
    labels[1:3, 2:4, 3:5] = 7
    io.save_volume(tmp_path / "labels.nii.gz", labels, np.eye(4))
    back = io.load_volume(tmp_path / "labels.nii.gz")
    assert back.data.dtype == np.int32
    np.testing.assert_array_equal(back.data, labels)
    io.save_volume(tmp_path / "mask.nii", labels > 0, np.eye(4))
    np.testing.assert_array_equal(io.load_volume(tmp_path / "mask.nii").data, labels > 0)


def test_volume_save_refuses_bad_arguments(tmp_path):
    with pytest.raises(DataFileError, match="3D array is needed"):
        io.save_volume(tmp_path / "a.nii", np.zeros((3, 3)), np.eye(4))
    with pytest.raises(DataFileError, match="invertible"):
        io.save_volume(tmp_path / "a.nii", np.zeros((3, 3, 3)), np.diag([1.0, 0.0, 1.0, 1.0]))
    with pytest.raises(DataFileError, match="volumes are written as .nii, .nii.gz, "):
        io.save_volume(tmp_path / "a.png", np.zeros((3, 3, 3)), np.eye(4))
    assert list(tmp_path.iterdir()) == []


def test_volume_scaling_and_single_volume_4d(tmp_path):
    raw = np.arange(60, dtype=np.int16).reshape(3, 4, 5, 1)
    img = nib.Nifti1Image(raw, np.eye(4))
    img.header.set_slope_inter(0.5, 10.0)
    nib.save(img, str(tmp_path / "scaled.nii"))
    vol = io.load_volume(tmp_path / "scaled.nii")
    assert vol.shape == (3, 4, 5)
    assert vol.data.dtype == np.float32
    np.testing.assert_allclose(vol.data, raw[..., 0] * 0.5 + 10.0)


def test_volume_nan_voxels_become_zero(tmp_path):
    data = np.ones((3, 3, 3), np.float32)
    data[1, 1, 1] = np.nan
    data[0, 0, 0] = np.inf
    vol = io.load_volume(_save_raw_nifti(tmp_path / "holes.nii", data))
    assert vol.data[1, 1, 1] == 0.0 and vol.data[0, 0, 0] == 0.0
    assert vol.data.sum() == 25.0


def test_volume_nifti2_and_big_endian(tmp_path):
    data = np.arange(24, dtype=">f4").reshape(2, 3, 4)
    nib.save(nib.Nifti2Image(data, _oblique_affine()), str(tmp_path / "two.nii"))
    vol = io.load_volume(tmp_path / "two.nii")
    assert vol.data.dtype.isnative
    np.testing.assert_array_equal(vol.data, data)
    np.testing.assert_allclose(vol.affine, _oblique_affine(), atol=1e-5)


def test_mesh_round_trip_keeps_vertex_order(tmp_path):
    mesh = sphere_mesh()
    for suffix in (".vtk", ".vtp", ".ply", ".gii"):
        io.save_mesh(tmp_path / f"m{suffix}", mesh)
        back = io.load_mesh(tmp_path / f"m{suffix}")
        assert back.name == f"m{suffix}"
        np.testing.assert_allclose(back.vertices, mesh.vertices, atol=1e-5, err_msg=suffix)
        np.testing.assert_array_equal(back.faces, mesh.faces, err_msg=suffix)


@pytest.mark.parametrize("suffix", [".stl", ".obj"])
def test_mesh_round_trip_same_geometry(tmp_path, suffix):
    # STL stores each triangle's corners separately (VTK merges them on reading) and OBJ
    # readers may reorder: compare the triangles as sets of corner coordinates.
    mesh = sphere_mesh()
    io.save_mesh(tmp_path / f"m{suffix}", mesh)
    back = io.load_mesh(tmp_path / f"m{suffix}")
    assert len(back.faces) == len(mesh.faces)
    assert back.n_vertices <= 3 * len(mesh.faces)
    assert _triangle_set(back.vertices, back.faces) == _triangle_set(mesh.vertices, mesh.faces)


def test_mesh_point_data_written(tmp_path):
    mesh = sphere_mesh()
    distance = np.linalg.norm(mesh.vertices - mesh.vertices.mean(axis=0), axis=1)
    io.save_mesh(tmp_path / "d.vtp", mesh, point_data={"distance": distance})
    np.testing.assert_allclose(pv.read(tmp_path / "d.vtp").point_data["distance"], distance)


def test_mesh_polygons_and_strips_are_triangulated(tmp_path):
    plane = pv.Plane(i_resolution=3, j_resolution=2)  # 6 quads
    plane.save(str(tmp_path / "quads.vtk"))
    quads = io.load_mesh(tmp_path / "quads.vtk")
    assert quads.faces.shape == (12, 3)
    np.testing.assert_allclose(quads.vertices, plane.points)
    # each quad splits into two triangles of half its area
    area = 0.5 * np.linalg.norm(np.cross(*(quads.vertices[quads.faces[:, 1:]]
                                            - quads.vertices[quads.faces[:, :1]]).transpose(1, 0, 2)),
                                axis=1)
    assert area.sum() == pytest.approx(plane.area)

    sphere = pv.Sphere(theta_resolution=12, phi_resolution=10)
    strips = sphere.strip()
    assert strips.n_strips > 0
    strips.save(str(tmp_path / "strips.vtk"))
    tri = io.load_mesh(tmp_path / "strips.vtk")
    assert len(tri.faces) == sphere.n_cells
    np.testing.assert_allclose(tri.vertices, sphere.points)
    assert tri.to_polydata().area == pytest.approx(sphere.area, rel=1e-6)
    assert tri.to_polydata().volume == pytest.approx(sphere.volume, rel=1e-6)


def test_mesh_unstructured_grid_gives_its_surface(tmp_path):
    grid = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid()  # 8 hexahedra
    grid.save(str(tmp_path / "cube.vtk"))
    mesh = io.load_mesh(tmp_path / "cube.vtk")
    assert len(mesh.faces) == 6 * 4 * 2  # 6 sides of 2x2 quads, 2 triangles each
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [0, 0, 0])
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [2, 2, 2])


def _ply_header(fmt: str, n_vertices: int, n_faces: int) -> bytes:
    return (f"ply\nformat {fmt} 1.0\ncomment hand written\nelement vertex {n_vertices}\n"
            "property double x\nproperty double y\nproperty double z\nproperty uchar red\n"
            f"element face {n_faces}\nproperty list uchar int vertex_indices\n"
            "end_header\n").encode()


def test_ply_reader_ascii_mixed_polygons(tmp_path):
    # a unit square (quad) and a triangle on top of it: fan-triangulated to 3 triangles
    text = _ply_header("ascii", 5, 2) + (
        b"0 0 0 255\n1 0 0 255\n1 1 0 255\n0 1 0 255\n0.5 0.5 1 0\n"
        b"4 0 1 2 3\n3 0 1 4\n")
    (tmp_path / "mixed.ply").write_bytes(text)
    mesh = io.load_mesh(tmp_path / "mixed.ply")
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [0, 1, 4]])
    np.testing.assert_allclose(mesh.vertices[4], [0.5, 0.5, 1.0])


@pytest.mark.parametrize("order, fmt", [("<", "binary_little_endian"), (">", "binary_big_endian")])
def test_ply_reader_binary(tmp_path, order, fmt):
    vertices = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0], [0, 0, 4]], float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    vrec = np.zeros(4, dtype=[("x", order + "f8"), ("y", order + "f8"), ("z", order + "f8"),
                              ("red", "u1")])
    vrec["x"], vrec["y"], vrec["z"] = vertices.T
    frec = np.zeros(4, dtype=[("n", "u1"), ("idx", order + "i4", (3,))])
    frec["n"], frec["idx"] = 3, faces
    (tmp_path / "tet.ply").write_bytes(_ply_header(fmt, 4, 4) + vrec.tobytes() + frec.tobytes())
    mesh = io.load_mesh(tmp_path / "tet.ply")
    np.testing.assert_array_equal(mesh.vertices, vertices)
    np.testing.assert_array_equal(mesh.faces, faces)


def test_ply_reader_matches_vtk_on_vtk_written_files(tmp_path):
    sphere = pv.Sphere(theta_resolution=9, phi_resolution=7)
    for binary in (True, False):
        sphere.save(str(tmp_path / "s.ply"), binary=binary)
        mesh = io.load_mesh(tmp_path / "s.ply")
        reference = pv.read(tmp_path / "s.ply")
        np.testing.assert_allclose(mesh.vertices, reference.points, atol=1e-6)
        np.testing.assert_array_equal(mesh.faces, reference.faces.reshape(-1, 4)[:, 1:])


def test_ply_reader_never_crashes_on_truncation(tmp_path):
    # VTK's own PLY reader segfaults on these; every cut must give a DataFileError.
    pv.Sphere(theta_resolution=6, phi_resolution=5).save(str(tmp_path / "s.ply"), binary=True)
    pv.Sphere(theta_resolution=6, phi_resolution=5).save(str(tmp_path / "a.ply"), binary=False)
    for name in ("s.ply", "a.ply"):
        raw = (tmp_path / name).read_bytes()
        # (an ASCII file cut inside its last number is still a valid file: stop before it)
        end = len(raw) - 1 if name == "s.ply" else raw.rstrip().rfind(b"\n") + 1
        for cut in np.linspace(4, end, 25).astype(int):
            (tmp_path / "cut.ply").write_bytes(raw[:cut])
            with pytest.raises(DataFileError, match="cut.ply"):
                io.load_mesh(tmp_path / "cut.ply")


def test_obj_reader_keeps_file_vertex_numbering(tmp_path):
    # faces share one normal ("//1"): VTK's reader would split them into 6 vertices
    (tmp_path / "tet.obj").write_text(
        "# tetrahedron\nmtllib none.mtl\no tet\nv 0 0 0\nv 2 0 0 1.0\nv 0 3 0\nv 0 0 4\n"
        "vn 0 0 1\nvt 0.5 0.5\ng side\nf 1//1 3//1 2//1\nf 1/1/1 2/1/1 4/1/1\n"
        "f -3 -2 -1\nf 1 4 3\nl 1 2\n")
    mesh = io.load_mesh(tmp_path / "tet.obj")
    np.testing.assert_array_equal(mesh.vertices, [[0, 0, 0], [2, 0, 0], [0, 3, 0], [0, 0, 4]])
    np.testing.assert_array_equal(mesh.faces, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def test_obj_reader_bad_records(tmp_path):
    (tmp_path / "a.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n")
    with pytest.raises(DataFileError, match="a.obj: line 4: bad face record"):
        io.load_mesh(tmp_path / "a.obj")
    (tmp_path / "b.obj").write_text("v 0 0 0\nv 1 0\n")
    with pytest.raises(DataFileError, match="b.obj: line 2: a vertex needs 3 coordinates"):
        io.load_mesh(tmp_path / "b.obj")
    (tmp_path / "c.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n")
    with pytest.raises(DataFileError, match="c.obj: line 4: face index 0"):
        io.load_mesh(tmp_path / "c.obj")


@pytest.mark.parametrize("suffix", [".csv", ".mrk.json"])
@pytest.mark.parametrize("with_normals", [False, True])
def test_points_round_trip(tmp_path, suffix, with_normals):
    rng = np.random.default_rng(6)
    points = rng.normal(scale=30, size=(25, 3))
    normals = None
    if with_normals:
        normals = rng.normal(size=(25, 3))
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    io.save_points(tmp_path / f"p{suffix}", points, normals)
    back = io.load_points(tmp_path / f"p{suffix}")
    np.testing.assert_allclose(back.points, points, atol=1e-6)
    if with_normals:
        np.testing.assert_allclose(back.normals, normals, atol=1e-6)
    else:
        assert back.normals is None


def test_points_csv_tolerates_bom_spaces_and_extra_columns(tmp_path):
    (tmp_path / "excel.csv").write_bytes(
        "\ufeffX, Y, Z, label\r\n1.5, -2, 3e1, a\r\n\r\n4,5,6,b\r\n".encode("utf-8"))
    pts = io.load_points(tmp_path / "excel.csv")
    np.testing.assert_allclose(pts.points, [[1.5, -2, 30], [4, 5, 6]])
    assert pts.normals is None


def test_points_save_refuses_nan(tmp_path):
    with pytest.raises(DataFileError, match="NaN"):
        io.save_points(tmp_path / "p.csv", np.array([[1.0, np.nan, 2.0]]))
    assert not (tmp_path / "p.csv").exists()


def test_markups_lps_is_converted_to_ras(tmp_path):
    # written by hand the way 3D Slicer writes fiducials (LPS), plus one undefined placeholder
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/"
                      "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                        "controlPoints": [
                            {"id": "1", "label": "F-1", "position": [10.0, -20.5, 30.25],
                             "orientation": [-1.0, -0.0, 0.0, -0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
                             "positionStatus": "defined"},
                            {"id": "2", "label": "F-2", "position": [-1.0, 2.0, -3.0],
                             "positionStatus": "defined"},
                            {"id": "3", "label": "F-3", "position": [0.0, 0.0, 0.0],
                             "positionStatus": "undefined"}]}]}
    pts = io.load_points(_write_markups(tmp_path / "slicer.mrk.json", doc))
    np.testing.assert_allclose(pts.points, [[-10.0, 20.5, 30.25], [1.0, -2.0, -3.0]])
    assert pts.normals is None  # Slicer's default orientation is not a surface normal

    doc["markups"][0]["coordinateSystem"] = "RAS"
    pts = io.load_points(_write_markups(tmp_path / "ras.mrk.json", doc))
    np.testing.assert_allclose(pts.points, [[10.0, -20.5, 30.25], [-1.0, 2.0, -3.0]])


def test_markups_written_in_lps(tmp_path):
    io.save_points(tmp_path / "out.mrk.json", PointSet([[1.0, 2.0, 3.0]], [[0.6, 0.0, 0.8]]))
    doc = json.loads((tmp_path / "out.mrk.json").read_text())
    markup = doc["markups"][0]
    assert markup["coordinateSystem"] == "LPS"
    cp = markup["controlPoints"][0]
    assert cp["position"] == [-1.0, -2.0, 3.0]
    frame = np.array(cp["orientation"]).reshape(3, 3)
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-12)  # a rotation
    np.testing.assert_allclose(frame[:, 2], [-0.6, 0.0, 0.8])  # normal, in LPS


def test_model_round_trip(tmp_path):
    model = small_model()
    io.save_model(tmp_path / "model.npz", model)
    back = io.load_model(tmp_path / "model.npz")
    for name in ("mean", "factors", "coef_var", "faces", "world_transform"):
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name), err_msg=name)
    assert back.method == "lsf"
    assert back.params == {"n_components": 3, "sparsity": 0.3}
    assert back.source_meshes == ["a.vtk", "b.vtk"]
    assert back.info == {"build_seconds": 1.5}
    with np.load(tmp_path / "model.npz", allow_pickle=False) as npz:
        header = json.loads(str(npz["header"]))
    assert header["format"] == "ssm-studio-model"
    assert header["format_version"] == 1
    assert header["units"] == "mm"
    assert (header["n_vertices"], header["n_factors"]) == (model.n_vertices, 3)


# --------------------------------------------------------------------------------------
# nibabel's own test images
# --------------------------------------------------------------------------------------


def test_nibabel_anatomical_loads_with_its_affine():
    vol = io.load_volume(NIBABEL_DATA / "anatomical.nii")
    assert vol.shape == (33, 41, 25)
    # the file's sform (code 2): 2 mm voxels, x flipped (LAS)
    np.testing.assert_allclose(vol.affine, [[-2, 0, 0, 32], [0, 2, 0, -40], [0, 0, 2, -16],
                                            [0, 0, 0, 1]])
    assert vol.axis_codes() == ("L", "A", "S")
    assert vol.data.dtype.isnative  # stored big-endian
    reference = nib.load(NIBABEL_DATA / "anatomical.nii").get_fdata()
    np.testing.assert_array_equal(vol.data, reference)


def test_nibabel_standard_uses_sform_when_qform_is_unset():
    vol = io.load_volume(NIBABEL_DATA / "standard.nii.gz")
    assert vol.shape == (4, 5, 7)
    np.testing.assert_allclose(vol.affine, np.diag([1.0, 3.0, 2.0, 1.0]))
    np.testing.assert_allclose(vol.spacing, [1.0, 3.0, 2.0])


@pytest.mark.parametrize("name, shape", [("reoriented_anat_moved.nii", (21, 26, 22)),
                                         ("resampled_anat_moved.nii", (17, 21, 3))])
def test_nibabel_odd_shapes_load(name, shape):
    vol = io.load_volume(NIBABEL_DATA / name)
    assert vol.shape == shape
    np.testing.assert_allclose(vol.affine, nib.load(NIBABEL_DATA / name).affine)


@pytest.mark.parametrize("name, phrases", [
    ("example4d.nii.gz", ["4D", "(128, 96, 24, 2)", "2 volumes"]),
    ("example_nifti2.nii.gz", ["4D", "(32, 20, 12, 2)", "2 volumes"]),
    ("functional.nii", ["4D", "20 volumes"]),
    ("row_major.dconn.nii", ["CIFTI"]),
    ("nifti1.hdr", ["not an image file name"]),
])
def test_nibabel_unsuitable_images_are_refused(name, phrases):
    with pytest.raises(DataFileError) as info:
        io.load_volume(NIBABEL_DATA / name)
    assert name in str(info.value)
    for phrase in phrases:
        assert phrase in str(info.value)


@pytest.mark.parametrize("name, n_vertices, n_faces", [("ascii.gii", 3, 1),
                                                       ("external.gii", 8, 12)])
def test_nibabel_gifti_surfaces_load(name, n_vertices, n_faces):
    mesh = io.load_mesh(GIFTI_DATA / name)
    assert mesh.vertices.shape == (n_vertices, 3)
    assert mesh.faces.shape == (n_faces, 3)
    reference = nib.load(GIFTI_DATA / name)
    np.testing.assert_allclose(mesh.vertices, reference.agg_data("pointset"))
    np.testing.assert_array_equal(mesh.faces, reference.agg_data("triangle"))


@pytest.mark.parametrize("name, phrase", [
    ("label.gii", "GIfTI file has no surface"),
    ("rh.shape.curv.gii", "GIfTI file has no surface"),
    # nibabel's samples of a large surface: 10 vertices, triangles indexing up to 25604
    ("base64bin.gii", "faces index vertices that do not exist"),
])
def test_nibabel_gifti_non_surfaces_are_refused(name, phrase):
    with pytest.raises(DataFileError, match=f"{name}: {phrase}"):
        io.load_mesh(GIFTI_DATA / name)


# --------------------------------------------------------------------------------------
# World coordinates with an oblique affine
# --------------------------------------------------------------------------------------


def test_oblique_affine_maps_voxel_to_ras_and_back(tmp_path):
    affine = _oblique_affine()  # 2, 1, 3 mm voxels, 30 degrees about z, origin (10, -20, 5)
    vol = io.Volume(np.zeros((6, 5, 4), np.float32), affine)
    assert vol.is_oblique
    # voxel (4, 2, 1), by hand with cos 30 = sqrt(3)/2, sin 30 = 1/2:
    #   x = 2*4*cos30 - 1*2*sin30 + 10 = 4*sqrt(3) + 9
    #   y = 2*4*sin30 + 1*2*cos30 - 20 = sqrt(3) - 16
    #   z = 3*1 + 5 = 8
    expected = np.array([4 * math.sqrt(3) + 9, math.sqrt(3) - 16, 8.0])
    np.testing.assert_allclose(vol.voxel_to_world([4, 2, 1]), expected, atol=1e-12)
    np.testing.assert_allclose(vol.world_to_voxel(expected), [4, 2, 1], atol=1e-12)
    # many points at once, fractional indices, and the inverse
    ijk = np.random.default_rng(7).uniform(0, 5, size=(50, 3))
    np.testing.assert_allclose(vol.world_to_voxel(vol.voxel_to_world(ijk)), ijk, atol=1e-12)
    np.testing.assert_allclose(vol.spacing, [2.0, 1.0, 3.0])

    io.save_volume(tmp_path / "oblique.nii.gz", vol.data, affine)
    back = io.load_volume(tmp_path / "oblique.nii.gz")
    assert back.is_oblique
    np.testing.assert_allclose(back.affine, affine, atol=1e-5)
    np.testing.assert_allclose(back.voxel_to_world([4, 2, 1]), expected, atol=1e-4)
    np.testing.assert_allclose(back.world_to_voxel(expected), [4, 2, 1], atol=1e-5)
    # the stored sform and qform both hold the rotation (nothing silently dropped)
    header = nib.load(tmp_path / "oblique.nii.gz").header
    np.testing.assert_allclose(header.get_sform(), affine, atol=1e-5)
    np.testing.assert_allclose(header.get_qform(), affine, atol=1e-5)


def test_qform_is_used_when_sform_is_unset(tmp_path):
    affine = _oblique_affine()
    img = nib.Nifti1Image(np.zeros((3, 3, 3), np.float32), None)
    img.set_qform(affine, code=1)
    img.set_sform(np.diag([5.0, 5.0, 5.0, 1.0]), code=0)
    nib.save(img, str(tmp_path / "qform.nii"))
    np.testing.assert_allclose(io.load_volume(tmp_path / "qform.nii").affine, affine, atol=1e-5)


def test_sheared_sform_wins_over_qform(tmp_path):
    shear = np.array([[1.0, 0.3, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.2, 2.0, 3.0],
                      [0.0, 0.0, 0.0, 1.0]])
    io.save_volume(tmp_path / "shear.nii", np.zeros((3, 3, 3), np.float32), shear)
    np.testing.assert_allclose(io.load_volume(tmp_path / "shear.nii").affine, shear, atol=1e-6)


def test_value_at_and_bounds():
    data = np.arange(6 * 5 * 4, dtype=np.float32).reshape(6, 5, 4)
    vol = io.Volume(data, _oblique_affine())
    assert vol.value_at(vol.voxel_to_world([4, 2, 1])) == data[4, 2, 1]
    assert vol.value_at(vol.voxel_to_world([6.2, 0, 0])) is None
    corners = vol.voxel_to_world(np.array(np.meshgrid([0, 5], [0, 4], [0, 3])).reshape(3, -1).T)
    np.testing.assert_allclose(vol.world_bounds(), [corners.min(0), corners.max(0)])


# --------------------------------------------------------------------------------------
# Atomic saves
# --------------------------------------------------------------------------------------


def _leftovers(folder: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name not in keep)


def test_failed_mesh_save_keeps_previous_file(tmp_path, monkeypatch):
    target = tmp_path / "surface.vtk"
    io.save_mesh(target, sphere_mesh())
    before = target.read_bytes()

    class FailingWriter:  # stands in for vtkPolyDataWriter: writes part of the file, fails
        def SetFileName(self, filename):
            self.filename = filename

        def Write(self):
            Path(self.filename).write_bytes(b"# vtk DataFile Version 4.2\npartial")
            raise OSError("disk full")

        def __getattr__(self, name):  # the other setters do nothing
            return lambda *args: None

    from core.io import vtk_meshes

    monkeypatch.setattr(vtk_meshes.vtk, "vtkPolyDataWriter", FailingWriter)
    with pytest.raises(OSError, match="disk full"):
        io.save_mesh(target, sphere_mesh())
    assert target.read_bytes() == before
    assert _leftovers(tmp_path, {"surface.vtk"}) == []


def test_failed_model_and_text_saves_keep_previous_file(tmp_path, monkeypatch):
    target = tmp_path / "model.npz"
    io.save_model(target, small_model())
    before = target.read_bytes()

    def failing_savez(fh, **arrays):
        fh.write(b"PK\x03\x04 partial")
        raise KeyboardInterrupt  # even an interrupt must not leave a half-written file

    monkeypatch.setattr(np, "savez_compressed", failing_savez)
    with pytest.raises(KeyboardInterrupt):
        io.save_model(target, small_model())
    assert target.read_bytes() == before

    (tmp_path / "notes.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with io.atomic_path(tmp_path / "notes.txt") as tmp:
            tmp.write_text("new but incomplete")
            raise RuntimeError("writer failed")
    assert (tmp_path / "notes.txt").read_text() == "old"
    assert _leftovers(tmp_path, {"model.npz", "notes.txt"}) == []


def test_writer_that_writes_nothing_is_an_error(tmp_path):
    (tmp_path / "a.txt").write_text("old")
    with pytest.raises(DataFileError, match="nothing was written"):
        with io.atomic_path(tmp_path / "a.txt"):
            pass
    assert (tmp_path / "a.txt").read_text() == "old"
    assert _leftovers(tmp_path, {"a.txt"}) == []


def test_saved_files_get_normal_permissions(tmp_path):
    umask = os.umask(0o022)
    os.umask(umask)
    io.save_points(tmp_path / "p.csv", np.zeros((2, 3)))
    assert stat.S_IMODE((tmp_path / "p.csv").stat().st_mode) == 0o666 & ~umask
    os.chmod(tmp_path / "p.csv", 0o640)  # replacing a file keeps its permissions
    io.save_points(tmp_path / "p.csv", np.ones((2, 3)))
    assert stat.S_IMODE((tmp_path / "p.csv").stat().st_mode) == 0o640


def test_vtk_output_window_is_restored_after_bad_file(tmp_path, capfd):
    import vtk

    before = vtk.vtkOutputWindow.GetInstance()
    (tmp_path / "bad.vtp").write_text("<VTKFile")
    with pytest.raises(DataFileError):
        io.load_mesh(tmp_path / "bad.vtp")
    assert vtk.vtkOutputWindow.GetInstance() is before
    assert capfd.readouterr().err == ""


def test_expand_and_load_meshes_keep_order_and_report_bad_files(tmp_path):
    import pyvista as pv

    from core.io import expand_mesh_paths, load_meshes, save_mesh

    folder = tmp_path / "meshes"
    folder.mkdir()
    sphere = TriMesh.from_polydata(pv.Sphere(theta_resolution=8, phi_resolution=8))
    for name in ("b.vtk", "a.ply"):
        save_mesh(folder / name, sphere)
    (folder / "notes.txt").write_text("not a mesh")
    (folder / "c.stl").write_bytes(b"")
    files = expand_mesh_paths([folder, folder / "a.ply"])
    assert [f.name for f in files] == ["a.ply", "b.vtk", "c.stl"]  # sorted, no repeat, no .txt
    loaded, failures = load_meshes(files)
    assert [p.name for p, _ in loaded] == ["a.ply", "b.vtk"]
    assert all(m.n_vertices == sphere.n_vertices for _, m in loaded)
    assert list(failures) == [str(folder / "c.stl")] and "empty" in failures[str(folder / "c.stl")]


# --------------------------------------------------------------------------------------
# Issue 18: damaged files, Slicer's coordinate systems, headers ITK reads differently
# --------------------------------------------------------------------------------------

_LEGACY_HEAD = "# vtk DataFile Version 4.2\ntest\nASCII\n"
_FOUR_POINTS = "POINTS 4 float\n0 0 0 10 0 0 0 10 0 10 10 0\n"
_TETRA_POINTS = "POINTS 4 float\n0 0 0 10 0 0 0 10 0 0 0 10\n"


@pytest.mark.parametrize("name, body, phrase", [
    # each of these crashed the process (segfault in VTK's filters) or passed garbage on
    ("poly_index", "DATASET POLYDATA\n" + _FOUR_POINTS + "POLYGONS 2 9\n4 0 1 3 2\n3 0 1 99999\n",
     "refer to point 99999"),
    ("poly_negative", "DATASET POLYDATA\n" + _FOUR_POINTS + "POLYGONS 1 4\n3 0 1 -7\n",
     "refer to point -7"),
    ("strip_index", "DATASET POLYDATA\n" + _FOUR_POINTS + "TRIANGLE_STRIPS 1 5\n4 0 1 2 77\n",
     "refer to point 77"),
    ("poly_count_overrun", "DATASET POLYDATA\n" + _FOUR_POINTS + "POLYGONS 1 4\n9 0 1 2\n",
     "refer to point"),
    ("poly_fewer_cells", "DATASET POLYDATA\n" + _FOUR_POINTS + "POLYGONS 2 4\n3 0 1 2\n",
     "the header declares 2 cells"),
    ("ug_index", "DATASET UNSTRUCTURED_GRID\n" + _TETRA_POINTS +
     "CELLS 1 5\n4 0 1 2 99999999\nCELL_TYPES 1\n10\n", "refer to point 99999999"),
    ("ug_cell_type", "DATASET UNSTRUCTURED_GRID\n" + _TETRA_POINTS +
     "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n255\n", "cell type 255"),
    ("ug_type_size", "DATASET UNSTRUCTURED_GRID\n" + _TETRA_POINTS +
     "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n5\n", "type 5 has 4 points"),
    ("points_huge", "DATASET POLYDATA\nPOINTS 2000000000 float\n0 0 0\n", "2000000000 points"),
])
def test_damaged_legacy_vtk_is_refused_before_vtk_filters(tmp_path, name, body, phrase):
    path = tmp_path / f"{name}.vtk"
    path.write_text(_LEGACY_HEAD + body)
    with pytest.raises(DataFileError, match=phrase) as info:
        io.load_mesh(path)
    assert str(info.value).startswith(str(path))


def test_vtp_claiming_two_billion_points_is_refused_before_reading(tmp_path):
    io.save_mesh(tmp_path / "m.vtp", sphere_mesh())
    text = (tmp_path / "m.vtp").read_bytes().replace(
        f'NumberOfPoints="{sphere_mesh().n_vertices}"'.encode(), b'NumberOfPoints="2000000000"')
    (tmp_path / "huge.vtp").write_bytes(text)  # VTK aborted with std::bad_alloc (exit 134)
    with pytest.raises(DataFileError, match="huge.vtp: .*declares 2000000000 points"):
        io.load_mesh(tmp_path / "huge.vtp")


def test_batch_reading_survives_a_native_reader_crash(tmp_path):
    """A reader that dies of SIGSEGV costs its file only (load_meshes(isolate=True))."""
    import signal

    from core.io import registry

    def crashing_reader(path):
        os.kill(os.getpid(), signal.SIGSEGV)

    registry.register(registry.FileFormat(".crash", "mesh", "crashing", read=crashing_reader))
    try:
        io.save_mesh(tmp_path / "a.vtk", sphere_mesh())
        io.save_mesh(tmp_path / "c.ply", sphere_mesh())
        (tmp_path / "b.crash").write_text("anything")
        files = [tmp_path / "a.vtk", tmp_path / "b.crash", tmp_path / "c.ply"]
        loaded, failures = io.load_meshes(files, isolate=True)
    finally:
        del registry._FORMATS[("mesh", ".crash")]
    assert [p.name for p, _ in loaded] == ["a.vtk", "c.ply"]
    assert list(failures) == [str(tmp_path / "b.crash")]
    assert "SIGSEGV" in failures[str(tmp_path / "b.crash")]
    np.testing.assert_allclose(loaded[1][1].vertices, sphere_mesh().vertices)


def test_unstructured_grid_keeps_the_file_point_numbering(tmp_path):
    """Before: vtkDataSetSurfaceFilter renumbered the points (README says indices are kept)."""
    path = tmp_path / "ug.vtk"
    # point 0 is unused; the tetra uses points 1..4 in a scrambled order
    path.write_text(_LEGACY_HEAD + "DATASET UNSTRUCTURED_GRID\nPOINTS 5 float\n"
                    "99 99 99 0 0 0 0 0 10 10 0 0 0 10 0\nCELLS 1 5\n4 1 3 4 2\n"
                    "CELL_TYPES 1\n10\n")
    mesh = io.load_mesh(path)
    assert mesh.n_vertices == 5
    np.testing.assert_allclose(mesh.vertices[0], [99, 99, 99])
    assert sorted(np.unique(mesh.faces)) == [1, 2, 3, 4]
    assert len(mesh.faces) == 4
    # every face is a face of the tetra (1, 3, 4, 2) in the file's numbering
    assert {tuple(sorted(f)) for f in mesh.faces.tolist()} == \
        {(1, 2, 3), (1, 2, 4), (1, 3, 4), (2, 3, 4)}


def test_vtu_and_gzipped_gifti_are_read(tmp_path):
    grid = pv.UnstructuredGrid(np.array([4, 0, 1, 2, 3]), np.array([10]),
                               np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10.0]]))
    grid.save(str(tmp_path / "t.vtu"))
    mesh = io.load_mesh(tmp_path / "t.vtu")
    assert mesh.n_vertices == 4 and len(mesh.faces) == 4
    io.save_mesh(tmp_path / "s.gii", sphere_mesh())
    (tmp_path / "s.gii.gz").write_bytes(gzip.compress((tmp_path / "s.gii").read_bytes()))
    mesh = io.load_mesh(tmp_path / "s.gii.gz")
    np.testing.assert_allclose(mesh.vertices, sphere_mesh().vertices, atol=1e-5)
    np.testing.assert_array_equal(mesh.faces, sphere_mesh().faces)
    assert tmp_path / "s.gii.gz" in io.expand_mesh_paths([tmp_path])
    bad = bytearray((tmp_path / "s.gii.gz").read_bytes())
    bad[-8] ^= 0xFF
    (tmp_path / "crc.gii.gz").write_bytes(bytes(bad))
    with pytest.raises(DataFileError, match="crc.gii.gz: .*gzip"):
        io.load_mesh(tmp_path / "crc.gii.gz")


def _slicer_lps_files(folder: Path, mesh: TriMesh) -> dict[str, Path]:
    """The mesh in LPS as 3D Slicer writes it, one file per format, with SPACE=LPS tags."""
    lps = TriMesh(mesh.vertices * [-1, -1, 1], mesh.faces)
    poly = lps.to_polydata()
    files = {}
    writer = vtk.vtkPolyDataWriter()
    writer.SetFileVersion(42)
    writer.SetHeader("3D Slicer output. SPACE=LPS")
    writer.SetFileName(str(folder / "slicer.vtk"))
    writer.SetInputData(poly)
    writer.Write()
    files["vtk"] = folder / "slicer.vtk"
    tagged = poly.copy()
    tag = vtk.vtkStringArray()
    tag.SetName("SPACE")
    tag.InsertNextValue("LPS")
    tagged.GetFieldData().AddArray(tag)
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetFileName(str(folder / "slicer.vtp"))
    writer.SetInputData(tagged)
    writer.Write()
    files["vtp"] = folder / "slicer.vtp"
    writer = vtk.vtkSTLWriter()
    writer.SetHeader("3D Slicer output. SPACE=LPS")
    writer.SetFileTypeToBinary()
    writer.SetFileName(str(folder / "slicer.stl"))
    writer.SetInputData(poly)
    writer.Write()
    files["stl"] = folder / "slicer.stl"
    writer = vtk.vtkPLYWriter()
    writer.AddComment("3D Slicer output. SPACE=LPS")
    writer.SetFileName(str(folder / "slicer.ply"))
    writer.SetInputData(poly)
    writer.Write()
    files["ply"] = folder / "slicer.ply"
    lines = ["# 3D Slicer output. SPACE=LPS"] + [f"v {x} {y} {z}" for x, y, z in lps.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in lps.faces]
    (folder / "slicer.obj").write_text("\n".join(lines) + "\n")
    files["obj"] = folder / "slicer.obj"
    return files


@pytest.mark.parametrize("fmt", ["vtk", "vtp", "stl", "ply", "obj"])
def test_slicer_lps_meshes_are_read_in_ras(tmp_path, fmt):
    """Before: read as RAS, i.e. mirrored to the other hemisphere."""
    mesh = sphere_mesh()  # centre (12, -30, 5) RAS
    path = _slicer_lps_files(tmp_path, mesh)[fmt]
    read = io.load_mesh(path)
    np.testing.assert_allclose(read.vertices.mean(axis=0), mesh.vertices.mean(axis=0),
                               atol=1e-4)
    if fmt != "stl":  # STL does not keep the vertex numbering
        np.testing.assert_allclose(read.vertices, mesh.vertices, atol=1e-4)


@pytest.mark.parametrize("suffix, tag", [
    (".vtk", b"SSM Studio output. SPACE=RAS"), (".stl", b"SPACE=RAS"),
    (".ply", b"comment SSM Studio output. SPACE=RAS"), (".obj", b"# SSM Studio output. SPACE=RAS"),
    (".vtp", b'Name="SPACE"'),
])
def test_every_mesh_written_says_space_ras_and_reads_back(tmp_path, suffix, tag):
    path = tmp_path / f"m{suffix}"
    io.save_mesh(path, sphere_mesh())
    raw = path.read_bytes()
    assert tag in raw
    if suffix == ".vtk":
        assert raw.startswith(b"# vtk DataFile Version 4.2\n")  # readable by VTK < 9, Slicer
    np.testing.assert_allclose(io.load_mesh(path).vertices.mean(axis=0),
                               sphere_mesh().vertices.mean(axis=0), atol=1e-4)
    io.save_mesh(tmp_path / f"lps{suffix}", sphere_mesh(), space="LPS")  # the user's choice
    assert tag.replace(b"RAS", b"LPS") in (tmp_path / f"lps{suffix}").read_bytes() or \
        suffix == ".vtp"
    np.testing.assert_allclose(io.load_mesh(tmp_path / f"lps{suffix}").vertices.mean(axis=0),
                               sphere_mesh().vertices.mean(axis=0), atol=1e-4)


def test_sitk_sees_masks_where_it_sees_their_image_for_every_sform_qform_code(tmp_path):
    """25 combinations of sform/qform codes 0-4 with different sform and qform matrices.

    Before, ``save_volume`` wrote the affine into both with code 1: ITK read the image's
    qform (sform code != 1) or its code-0 fallback and put the mask elsewhere (13 of 25).
    """
    sitk = pytest.importorskip("SimpleITK")
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    c, s = math.cos(0.3), math.sin(0.3)
    sform = np.array([[c, -1.2 * s, 0, -60], [s, 1.2 * c, 0, 10], [0, 0, 1.5, 25], [0, 0, 0, 1]])
    qform = np.array([[-1.0, 0, 0, 70], [0, 1.2, 0, -90], [0, 0, 1.5, 10], [0, 0, 0, 1]])
    data = np.random.default_rng(0).random((6, 7, 8)).astype(np.float32)
    disagree = []
    for sform_code in range(5):
        for qform_code in range(5):
            img = nib.Nifti1Image(data, None)
            img.header.set_qform(qform, code=qform_code)
            img.header.set_sform(sform, code=sform_code)
            nib.save(img, str(tmp_path / "image.nii.gz"))
            volume = io.load_volume(tmp_path / "image.nii.gz")
            io.save_volume(tmp_path / "mask.nii.gz", (volume.data > 0.5).astype(np.uint8),
                           volume.affine, like=volume)
            a = sitk.ReadImage(str(tmp_path / "image.nii.gz"))
            b = sitk.ReadImage(str(tmp_path / "mask.nii.gz"))
            index = (5, 6, 7)
            if not np.allclose(a.TransformIndexToPhysicalPoint(index),
                               b.TransformIndexToPhysicalPoint(index), atol=1e-3):
                disagree.append((sform_code, qform_code))
            np.testing.assert_allclose(io.load_volume(tmp_path / "mask.nii.gz").affine,
                                       volume.affine, atol=1e-4)  # and nibabel agrees too
    assert disagree == []


def test_corrupt_gzip_crc_in_nifti_is_refused(tmp_path):
    """Before: nibabel stopped reading before the CRC; segment exited 0 with wrong voxels."""
    _save_raw_nifti(tmp_path / "good.nii.gz", np.arange(1000, dtype=np.float32).reshape(10, 10, 10))
    raw = bytearray((tmp_path / "good.nii.gz").read_bytes())
    raw[-8] ^= 0xFF  # the CRC-32 of the uncompressed data
    (tmp_path / "crc.nii.gz").write_bytes(bytes(raw))
    with pytest.raises(DataFileError, match="crc.nii.gz: corrupt gzip data"):
        io.load_volume(tmp_path / "crc.nii.gz")


@pytest.mark.parametrize("name, dims, extra, phrase", [
    ("huge.nii.gz", (30000, 30000, 30000), 0, "30000x30000x30000 voxels"),
    ("big.nii", (1400, 1400, 1400), 700, "image data are truncated"),  # 1 kB, 2.7 GB claimed
])
def test_nifti_declared_size_is_checked_before_allocating(tmp_path, name, dims, extra, phrase):
    import tracemalloc

    img = nib.Nifti1Image(np.zeros((2, 2, 2), np.float32), np.eye(4))
    header = img.header.copy()
    header.set_data_shape(dims)
    raw = header.binaryblock + b"\x00" * 4 + b"\x00" * extra
    path = tmp_path / name
    path.write_bytes(gzip.compress(raw) if name.endswith(".gz") else raw)
    tracemalloc.start()
    try:
        with pytest.raises(DataFileError, match=phrase):
            io.load_volume(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6  # before: 2.7 GB allocated before refusing


def _npz_with_member(path: Path, name: str, shape: tuple, data: bytes) -> None:
    import zipfile

    io.save_model(path, small_model())
    header = f"{{'descr': '<f8', 'fortran_order': False, 'shape': {shape}, }}"
    header += " " * (117 - len(header)) + "\n"
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
            member.write(b"\x93NUMPY\x01\x00" + (118).to_bytes(2, "little") + header.encode())
            member.write(data)


def test_model_npz_member_claiming_a_huge_shape_is_refused(tmp_path):
    _npz_with_member(tmp_path / "shape.npz", "extra", (1000000000000, 3), b"\x00" * 48)
    with pytest.raises(DataFileError, match=r"shape.npz: .*shape \(1000000000000, 3\)"):
        io.load_model(tmp_path / "shape.npz")


def test_model_npz_zip_bomb_is_refused_without_inflating(tmp_path):
    import tracemalloc

    n = 3 << 20  # 24 MB of zeros, ~25 kB compressed
    path = tmp_path / "bomb.npz"
    io.save_model(path, small_model())
    import zipfile

    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open("zeros.npy", "w", force_zip64=True) as member:
            header = f"{{'descr': '<f8', 'fortran_order': False, 'shape': ({n},), }}"
            header += " " * (117 - len(header)) + "\n"
            member.write(b"\x93NUMPY\x01\x00" + (118).to_bytes(2, "little") + header.encode())
            for _ in range(24):
                member.write(bytes(1 << 20))
    tracemalloc.start()
    try:
        with pytest.raises(DataFileError, match="bomb.npz: .*zip bomb"):
            io.load_model(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10e6


@pytest.mark.parametrize("change, phrase", [
    ({"mean": "complex"}, "'mean' must hold real numbers, got complex numbers"),
    ({"factors": "text"}, "'factors' must hold real numbers, got text"),
    ({"coef_var": "text"}, "'coef_var' must hold real numbers, got text"),
    ({"world_transform": "singular"}, "world_transform is singular"),
    ({"world_transform": "projective"}, "world_transform is not affine"),
])
def test_model_loader_refuses_complex_text_and_singular_arrays(tmp_path, change, phrase):
    """Before: complex parts dropped, text converted or refused deep in the fit, singular
    transforms accepted (the later error then blamed the points file)."""
    model = small_model()
    arrays = {"mean": model.mean, "factors": model.factors, "coef_var": model.coef_var,
              "faces": model.faces, "world_transform": model.world_transform}
    key, kind = next(iter(change.items()))
    arrays[key] = {"complex": lambda a: a + 1j, "text": lambda a: a.astype(str),
                   "singular": lambda a: np.diag([1.0, 1.0, 0.0, 1.0]),
                   "projective": lambda a: np.vstack([a[:3], [0.1, 0, 0, 1]])}[kind](arrays[key])
    header = {"format": io.MODEL_FORMAT, "format_version": io.MODEL_FORMAT_VERSION,
              "units": "mm", "method": "lsf", "params": {}, "source_meshes": [], "info": {}}
    np.savez(tmp_path / "m.npz", header=np.array(json.dumps(header)), **arrays)
    with pytest.raises(DataFileError, match=phrase):
        io.load_model(tmp_path / "m.npz")


@pytest.mark.parametrize("name, write, phrase", [
    ("deep.mrk.json", lambda p: p.write_text("[" * 100000 + "]" * 100000), "nested too deeply"),
    ("deep.npz", lambda p: np.savez(p, header=np.array("[" * 100000 + "]" * 100000)),
     "nested too deeply"),
    ("huge.obj", lambda p: p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 100000000000000000000\n"),
     "face index out of range"),
    ("scalar.ply", lambda p: p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n2\n"), "is a scalar, a face needs a list"),
    ("count.ply", lambda p: p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n7 0 1 2\n"), "count.ply: PLY element 'face'"),
])
def test_former_tracebacks_are_one_line_errors(tmp_path, name, write, phrase):
    path = tmp_path / name
    write(path)
    load = io.load_model if name.endswith(".npz") else \
        io.load_points if name.endswith(".json") else io.load_mesh
    with pytest.raises(DataFileError, match=phrase) as info:
        load(path)
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)


def test_obj_with_tabs_indentation_continuations_and_foreign_comments(tmp_path):
    """Before: indented or tab-separated records were dropped (half of a two-object file)."""
    text = ("# caf\xe9 in latin-1\no first\nv 0 0 0\nv\t10 0 0\n  v 0 10 0\nf 1 2 3\n"
            "o second\n\tv 0 0 10\n    v 10 0 10\nv 0 \\\n  10 10\n\tf\t4 5 6  # a comment\n")
    (tmp_path / "two.obj").write_bytes(text.encode("latin-1"))
    mesh = io.load_mesh(tmp_path / "two.obj")
    assert mesh.n_vertices == 6
    np.testing.assert_allclose(mesh.vertices[5], [0, 10, 10])
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [3, 4, 5]])


def test_stl_cannot_hold_corresponded_shapes(tmp_path):
    """Before: align on STL outputs exited 0 with 6.8 mm RMS garbage."""
    mesh = sphere_mesh()
    with pytest.raises(DataFileError, match="s.stl: not written: STL files do not keep vertex"):
        io.save_mesh(tmp_path / "s.stl", mesh, vertex_order=True)
    io.save_mesh(tmp_path / "s.stl", mesh)
    io.save_mesh(tmp_path / "s.vtk", mesh)
    loaded, failures = io.load_meshes([tmp_path / "s.vtk", tmp_path / "s.stl"],
                                      vertex_order=True)
    assert [p.name for p, _ in loaded] == ["s.vtk"]
    assert "do not keep vertex order" in failures[str(tmp_path / "s.stl")]


def test_align_refuses_stl_inputs_by_name(tmp_path, capsys):
    from core.cli import main

    rng = np.random.default_rng(0)
    names = []
    for i, suffix in enumerate((".vtk", ".ply", ".obj", ".stl")):
        mesh = sphere_mesh()
        io.save_mesh(tmp_path / f"s{i}{suffix}",
                     TriMesh(mesh.vertices + rng.normal(scale=0.2, size=mesh.vertices.shape),
                             mesh.faces))
        names.append(str(tmp_path / f"s{i}{suffix}"))
    assert main(["align", *names, "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert f"{tmp_path / 's3.stl'}: STL files do not keep vertex order" in err
    report = json.loads((tmp_path / "out" / "transforms.json").read_text())
    assert len(report["shapes"]) == 3


def test_folder_expansion_skips_hidden_and_temporary_files_and_stale_ones_are_cleaned(tmp_path):
    """Before: a killed save's .NAME.XXXX.tmp.vtk was read as a 7th training shape."""
    mesh = sphere_mesh()
    io.save_mesh(tmp_path / "a.vtk", mesh)
    io.save_mesh(tmp_path / "b.vtk", mesh)
    for name in (".a.vtk.k2j3h4.tmp.vtk", ".a.99999999.x8d7.tmp.vtk", ".hidden.vtk", "c.vtk~"):
        (tmp_path / name).write_bytes((tmp_path / "a.vtk").read_bytes())
    assert [p.name for p in io.expand_mesh_paths([tmp_path])] == ["a.vtk", "b.vtk"]
    # the next save of a.vtk removes the temporary of the process that no longer runs
    io.save_mesh(tmp_path / "a.vtk", mesh)
    assert not (tmp_path / ".a.99999999.x8d7.tmp.vtk").exists()
    assert (tmp_path / ".hidden.vtk").exists()


def test_special_files_are_named_for_what_they_are(tmp_path):
    fifo = tmp_path / "pipe.vtk"
    os.mkfifo(fifo)
    with pytest.raises(DataFileError, match="pipe.vtk: is a named pipe"):
        io.load_mesh(fifo)  # before: "file is empty" (or a hang)
    with pytest.raises(DataFileError, match="/dev/zero: is a device"):
        io.load_points("/dev/zero")


def test_non_utf8_file_names_are_read_and_named(tmp_path):
    """Before: a codec error that named no file, for valid files too."""
    name = os.fsdecode(b"caf\xe9")
    io.save_mesh(tmp_path / f"{name}.vtk", sphere_mesh())
    io.save_mesh(tmp_path / f"{name}.vtp", sphere_mesh())
    for suffix in (".vtk", ".vtp"):
        np.testing.assert_allclose(io.load_mesh(tmp_path / f"{name}{suffix}").vertices,
                                   sphere_mesh().vertices, atol=1e-5)
    (tmp_path / f"{name}.stl").write_bytes(b"solid x\n")
    with pytest.raises(DataFileError) as info:
        io.load_mesh(tmp_path / f"{name}.stl")
    assert "caf\\xe9.stl" in str(info.value)  # the byte shown, not U+FFFD
    str(info.value).encode("utf-8")  # printable


def test_library_warnings_become_one_line_notes_naming_the_file(tmp_path, capsys):
    """nibabel's warnings leaked to stderr as two-line reports; now one line each."""
    from core.cli import main

    img = nib.Nifti1Image(np.full((4, 4, 4), 1000, np.int16), np.eye(4))
    img.header.set_slope_inter(1e38, 0)  # numpy warns: overflow encountered in cast
    path = tmp_path / "odd.nii"
    img.to_filename(str(path))
    model = tmp_path / "m.npz"
    io.save_model(model, small_model())
    io.save_points(tmp_path / "p.csv", small_model().mean[:3])
    main(["segment", "--model", str(model), "--points", str(tmp_path / "p.csv"), "--image",
          str(path), "--out", str(tmp_path / "mask.nii.gz")])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert all(ln.startswith("ssm-studio segment: ") for ln in err), err
    assert any("odd.nii" in ln and "warning" in ln for ln in err), err


@pytest.mark.parametrize("name, text, expected", [
    ("lps.csv", "label,l,p,s,defined,selected,visible,locked,description\n"
                "F-1,-19.9,13.9,29.4,1,1,1,0,\nF-2,-7.4,-76.9,17.6,1,1,1,0,\nF-3,1,1,1,0,1,1,0,\n",
     [[19.9, -13.9, 29.4], [7.4, 76.9, 17.6]]),
    ("ras.csv", "label,r,a,s\nF-1,-19.9,13.9,29.4\n", [[-19.9, 13.9, 29.4]]),
    ("lps.tsv", "label\tl\tp\ts\nF-1\t1\t2\t3\n", [[-1, -2, 3]]),
    ("plain.csv", "x,y,z\n1,2,3\n", [[1, 2, 3]]),
    ("new.fcsv", "# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"
                 "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                 "1,1,2,3,0,0,0,1,1,1,0,F-1,,\n", [[-1, -2, 3]]),
    ("ras.fcsv", "# Markups fiducial file version = 4.10\n# CoordinateSystem = 0\n"
                 "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                 "1,1,2,3,0,0,0,1,1,1,0,F-1,,\n", [[1, 2, 3]]),
    ("old.fcsv", "# Markups fiducial file version = 4.6\n"
                 "vtkMRMLMarkupsFiducialNode_0,1,2,3,0,0,0,1,1,1,0,F-1,,\n", [[1, 2, 3]]),
    ("empty_system.mrk.json", json.dumps({"markups": [{"coordinateSystem": "", "controlPoints": [
        {"position": [1, 2, 3], "positionStatus": "defined"}]}]}), [[-1, -2, 3]]),
    ("preview.json", json.dumps({"@schema": "markups-schema-v1.0.3.json", "markups": [{
        "coordinateSystem": "RAS", "controlPoints": [
            {"position": [1, 2, 3], "positionStatus": "defined"},
            {"position": [], "positionStatus": "preview"}]}]}), [[1, 2, 3]]),
])
def test_slicer_point_files_read_in_ras(tmp_path, name, text, expected):
    path = tmp_path / name
    path.write_text(text)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        points = io.load_points(path)
    np.testing.assert_allclose(points.points, expected)
    notes = [str(w.message) for w in caught]
    if name in ("lps.csv", "preview.json"):  # the skipped point is said, naming the file
        assert len(notes) == 1 and notes[0].startswith(str(path)) and "skipped" in notes[0]
    else:
        assert notes == []


def test_markups_json_is_recognised_as_points_not_session(tmp_path):
    from core.io.points import is_markups_file
    from core.session.document import Session, save_session

    io.save_points(tmp_path / "p.json", np.array([[1.0, 2, 3]]))
    save_session(tmp_path / "s.json", Session(points=[[1.0, 2, 3]]))
    assert is_markups_file(tmp_path / "p.json")
    assert not is_markups_file(tmp_path / "s.json")


def test_correspond_writes_stl_inputs_as_vtk_and_says_so(tmp_path, capsys):
    from core.cli import main

    mesh = sphere_mesh()
    rng = np.random.default_rng(2)
    inputs = []
    for i, suffix in enumerate((".vtk", ".ply", ".stl")):
        io.save_mesh(tmp_path / f"in{i}{suffix}",
                     TriMesh(mesh.vertices + rng.normal(scale=0.1, size=mesh.vertices.shape),
                             mesh.faces))
        inputs.append(str(tmp_path / f"in{i}{suffix}"))
    assert main(["correspond", *inputs, "--out", str(tmp_path / "out"), "--n-references", "1",
                 "--jobs", "1", "--max-iterations", "5"]) == 0
    err = capsys.readouterr().err
    assert f"{tmp_path / 'out' / 'in2.vtk'}: written as .vtk" in err
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == \
        ["correspondence.json", "in0.vtk", "in1.ply", "in2.vtk"]
    report = json.loads((tmp_path / "out" / "correspondence.json").read_text())
    assert {s["output"] for s in report["shapes"]} == \
        {str(tmp_path / "out" / n) for n in ("in0.vtk", "in1.ply", "in2.vtk")}


def test_a_reader_message_names_the_file_once(tmp_path):
    # VTK's reader says "Unrecognized file type: ... for file: <path>"; the error names the
    # file itself, so the message read "... for file: the file".
    path = tmp_path / "garbage.vtk"
    path.write_text("garbage")
    with pytest.raises(DataFileError) as caught:
        io.load_mesh(path)
    text = str(caught.value)
    assert text.count(str(path)) == 1 and "the file" not in text, text
    assert "\n" not in text
