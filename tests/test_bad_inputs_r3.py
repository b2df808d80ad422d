"""Issue 28, item 5 (the round-3 bad-input audit): one table row per case.

Each row makes its input in ``tmp_path`` and says what must happen: a refusal (the command
exits 2 with one error line naming the file and a word of the problem, no traceback) or a
correct read (compared with the values the file was written from). The comment on a row says
what the code did before (commit eb2bdcf).
"""

from __future__ import annotations

import bz2
import gzip
import json
import os
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

pytest.importorskip("SimpleITK")

REPO = Path(__file__).resolve().parents[1]
DEMO_MODEL = REPO / "resources" / "demo" / "model.npz"
SLICER = Path(__file__).resolve().parent / "data" / "real" / "slicer"

VOXELS = np.arange(40 * 30 * 20, dtype=np.int16).reshape((40, 30, 20), order="F")
RAW = VOXELS.ravel(order="F").tobytes()  # i fastest, as NRRD and MetaImage store it
OCTAHEDRON_V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                        float) * 10 + [5.0, -20.0, 12.0]
OCTAHEDRON_F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                         [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


# --------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------


def _mha_header(data_file: str, **extra) -> str:
    fields = {"ObjectType": "Image", "NDims": "3", "DimSize": "40 30 20",
              "ElementType": "MET_SHORT", "ElementSpacing": "1 1 2", "Offset": "0 0 0",
              "TransformMatrix": "1 0 0 0 1 0 0 0 1", **extra, "ElementDataFile": data_file}
    return "".join(f"{k} = {v}\n" for k, v in fields.items())


def _corrupt_zlib() -> bytes:
    """A zlib stream of the right length whose middle is damaged (the checksum fails)."""
    stream = bytearray(zlib.compress(RAW))
    stream[len(stream) // 2] ^= 0xFF
    stream[len(stream) // 2 + 1] ^= 0x55
    return bytes(stream)


def mha_corrupt_zlib(t: Path) -> Path:
    stream = _corrupt_zlib()
    header = _mha_header("LOCAL", CompressedData="True", CompressedDataSize=str(len(stream)))
    (t / "a.mha").write_bytes(header.encode() + stream)
    return t / "a.mha"


def nrrd_corrupt_gzip(t: Path) -> Path:
    """The gzip twin of the MetaImage case: damaged middle, trailer (size) intact."""
    stream = bytearray(gzip.compress(RAW))
    stream[len(stream) // 2] ^= 0xFF
    stream[len(stream) // 2 + 1] ^= 0x55
    header = ("NRRD0004\ntype: short\ndimension: 3\nsizes: 40 30 20\nencoding: gzip\n"
              "endian: little\n\n")
    (t / "a.nrrd").write_bytes(header.encode() + bytes(stream))
    return t / "a.nrrd"


def mhd_corrupt_zlib(t: Path) -> Path:
    stream = _corrupt_zlib()
    (t / "a.zraw").write_bytes(stream)
    (t / "a.mhd").write_text(_mha_header("a.zraw", CompressedData="True",
                                         CompressedDataSize=str(len(stream))))
    return t / "a.mhd"


def _nhdr(path: Path, data_file: str, n: int, *, encoding: str = "raw") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"NRRD0004\ntype: uchar\ndimension: 3\nspace: left-posterior-superior\n"
                    f"sizes: {n} 1 1\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"
                    f"endian: little\nencoding: {encoding}\nspace origin: (0,0,0)\n"
                    f"data file: {data_file}\n")
    return path


def _mhd(path: Path, data_file: str, n: int) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"ObjectType = Image\nNDims = 3\nDimSize = {n} 1 1\nElementType = MET_UCHAR\n"
                    f"ElementSpacing = 1 1 1\nOffset = 0 0 0\n"
                    f"TransformMatrix = 1 0 0 0 1 0 0 0 1\nElementDataFile = {data_file}\n")
    return path


def _secret(t: Path) -> Path:
    (t / "secret.raw").write_bytes(bytes(range(256)) * 4)
    return t / "secret.raw"


PASSWD = Path("/etc/passwd")


def nhdr_absolute_data_file(t: Path) -> Path:
    return _nhdr(t / "h" / "a.nhdr", str(PASSWD), PASSWD.stat().st_size)


def nhdr_dotdot_data_file(t: Path) -> Path:
    _secret(t)
    return _nhdr(t / "h" / "a.nhdr", "../secret.raw", 1024)


def nhdr_list_dotdot_data_file(t: Path) -> Path:
    _secret(t)
    path = _nhdr(t / "h" / "a.nhdr", "LIST", 1024)
    path.write_text(path.read_text() + "../secret.raw\n")
    return path


def mhd_absolute_data_file(t: Path) -> Path:
    return _mhd(t / "h" / "a.mhd", str(PASSWD), PASSWD.stat().st_size)


def mhd_dotdot_data_file(t: Path) -> Path:
    _secret(t)
    return _mhd(t / "h" / "a.mhd", "../secret.raw", 1024)


def _nrrd_bzip2(t: Path, payload: bytes) -> Path:
    header = ("NRRD0004\ntype: short\ndimension: 3\nspace: left-posterior-superior\n"
              "sizes: 40 30 20\nspace directions: (-1,0,0) (0,-1,0) (0,0,2)\n"
              "endian: little\nencoding: bzip2\nspace origin: (10,20,30)\n\n")
    (t / "a.nrrd").write_bytes(header.encode() + payload)
    return t / "a.nrrd"


def nrrd_bzip2(t: Path) -> Path:
    return _nrrd_bzip2(t, bz2.compress(RAW))


def nhdr_bzip2(t: Path) -> Path:
    (t / "a.raw.bz2").write_bytes(bz2.compress(RAW))
    path = _nhdr(t / "a.nhdr", "a.raw.bz2", 1, encoding="bzip2")
    text = path.read_text().replace("type: uchar", "type: short").replace(
        "sizes: 1 1 1", "sizes: 40 30 20").replace(
        "space directions: (1,0,0) (0,1,0) (0,0,1)", "space directions: (-1,0,0) (0,-1,0) (0,0,2)"
    ).replace("space origin: (0,0,0)", "space origin: (10,20,30)")
    path.write_text(text)
    return path


def nrrd_bzip2_truncated(t: Path) -> Path:
    return _nrrd_bzip2(t, bz2.compress(RAW)[:-40])


def _stl_bytes() -> bytes:
    out = b"binary STL".ljust(80, b" ") + struct.pack("<I", len(OCTAHEDRON_F))
    for face in OCTAHEDRON_F:
        out += struct.pack("<12fH", 0, 0, 0, *OCTAHEDRON_V[face].ravel(), 0)
    return out


def stl_non_utf8_name(t: Path) -> Path:
    path = Path(os.fsdecode(os.fsencode(str(t)) + b"/caf\xe9.stl"))
    path.write_bytes(_stl_bytes())
    return path


def _ply(t: Path, fmt: str) -> Path:
    header = (f"ply\nformat {fmt} 1.0\ncomment this line mentions end_header before the "
              "header ends\ncomment SPACE=RAS end_header\nelement vertex 6\nproperty float x\n"
              "property float y\nproperty float z\nelement face 8\n"
              "property list uchar int vertex_indices\nend_header\n").encode()
    if fmt == "ascii":
        body = "".join(" ".join(f"{c:g}" for c in v) + "\n" for v in OCTAHEDRON_V)
        body += "".join("3 " + " ".join(map(str, f)) + "\n" for f in OCTAHEDRON_F)
        data = body.encode()
    else:
        order = ">" if fmt == "binary_big_endian" else "<"
        data = b"".join(struct.pack(order + "3f", *v) for v in OCTAHEDRON_V)
        data += b"".join(struct.pack(order + "B3i", 3, *f) for f in OCTAHEDRON_F)
    (t / "m.ply").write_bytes(header + data)
    return t / "m.ply"


def _nifti_zero_pixdim(t: Path, sform_code: int, qform_code: int) -> Path:
    import nibabel as nib

    img = nib.Nifti1Image(np.arange(64, dtype=np.uint8).reshape(4, 4, 4),
                          np.diag([2.0, 3.0, 4.0, 1.0]))
    img.to_filename(str(t / "tmp.nii"))
    raw = bytearray((t / "tmp.nii").read_bytes())
    struct.pack_into("<3f", raw, 80, 0.0, 0.0, 0.0)  # pixdim[1..3]
    struct.pack_into("<2h", raw, 252, qform_code, sform_code)
    (t / "a.nii").write_bytes(bytes(raw))
    return t / "a.nii"


def _seg_with(t: Path, old: bytes, new: bytes) -> Path:
    raw = (SLICER / "Segmentation.seg.nrrd").read_bytes()
    assert old in raw
    (t / "s.seg.nrrd").write_bytes(raw.replace(old, new))
    return t / "s.seg.nrrd"


def _vtk(path: Path, vertices: np.ndarray) -> Path:
    lines = ["# vtk DataFile Version 4.2", "mesh", "ASCII", "DATASET POLYDATA",
             f"POINTS {len(vertices)} double"]
    lines += [" ".join(repr(float(c)) for c in v) for v in vertices]
    lines += [f"POLYGONS {len(OCTAHEDRON_F)} {4 * len(OCTAHEDRON_F)}"]
    lines += ["3 " + " ".join(map(str, f)) for f in OCTAHEDRON_F]
    path.write_text("\n".join(lines) + "\n")
    return path


def _training(t: Path, bad: np.ndarray) -> list[Path]:
    good = [_vtk(t / f"ok{k}.vtk", OCTAHEDRON_V * s + k) for k, s in enumerate((1.0, 1.1, 0.9))]
    return [*good, _vtk(t / "bad.vtk", bad)]


def _session(t: Path, **fields) -> Path:
    doc = {"format": "ssm-studio-session", "format_version": 1, "image": None,
           "model": str(DEMO_MODEL), "points": [], "coef": None, "pose": None, "fit": {},
           "info": {}}
    doc.update(fields)
    (t / "s.json").write_text(json.dumps(doc))
    return t / "s.json"


def _planning(block):
    return lambda t: _session(t, info={"planning": block})


# --------------------------------------------------------------------------------------
# Refusals: (make input -> path, argv for that path and tmp folder, word of the message)
# --------------------------------------------------------------------------------------


def _segment(path: Path, t: Path) -> list[str]:
    """``segment`` reads its image before its model: the image's error comes first."""
    return ["segment", "--model", str(t / "never-read.npz"), "--points",
            str(t / "never-read.csv"), "--image", str(path), "--out", str(t / "out.nii.gz")]


def _plan(path: Path, t: Path) -> list[str]:
    return ["plan", "--session", str(path), "--out", str(t / "plan.json")]


def _plan_export(path: Path, t: Path) -> list[str]:
    return _plan(path, t) + ["--export", str(t / "export")]


def _build(path: Path, t: Path) -> list[str]:
    inputs = [str(p) for p in sorted(t.glob("ok*.vtk"))] + [str(path)]
    return ["build-model", *inputs, "--out", str(t / "model.npz")]


def _fit(path: Path, t: Path) -> list[str]:
    return ["fit", "--model", str(DEMO_MODEL), "--points", str(path), "--out", str(t / "f.vtk")]


GARBAGE_PLANNING = {
    "a list": [1, 2],
    "ac is text": {"ac": "garbage", "pc": [0, 1, 0], "midline": [0, 0, 1]},
    "ac has 2 values": {"ac": [0, 1], "pc": [0, 1, 0], "midline": [0, 0, 1]},
    "structures not a list": {"structures": 5},
    "structure item not an object": {"structures": ["x"]},
    "structure index text": {"structures": [{"structure": "0"}]},
    "structure index out of range": {"structures": [{"structure": 3}]},
    "target is text": {"structures": [{"structure": 0, "target": "abc"}]},
    "entry at 1e200": {"structures": [{"structure": 0, "entry": [1e200, 0, 0]}]},
}

REFUSALS = {
    # before: an all-zero volume, exit 0 ("Uncompress failed" on stderr only)
    "mha corrupt zlib, declared size right": (mha_corrupt_zlib, _segment, "corrupt compressed"),
    "mhd corrupt zlib, declared size right": (mhd_corrupt_zlib, _segment, "corrupt compressed"),
    # already refused before (ITK's gzip reader checks the stream)
    "nrrd corrupt gzip, trailer right": (nrrd_corrupt_gzip, _segment, "gzip"),
    # before: the other file read as voxels, exit 0
    "nhdr data file /etc/passwd": (nhdr_absolute_data_file, _segment, "outside the header's"),
    "nhdr data file ../secret.raw": (nhdr_dotdot_data_file, _segment, "outside the header's"),
    "nhdr data file LIST with ../": (nhdr_list_dotdot_data_file, _segment, "outside the header's"),
    "mhd ElementDataFile /etc/passwd": (mhd_absolute_data_file, _segment, "outside the header's"),
    "mhd ElementDataFile ../secret.raw": (mhd_dotdot_data_file, _segment, "outside the header's"),
    # new: a damaged bzip2 stream (before: ITK's "Sorry, bzip2 encoding not available")
    "nrrd bzip2 truncated": (nrrd_bzip2_truncated, _segment, "bzip2"),
    # before: exit 0 with 1 mm voxels after nibabel's console warning
    "nifti zero pixdim, qform": (lambda t: _nifti_zero_pixdim(t, 0, 1), _segment, "pixdim"),
    "nifti zero pixdim, no sform or qform": (lambda t: _nifti_zero_pixdim(t, 0, 0), _segment,
                                             "pixdim"),
    # before: "invalid literal for int() with base 10: 'two'", no file named
    "seg.nrrd LabelValue two": (lambda t: _seg_with(t, b"Segment0_LabelValue:=1",
                                                    b"Segment0_LabelValue:=two"),
                                _segment, "Segment0_LabelValue is 'two'"),
    "seg.nrrd Layer x": (lambda t: _seg_with(t, b"Segment2_Layer:=0", b"Segment2_Layer:=x"),
                         _segment, "Segment2_Layer is 'x'"),
    "seg.nrrd Layer 3 of 1": (lambda t: _seg_with(t, b"Segment2_Layer:=0", b"Segment2_Layer:=3"),
                              _segment, "Segment2_Layer is 3"),
    # before: "... lie far outside the model (up to inf mm ...)" after an overflow warning
    "points near float max": (lambda t: (t / "p.csv").write_text(
        "x,y,z\n0,0,0\n1.7e308,0,0\n0,1.7e308,0\n0,0,-1.7e308\n") and t / "p.csv", _fit,
        "1.7e+308 mm from the origin"),
    # before: "X contains NaN or infinite coordinates" after 2 warnings, no file named
    "training mesh with a 1e300 vertex": (
        lambda t: _training(t, np.vstack([[1e300, 0, 0], OCTAHEDRON_V[1:]]))[-1], _build,
        "1e+300 mm from the origin"),
    # before: a model built, exit 0
    "training mesh whose vertices coincide": (
        lambda t: _training(t, np.zeros_like(OCTAHEDRON_V) + 5.0)[-1], _build, "one point"),
    "training mesh on a line": (
        lambda t: _training(t, np.outer(np.arange(6.0), [1.0, 2.0, 3.0]))[-1], _build,
        "zero area"),
    # before: plan exit 0, plan --export "embedded null byte" (no file named)
    "session image path with a null byte": (lambda t: _session(t, image="a\u0000b.nii.gz"),
                                            _plan, "null byte"),
    "session image path with a null byte (export)": (
        lambda t: _session(t, image="a\u0000b.nii.gz"), _plan_export, "null byte"),
    # before: 57 s and 1.7 GB for 10,000 (here 257: the limit is 256)
    "session with 257 structures": (lambda t: _session(t, structures=[
        {"name": f"s{i}", "model": str(DEMO_MODEL)} for i in range(257)]), _plan,
        "more than the 256"),
    # before: plan exit 0 after overflow warnings; the GUI an IndexError (core/geometry/toolkit.py)
    "session pose 1e200": (lambda t: _session(t, pose=[[1e200, 0, 0, 0], [0, 1, 0, 0],
                                                       [0, 0, 1, 0], [0, 0, 0, 1]]), _plan,
                           "pose"),
    "session pose translation 1e200": (lambda t: _session(t, pose=[
        [1, 0, 0, 1e200], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), _plan, "pose moves"),
    "session pose sheared": (lambda t: _session(t, pose=[[1, 0.5, 0, 0], [0, 1, 0, 0],
                                                         [0, 0, 1, 0], [0, 0, 0, 1]]), _plan,
                             "not a similarity"),
    "session pose projective": (lambda t: _session(t, pose=[[1, 0, 0, 0], [0, 1, 0, 0],
                                                            [0, 0, 1, 0], [0, 0, 1, 1]]), _plan,
                                "0 0 0 1"),
    "session structure pose 1e200": (lambda t: _session(t, structures=[
        {"name": "a", "model": str(DEMO_MODEL),
         "pose": [[1, 0, 0, 0], [0, 1e200, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]), _plan,
        "structure pose"),
    "session points 1e200": (lambda t: _session(t, points=[[1e200, 0, 0]]), _plan,
                             "from the origin"),
}
for _name, _block in GARBAGE_PLANNING.items():
    # before: tracebacks (TypeError, AttributeError) or "could not convert string to float"
    REFUSALS[f"planning {_name}"] = (_planning(_block), _plan, "info.planning")
    REFUSALS[f"planning {_name} (export)"] = (_planning(_block), _plan_export, "info.planning")


def _the_error_line(capsys, rc: int, path: Path, word: str) -> str:
    from core.errors import display_path

    err = capsys.readouterr().err
    assert rc == 2, err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(lines) == 1, err
    assert len([ln for ln in err.splitlines() if "warning" in ln]) == 0, err
    assert display_path(path) in lines[0], lines[0]
    assert word.lower() in lines[0].lower(), lines[0]
    return lines[0]


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_bad_input_is_a_one_line_error(tmp_path, capsys, case):
    from core.cli import main

    make, argv, word = REFUSALS[case]
    path = Path(make(tmp_path))
    capsys.readouterr()
    rc = main(argv(path, tmp_path))
    _the_error_line(capsys, rc, path, word)
    for name in ("out.nii.gz", "plan.json", "model.npz", "f.vtk"):
        assert not (tmp_path / name).exists()


def test_a_pose_error_is_the_same_on_load_as_the_gui_sees_it(tmp_path):
    """The GUI opens sessions through load_session: the refusal comes before any geometry."""
    from core.io import DataFileError
    from core.session.document import load_session

    path = _session(tmp_path, pose=[[1e200, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    with pytest.raises(DataFileError, match=r"s\.json: invalid session: pose scales by up to"):
        load_session(path)
    # a scaled, rotated, translated pose (the handles' moves) still loads
    angle = 0.3
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                         [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3] = 1.7 * rotation
    pose[:3, 3] = [12.0, -140.0, 30.0]
    np.testing.assert_array_equal(load_session(_session(tmp_path, pose=pose.tolist())).pose, pose)


def test_a_valid_planning_block_still_plans(tmp_path, capsys):
    from core.cli import main

    path = _planning({"ac": [0, 12, 0], "pc": [0, -12, 0], "midline": [0, 0, 40],
                      "structures": [{"structure": 0, "target": None, "entry": [10, 60, 70]}]}
                     )(tmp_path)
    rc = main(_plan(path, tmp_path))
    assert rc == 0, capsys.readouterr().err
    report = json.loads((tmp_path / "plan.json").read_text())
    assert report["acpc"]["ac_pc_distance_mm"] == pytest.approx(24.0)
    assert report["structures"][0]["trajectory"]["entry"] == [10.0, 60.0, 70.0]


def test_stl_refusal_names_the_file_with_its_bytes(tmp_path, capsys):
    """The rule is right (STL cannot hold corresponded shapes); the name was shown with
    U+FFFD for its byte 0xe9 before, now as ``\\xe9`` (as ``ls -b`` shows it)."""
    from core.cli import main
    from core.io import load_mesh

    path = stl_non_utf8_name(tmp_path)
    np.testing.assert_allclose(load_mesh(path).vertices.min(0), OCTAHEDRON_V.min(0), atol=1e-5)
    rc = main(["build-model", str(path), str(path), "--out", str(tmp_path / "m.npz")])
    line = _the_error_line(capsys, rc, path, "do not keep vertex order")
    assert "caf\\xe9.stl" in line and "\ufffd" not in line
    line.encode("utf-8")


def test_fit_help_names_commands_that_exist(capsys):
    """Before: ``fit --help`` named ``ssm-studio build``, which does not exist."""
    import re

    from core.cli import command_names, main

    names = set(command_names()) | {"view", "demo"}  # the GUI's own commands (app.main)
    for command in sorted(command_names()):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = capsys.readouterr().out
        mentioned = set(re.findall(r"ssm-studio ([a-z][a-z-]*[a-z])", text))
        assert mentioned <= names, (command, mentioned - names)
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    assert "ssm-studio build-model" in capsys.readouterr().out


# --------------------------------------------------------------------------------------
# Correct reads
# --------------------------------------------------------------------------------------


def _check_bzip2_volume(volume) -> None:
    np.testing.assert_array_equal(volume.data, VOXELS)
    # space directions (-1,0,0) (0,-1,0) (0,0,2), origin (10,20,30) in LPS -> RAS by hand
    np.testing.assert_allclose(volume.affine, [[1, 0, 0, -10], [0, 1, 0, -20], [0, 0, 2, 30],
                                               [0, 0, 0, 1]], rtol=0, atol=1e-12)


@pytest.mark.parametrize("make", [nrrd_bzip2, nhdr_bzip2], ids=["attached", "detached"])
def test_bzip2_nrrd_is_read(tmp_path, make):
    """Before: refused ("trouble reading", SimpleITK is built without bzip2)."""
    from core.io import load_volume

    _check_bzip2_volume(load_volume(make(tmp_path)))


def test_data_file_outside_is_read_when_allowed(tmp_path):
    from core.io.itk_image import read_itk_image

    path = nhdr_dotdot_data_file(tmp_path)
    volume = read_itk_image(path, allow_outside=True)
    np.testing.assert_array_equal(volume.data[:, 0, 0], np.frombuffer(bytes(range(256)) * 4,
                                                                      np.uint8))
    path = mhd_dotdot_data_file(tmp_path)
    np.testing.assert_array_equal(read_itk_image(path, allow_outside=True).data[:, 0, 0],
                                  np.frombuffer(bytes(range(256)) * 4, np.uint8))


def test_a_data_file_beside_the_header_is_still_read(tmp_path):
    from core.io import load_volume

    (tmp_path / "h").mkdir()
    (tmp_path / "h" / "sub").mkdir()
    (tmp_path / "h" / "sub" / "d.raw").write_bytes(bytes(range(200)))
    path = _nhdr(tmp_path / "h" / "a.nhdr", "sub/../sub/d.raw", 200)
    np.testing.assert_array_equal(load_volume(path).data[:, 0, 0], np.arange(200))


@pytest.mark.parametrize("compressed", [False, True])
def test_valid_metaimage_still_reads(tmp_path, compressed):
    from core.io import load_volume

    if compressed:
        stream = zlib.compress(RAW)
        header = _mha_header("LOCAL", CompressedData="True", CompressedDataSize=str(len(stream)))
    else:
        stream, header = RAW, _mha_header("LOCAL")
    (tmp_path / "a.mha").write_bytes(header.encode() + stream)
    volume = load_volume(tmp_path / "a.mha")
    np.testing.assert_array_equal(volume.data, VOXELS)
    np.testing.assert_allclose(volume.spacing, [1, 1, 2])


@pytest.mark.parametrize("fmt", ["binary_big_endian", "binary_little_endian", "ascii"])
def test_ply_whose_comment_mentions_end_header_is_read(tmp_path, fmt):
    """Before: refused as "PLY file has no 'vertex' element" (the header was cut at the
    comment's ``end_header``)."""
    from core.io import load_mesh

    mesh = load_mesh(_ply(tmp_path, fmt))
    np.testing.assert_allclose(mesh.vertices, OCTAHEDRON_V, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(mesh.faces, OCTAHEDRON_F)


def test_nifti_zero_pixdim_with_an_sform_is_read_quietly(tmp_path, capfd):
    """An sform holds its own scale, so pixdim does not matter: read, no console message."""
    from core.io import load_volume

    volume = load_volume(_nifti_zero_pixdim(tmp_path, 1, 1))
    np.testing.assert_allclose(volume.affine, np.diag([2.0, 3.0, 4.0, 1.0]), atol=1e-6)
    assert capfd.readouterr().err == ""


def test_seg_label_value_error_in_mesh_labels_names_field_and_file(tmp_path, capsys):
    from core.cli import main

    path = _seg_with(tmp_path, b"Segment0_LabelValue:=1", b"Segment0_LabelValue:=two")
    rc = main(["mesh-labels", str(path), "--label", "ribs", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1
    assert err[0] == f"ssm-studio mesh-labels: {path}: Segment0_LabelValue is 'two', not an integer"
