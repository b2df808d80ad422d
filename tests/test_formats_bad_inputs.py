"""Bad NRRD, MetaImage, DICOM and statismo inputs: each a one-line error naming the file, exit 2.

Table-driven: each case writes its broken input in a temporary folder and names a word the
message must contain, so a case cannot pass on an unrelated error.
"""

from __future__ import annotations

import gzip
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import formats_synth as synth  # noqa: E402

pytest.importorskip("SimpleITK")
h5py = pytest.importorskip("h5py")

VOXELS = np.arange(4 * 3 * 2, dtype=np.int16)


def _write(path: Path, data: bytes | str) -> Path:
    if isinstance(data, str):
        path.write_text(data)
    else:
        path.write_bytes(data)
    return path


def _nrrd(path: Path, fields: dict[str, str], payload: bytes, *, end: bytes = b"\n\n") -> Path:
    text = "NRRD0004\n" + "".join(f"{k}: {v}\n" for k, v in fields.items())
    path.write_bytes(text.encode()[:-1] + end + payload)
    return path


def _nrrd_fields(**over) -> dict[str, str]:
    fields = {"type": "short", "dimension": "3", "space": "left-posterior-superior",
              "sizes": "4 3 2", "space directions": "(1,0,0) (0,1,0) (0,0,1)",
              "endian": "little", "encoding": "raw", "space origin": "(0,0,0)"}
    fields.update(over)
    return {k: v for k, v in fields.items() if v is not None}


def _mha(path: Path, fields: dict[str, str], payload: bytes) -> Path:
    text = "".join(f"{k} = {v}\n" for k, v in fields.items())
    path.write_bytes(text.encode() + payload)
    return path


def _mha_fields(**over) -> dict[str, str]:
    fields = {"ObjectType": "Image", "NDims": "3", "DimSize": "4 3 2", "ElementType": "MET_SHORT",
              "ElementSpacing": "1 1 1", "Offset": "0 0 0", "TransformMatrix": "1 0 0 0 1 0 0 0 1",
              "ElementDataFile": "LOCAL"}
    fields.update(over)
    fields["ElementDataFile"] = fields.pop("ElementDataFile")  # must come last
    return {k: v for k, v in fields.items() if v is not None}


RAW = VOXELS.tobytes()


def _series(tmp: Path, **kw) -> Path:
    image = synth.oblique_image((6, 5, 6), (1.0, 1.0, 2.0))
    synth.write_series(tmp / "series", image, **kw)
    return tmp / "series"


def _geometry(tmp: Path, change) -> Path:
    image = synth.oblique_image((6, 5, 6), (1.0, 1.0, 2.0))
    d = np.asarray(image.GetDirection()).reshape(3, 3)
    pos = [np.array(image.TransformIndexToPhysicalPoint((0, 0, k))) for k in range(6)]
    orient = [list(d[:, 0]) + list(d[:, 1]) for _ in range(6)]
    kw = change(pos, orient, d)
    synth.write_series(tmp / "series", image, **kw)
    return tmp / "series"


def _corrupt_slice(tmp: Path) -> Path:
    folder = _series(tmp)
    victim = folder / "IM0003.dcm"
    victim.write_bytes(victim.read_bytes()[:400])
    return folder


def _raw_dicoms(tmp: Path, n: int, **kw) -> Path:
    for k in range(n):
        synth.write_raw_dicom(tmp / "raw" / f"f{k}.dcm", instance=k + 1,
                              position=(0.0, 0.0, 2.0 * k), **kw)
    return tmp / "raw"


def _mixed_orientation(pos, orient, d):
    orient[4] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    return {"orientations": orient}


IMAGE_CASES = {
    # NRRD
    "nrrd truncated header": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(), b"", end=b"\nsi"),
                              "truncated NRRD header"),
    "nrrd truncated raw data": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(), RAW[:30]),
                                "truncated"),
    "nrrd header lies (sizes too big)": (
        lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(sizes="40 30 20"), RAW), "lying about the size"),
    "nrrd header lies (sizes too small)": (
        lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(sizes="2 3 2"), RAW), "bytes follow it"),
    "nrrd truncated gzip": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(encoding="gzip"),
                                            gzip.compress(RAW)[:20]), "gzip"),
    "nrrd gzip header lies": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(encoding="gzip",
                                                                         sizes="4 3 5"),
                                              gzip.compress(RAW)), "header lying"),
    "nrrd unknown type": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(type="quaternion"), RAW),
                          "unsupported type"),
    "nrrd unknown encoding": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(encoding="zstd"), RAW),
                              "unknown encoding"),
    "nrrd sizes vs dimension": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(sizes="4 6"), RAW),
                                "dimension 3 but 2 sizes"),
    "nrrd no magic": (lambda t: _write(t / "a.nrrd", b"P5 4 3 255\n" + RAW),
                      "not an NRRD file"),
    "nrrd missing sizes": (lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(sizes=None), RAW),
                           "lacks the required field 'sizes'"),
    "nhdr missing data file": (lambda t: _nrrd(t / "a.nhdr", _nrrd_fields(**{"data file": "a.raw"}),
                                               b"", end=b"\n"), "data file 'a.raw'"),
    "nrrd 4D (two volumes)": (
        lambda t: _nrrd(t / "a.nrrd", _nrrd_fields(dimension="4", sizes="4 3 1 2",
                                                   **{"space directions":
                                                      "(1,0,0) (0,1,0) (0,0,1) none",
                                                      "kinds": "domain domain domain list"}),
                        RAW), "3D"),
    # MetaImage
    "mha truncated raw data": (lambda t: _mha(t / "a.mha", _mha_fields(), RAW[:10]), "truncated"),
    "mha header lies (DimSize too big)": (
        lambda t: _mha(t / "a.mha", _mha_fields(DimSize="64 64 64"), RAW), "lying about the size"),
    "mha header lies (DimSize too small)": (
        lambda t: _mha(t / "a.mha", _mha_fields(DimSize="2 3 2"), RAW), "follow it"),
    "mha no ElementDataFile": (lambda t: _mha(t / "a.mha", {"NDims": "3", "DimSize": "4 3 2"}, b""),
                               "ElementDataFile"),
    "mha unknown ElementType": (lambda t: _mha(t / "a.mha", _mha_fields(ElementType="MET_RGB"), RAW),
                                "unknown ElementType"),
    "mha NDims vs DimSize": (lambda t: _mha(t / "a.mha", _mha_fields(NDims="2"), RAW),
                             "NDims = 2 but DimSize has 3"),
    "mhd missing raw file": (lambda t: _mha(t / "a.mhd", _mha_fields(ElementDataFile="a.raw"), b""),
                             "data file 'a.raw'"),
    "mha truncated compressed data": (
        lambda t: _mha(t / "a.mha", _mha_fields(CompressedData="True"), zlib.compress(RAW)[:12]),
        "compressed"),
    "mha 2D image": (lambda t: _mha(t / "a.mha", _mha_fields(NDims="2", DimSize="4 6",
                                                             ElementSpacing="1 1", Offset="0 0",
                                                             TransformMatrix="1 0 0 1"), RAW),
                     "a 3D image is needed"),
    # DICOM
    "dicom one corrupt slice": (_corrupt_slice, "IM0003.dcm"),
    "dicom gantry tilt": (lambda t: _geometry(t, lambda p, o, d: {
        "positions": [x + d[:, 1] * 0.5 * k for k, x in enumerate(p)]}), "gantry tilt"),
    "dicom missing slice": (lambda t: _series(t, keep=[0, 1, 2, 4, 5]), "missing"),
    "dicom non-uniform spacing": (lambda t: _geometry(t, lambda p, o, d: {
        "positions": [x + d[:, 2] * 0.1 * k * k for k, x in enumerate(p)]}), "non-uniform"),
    "dicom mixed orientations": (lambda t: _geometry(t, _mixed_orientation), "mixed"),
    "dicom 4D series": (lambda t: _series(t) and _series(t, name="B{:04d}.dcm"), "4D series"),
    "dicom multi-frame": (lambda t: _raw_dicoms(t, 2, frames=5), "multi-frame"),
    "dicom structured report only": (
        lambda t: synth.write_raw_dicom(t / "sr" / "report.dcm", sop_class=synth.BASIC_TEXT_SR,
                                        pixels=False).parent, "structured report"),
    "dicom undecodable transfer syntax": (
        lambda t: _raw_dicoms(t, 3, transfer_syntax=synth.HTJ2K, encapsulated=True),
        "High-Throughput JPEG 2000"),
    "dicom single slice": (lambda t: _raw_dicoms(t, 1), "single slice"),
    "dicom empty folder": (lambda t: (t / "empty").mkdir() or t / "empty", "empty folder"),
    "dicom folder without dicom": (
        lambda t: ((t / "d").mkdir(), (t / "d" / "notes.txt").write_text("x"))[0] or t / "d",
        "no DICOM files"),
    "dcm file that is not dicom": (lambda t: _write(t / "x.dcm", b"\0" * 300),
                                   "not a DICOM file"),
}


def _statismo(path: Path, *, drop=(), change=None, **attrs) -> Path:
    from core.evaluation.simulated_user import pca_model, synthetic_shapes

    shapes, faces = synthetic_shapes(6, subdivisions=1, seed=0)
    model = pca_model(shapes, faces)
    n, m = model.n_vertices, model.n_factors
    data = {
        "model/mean": model.mean.reshape(-1), "model/pcaBasis": model.basis,
        "model/pcaVariance": model.coef_var, "model/noiseVariance": np.float32(0),
        "representer/points": model.mean.T, "representer/cells": model.faces.T.astype(np.int32),
        "version/majorVersion": np.int32(0), "version/minorVersion": np.int32(9),
    }
    if change:
        change(data, n, m)
    with h5py.File(path, "w") as h5:
        for key, value in data.items():
            if key not in drop:
                h5.create_dataset(key, data=value)
        rep = h5.require_group("representer")
        rep.attrs["name"] = attrs.get("name", "itkStandardMeshRepresenter")
        rep.attrs["datasetType"] = attrs.get("dataset_type", "POLYGON_MESH")
    return path


def _set(key, fn):
    def change(data, n, m):
        data[key] = fn(data[key], n, m)
    return change


def _truncated_h5(t: Path) -> Path:
    good = _statismo(t / "good.h5")
    (t / "m.h5").write_bytes(good.read_bytes()[:1500])
    return t / "m.h5"


def _catalog(t: Path) -> Path:
    with h5py.File(t / "m.h5", "w") as h5:
        h5.create_dataset("catalog/left/modelPath", data=b"/left")
    return t / "m.h5"


MODEL_CASES = {
    "h5 that is text": (lambda t: _write(t / "m.h5", "not hdf5\n" * 20),
                        "not an HDF5 file"),
    "h5 truncated": (_truncated_h5, "HDF5"),
    "h5 missing model/mean": (lambda t: _statismo(t / "m.h5", drop=("model/mean",)), "model/mean"),
    "h5 missing pcaVariance": (lambda t: _statismo(t / "m.h5", drop=("model/pcaVariance",)),
                               "model/pcaVariance"),
    "h5 missing cells (point set)": (lambda t: _statismo(t / "m.h5", drop=("representer/cells",)),
                                     "point-set model without cells"),
    "h5 missing version": (lambda t: _statismo(t / "m.h5", drop=("version/majorVersion",)),
                           "version"),
    "h5 mean length mismatch": (lambda t: _statismo(t / "m.h5", change=_set(
        "model/mean", lambda v, n, m: v[:-3])), "representer has"),
    "h5 basis rows mismatch": (lambda t: _statismo(t / "m.h5", change=_set(
        "model/pcaBasis", lambda v, n, m: v[:-6])), "pcaBasis must be"),
    "h5 variance count mismatch": (lambda t: _statismo(t / "m.h5", change=_set(
        "model/pcaVariance", lambda v, n, m: v[:-1])), "basis columns"),
    "h5 points not 3 x N": (lambda t: _statismo(t / "m.h5", change=_set(
        "representer/points", lambda v, n, m: v.T)), "(3, N)"),
    "h5 NaN in mean": (lambda t: _statismo(t / "m.h5", change=_set(
        "model/mean", lambda v, n, m: np.where(np.arange(v.size) == 5, np.nan, v))), "NaN"),
    "h5 cells out of range": (lambda t: _statismo(t / "m.h5", change=_set(
        "representer/cells", lambda v, n, m: v + n)), "must index"),
    "h5 negative variance": (lambda t: _statismo(t / "m.h5", change=_set(
        "model/pcaVariance", lambda v, n, m: -v)), "negative"),
    "h5 image model": (lambda t: _statismo(t / "m.h5", name="itkStandardImageRepresenter",
                                           dataset_type="IMAGE"), "image"),
    "h5 volume mesh": (lambda t: _statismo(t / "m.h5", name="itkStandardMeshRepresenter",
                                           dataset_type="VOLUME_MESH"), "volume"),
    "h5 tetrahedral cells": (lambda t: _statismo(t / "m.h5", change=_set(
        "representer/cells", lambda v, n, m: np.vstack([v, v[:1]]))), "tetrahedra"),
    "h5 catalog": (_catalog, "catalog"),
}


def _one_line_error(capsys, rc: int, path: Path, word: str) -> None:
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert str(path) in lines[0] and "Traceback" not in err
    assert word.lower() in lines[0].lower(), lines[0]


@pytest.mark.parametrize("case", sorted(IMAGE_CASES))
def test_bad_image_is_a_one_line_error(tmp_path, capsys, case):
    from core.cli import main

    make, word = IMAGE_CASES[case]
    path = Path(make(tmp_path))
    capsys.readouterr()
    rc = main(["segment", "--model", str(tmp_path / "never-read.npz"), "--points",
               str(tmp_path / "never-read.csv"), "--image", str(path),
               "--out", str(tmp_path / "out.nii.gz")])
    _one_line_error(capsys, rc, path, word)
    assert not (tmp_path / "out.nii.gz").exists()


@pytest.mark.parametrize("case", sorted(MODEL_CASES))
def test_bad_statismo_model_is_a_one_line_error(tmp_path, capsys, case):
    from core.cli import main

    make, word = MODEL_CASES[case]
    path = Path(make(tmp_path))
    rc = main(["convert-model", str(path), str(tmp_path / "out.npz")])
    _one_line_error(capsys, rc, path, word)
    assert not (tmp_path / "out.npz").exists()


def test_fit_refuses_a_bad_h5_model_the_same_way(tmp_path, capsys):
    from core.cli import main

    path = _statismo(tmp_path / "m.h5", drop=("model/pcaBasis",))
    (tmp_path / "p.csv").write_text("x,y,z\n0,0,0\n1,0,0\n0,1,0\n")
    rc = main(["fit", "--model", str(path), "--points", str(tmp_path / "p.csv"),
               "--out", str(tmp_path / "o.vtk")])
    _one_line_error(capsys, rc, path, "model/pcaBasis")
