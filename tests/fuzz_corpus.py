"""Generate the corpus of damaged inputs that every reader and CLI command must refuse cleanly.

Nothing binary is committed: each case is made from a small valid file (written here by our
own writers, or by hand for the formats other tools write) and one deterministic damage
(seeded random bytes, cut-off data, impossible counts, out-of-range indices, deep JSON, ...).
Every case is structurally corrupt, so a reader that returns data for it has silently
accepted corrupt data. Used by ``tests/test_fuzz.py``; run ``python tests/fuzz_corpus.py DIR``
to write the corpus into DIR and list it.
"""

from __future__ import annotations

import gzip
import json
import struct
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# readers by kind: the name of the core.io (or core.session.document) loader the case goes through
KINDS = ("mesh", "volume", "points", "model", "session")


@dataclass(frozen=True)
class Case:
    name: str      # unique, also the start of the file name
    path: Path
    kind: str      # one of KINDS
    damage: str    # what was done to the valid file


def _rng(seed: str) -> np.random.Generator:
    return np.random.default_rng(abs(hash_text(seed)) % (2**32))


def hash_text(text: str) -> int:
    """A stable hash (Python's hash() is salted per process)."""
    value = 0
    for ch in text.encode():
        value = (value * 131 + ch) % (2**61 - 1)
    return value


# --------------------------------------------------------------------------------------
# Valid seeds
# --------------------------------------------------------------------------------------


def _octahedron():
    from core.io import TriMesh

    vertices = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                        float) * 10 + [5.0, -20.0, 12.0]
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                      [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return TriMesh(vertices, faces, "octahedron")


_LEGACY_ASCII = """# vtk DataFile Version 4.2
seed
ASCII
DATASET POLYDATA
POINTS 6 float
15 -20 12 -5 -20 12 5 -10 12
5 -30 12 5 -20 22 5 -20 2
POLYGONS 8 32
3 0 2 4
3 2 1 4
3 1 3 4
3 3 0 4
3 2 0 5
3 1 2 5
3 3 1 5
3 0 3 5
"""

_UNSTRUCTURED = """# vtk DataFile Version 4.2
seed
ASCII
DATASET UNSTRUCTURED_GRID
POINTS 5 float
0 0 0 10 0 0 0 10 0 0 0 10 10 10 10
CELLS 2 10
4 0 1 2 3
4 1 2 3 4
CELL_TYPES 2
10
10
"""

_PLY_ASCII = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 4
property list uchar int vertex_indices
end_header
0 0 0
10 0 0
0 10 0
0 0 10
3 0 2 1
3 0 1 3
3 0 3 2
3 1 2 3
"""

_OBJ = """# seed
v 0 0 0
v 10 0 0
v 0 10 0
v 0 0 10
f 1 3 2
f 1 2 4
f 1 4 3
f 2 3 4
"""

_STL_ASCII = """solid seed
facet normal 0 0 1
outer loop
vertex 0 0 0
vertex 10 0 0
vertex 0 10 0
endloop
endfacet
facet normal 0 0 1
outer loop
vertex 0 0 0
vertex 0 10 0
vertex 0 0 10
endloop
endfacet
endsolid seed
"""


def _markups(points: list, system: str = "LPS") -> dict:
    return {"@schema": "https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/"
                       "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
            "markups": [{"type": "Fiducial", "coordinateSystem": system,
                         "controlPoints": [{"label": f"F-{i}", "position": p,
                                            "positionStatus": "defined"}
                                           for i, p in enumerate(points)]}]}


def _small_model():
    from core.models.shape_model import ShapeModel

    mesh = _octahedron()
    factors = np.random.default_rng(0).normal(size=(2, mesh.n_vertices, 3))
    return ShapeModel(mean=mesh.vertices, factors=factors, coef_var=np.array([4.0, 1.0]),
                      faces=mesh.faces, world_transform=np.eye(4), method="pca")


def _write_npz(path: Path, arrays: dict, header: dict | str | None) -> None:
    with open(path, "wb") as fh:
        payload = dict(arrays)
        if header is not None:
            payload["header"] = np.array(header if isinstance(header, str) else json.dumps(header))
        np.savez(fh, **payload)


def _model_header(**changes) -> dict:
    header = {"format": "ssm-studio-model", "format_version": 1, "units": "mm",
              "method": "pca", "params": {}, "source_meshes": [], "n_vertices": 6,
              "n_factors": 2, "info": {}}
    header.update(changes)
    return header


def _model_arrays(**changes) -> dict:
    model = _small_model()
    arrays = {"mean": model.mean, "factors": model.factors, "coef_var": model.coef_var,
              "faces": model.faces, "world_transform": model.world_transform}
    arrays.update(changes)
    return arrays


# --------------------------------------------------------------------------------------
# Damage
# --------------------------------------------------------------------------------------


def _cut(raw: bytes, fraction: float) -> bytes:
    return raw[: max(1, int(len(raw) * fraction))]


def _garbage(seed: str, n: int) -> bytes:
    return _rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


def _deep_json(depth: int = 100_000) -> str:
    return "[" * depth + "]" * depth


class _Writer:
    def __init__(self, folder: Path):
        self.folder = folder
        self.cases: list[Case] = []

    def add(self, name: str, suffix: str, kind: str, damage: str, data: bytes | str) -> None:
        path = self.folder / f"{name}{suffix}"
        if isinstance(data, str):
            data = data.encode("utf-8")
        path.write_bytes(data)
        self.cases.append(Case(name, path, kind, damage))


def _seed_bytes(folder: Path) -> dict[str, bytes]:
    """Valid files of every format, as bytes (written by our writers or by hand)."""
    import nibabel as nib

    from core.io import save_mesh, save_model, save_points

    seeds: dict[str, bytes] = {}
    mesh = _octahedron()
    work = folder / "_seeds"
    work.mkdir(exist_ok=True)
    for suffix in (".vtk", ".vtp", ".stl", ".ply", ".obj", ".gii"):
        save_mesh(work / f"m{suffix}", mesh)
        seeds[suffix] = (work / f"m{suffix}").read_bytes()
    seeds[".gii.gz"] = gzip.compress(seeds[".gii"], mtime=0)
    seeds["ascii.vtk"] = _LEGACY_ASCII.encode()
    seeds["ug.vtk"] = _UNSTRUCTURED.encode()
    seeds["ascii.ply"] = _PLY_ASCII.encode()
    seeds["hand.obj"] = _OBJ.encode()
    seeds["ascii.stl"] = _STL_ASCII.encode()
    import pyvista as pv

    grid = pv.UnstructuredGrid(np.array([4, 0, 1, 2, 3]), np.array([10]),
                               np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10.0]]))
    grid.save(str(work / "g.vtu"))
    seeds[".vtu"] = (work / "g.vtu").read_bytes()
    data = np.arange(512, dtype=np.float32).reshape(8, 8, 8)
    img = nib.Nifti1Image(data, np.diag([2.0, 2.0, 2.0, 1.0]))
    nib.save(img, str(work / "v.nii"))
    seeds[".nii"] = (work / "v.nii").read_bytes()
    seeds[".nii.gz"] = gzip.compress(seeds[".nii"], mtime=0)
    save_points(work / "p.csv", np.array([[1.0, 2, 3], [4, 5, 6], [7, 8, 9]]))
    seeds[".csv"] = (work / "p.csv").read_bytes()
    seeds[".mrk.json"] = json.dumps(_markups([[1, 2, 3], [4, 5, 6]])).encode()
    save_model(work / "model.npz", _small_model())
    seeds[".npz"] = (work / "model.npz").read_bytes()
    return seeds


def _generic(w: _Writer, seeds: dict[str, bytes]) -> None:
    """Damage that applies to every format: empty, cut short, garbage, a wrong format."""
    kinds = {".vtk": "mesh", ".vtp": "mesh", ".stl": "mesh", ".ply": "mesh", ".obj": "mesh",
             ".gii": "mesh", ".gii.gz": "mesh", ".vtu": "mesh", ".nii": "volume",
             ".nii.gz": "volume", ".csv": "points", ".mrk.json": "points", ".npz": "model"}
    # cut points at which the data are structurally incomplete for each format (formats
    # without counts, like OBJ and CSV, are not cut: a shorter file is a valid smaller one)
    cuts = {".vtk": (0.05, 0.3, 0.6, 0.9), ".vtp": (0.1, 0.5, 0.9), ".stl": (0.5, 0.9),
            ".ply": (0.1, 0.4, 0.8), ".gii": (0.2, 0.6, 0.95), ".gii.gz": (0.3, 0.7, 0.98),
            ".vtu": (0.2, 0.6, 0.9), ".nii": (0.05, 0.5, 0.9), ".nii.gz": (0.1, 0.5, 0.97),
            ".mrk.json": (0.3, 0.7), ".npz": (0.1, 0.5, 0.9)}
    for suffix, kind in kinds.items():
        tag = suffix.strip(".").replace(".", "_")
        raw = seeds[suffix]
        w.add(f"{tag}_empty", suffix, kind, "empty file", b"")
        w.add(f"{tag}_whitespace", suffix, kind, "only whitespace", b"   \n\n  \t\n")
        w.add(f"{tag}_garbage", suffix, kind, "random bytes", _garbage(tag, 700))
        w.add(f"{tag}_nul", suffix, kind, "NUL bytes", b"\x00" * 600)
        w.add(f"{tag}_prefixed", suffix, kind, "garbage before valid data",
              _garbage(tag + "p", 64) + raw)
        for fraction in cuts.get(suffix, ()):
            w.add(f"{tag}_cut{int(fraction * 100)}", suffix, kind,
                  f"cut at {fraction:.0%}", _cut(raw, fraction))
        other = seeds[".nii"] if kind != "volume" else seeds[".ply"]
        w.add(f"{tag}_other_format", suffix, kind, "a file of another format", other)


def _legacy_vtk(w: _Writer) -> None:
    head = "# vtk DataFile Version 4.2\nseed\nASCII\nDATASET POLYDATA\n"
    pts = "POINTS 4 float\n0 0 0 10 0 0 0 10 0 10 10 0\n"
    cases = {
        "index_past_end": pts + "POLYGONS 1 4\n3 0 1 99999999\n",
        "index_negative": pts + "POLYGONS 1 4\n3 0 1 -7\n",
        "quad_bad_index": pts + "POLYGONS 2 9\n4 0 1 3 2\n3 0 1 400\n",
        "count_negative": pts + "POLYGONS 1 4\n-3 0 1 2\n",
        "count_overrun": pts + "POLYGONS 1 4\n9 0 1 2\n",
        "fewer_cells": pts + "POLYGONS 2 8\n3 0 1 2\n",
        "size_huge": pts + "POLYGONS 1 400000000\n3 0 1 2\n",
        "strip_bad_index": pts + "TRIANGLE_STRIPS 1 5\n4 0 1 2 77\n",
        "points_huge": "POINTS 2000000000 float\n0 0 0\n",
        "points_negative": "POINTS -5 float\n0 0 0\n",
        "points_short": "POINTS 4 float\n0 0 0 10 0\n" + "POLYGONS 1 4\n3 0 1 2\n",
        "points_nan": "POINTS 4 float\n0 0 0 nan 0 0 0 10 0 10 10 0\nPOLYGONS 1 4\n3 0 1 2\n",
        "no_cells": pts,
        "lines_only": pts + "LINES 1 3\n2 0 1\n",
        "point_data_short": pts + "POLYGONS 1 4\n3 0 1 2\nPOINT_DATA 4\nSCALARS s float\n"
                                  "LOOKUP_TABLE default\n1 2\n",
        "dataset_image": "",
    }
    for name, body in cases.items():
        text = head + body
        if name == "dataset_image":
            text = ("# vtk DataFile Version 4.2\nseed\nASCII\nDATASET STRUCTURED_POINTS\n"
                    "DIMENSIONS 2 2 2\nSPACING 1 1 1\nORIGIN 0 0 0\nPOINT_DATA 8\n"
                    "SCALARS s float\nLOOKUP_TABLE default\n0 1 2 3 4 5 6 7\n")
        w.add(f"vtk_{name}", ".vtk", "mesh", name.replace("_", " "), text)
    ug_head = "# vtk DataFile Version 4.2\nseed\nASCII\nDATASET UNSTRUCTURED_GRID\n" \
              "POINTS 4 float\n0 0 0 10 0 0 0 10 0 0 0 10\n"
    ug = {
        "index_past_end": "CELLS 1 5\n4 0 1 2 99999999\nCELL_TYPES 1\n10\n",
        "index_negative": "CELLS 1 5\n4 0 1 2 -1\nCELL_TYPES 1\n10\n",
        "bad_type": "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n255\n",
        "type_size_mismatch": "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n5\n",
        "more_types": "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 3\n10 10 10\n",
        "cells_huge": "CELLS 1000000000 5000000000\n4 0 1 2 3\nCELL_TYPES 1\n10\n",
        "polyhedron": "CELLS 1 5\n4 0 1 2 3\nCELL_TYPES 1\n42\n",
    }
    for name, body in ug.items():
        w.add(f"vtu_legacy_{name}", ".vtk", "mesh", "unstructured grid: " + name, ug_head + body)
    w.add("vtk_binary_points_huge", ".vtk", "mesh", "binary header claims 2e9 points",
          b"# vtk DataFile Version 4.2\nseed\nBINARY\nDATASET POLYDATA\nPOINTS 2000000000 "
          b"float\n" + b"\x00" * 48)


def _xml_vtk(w: _Writer, seeds: dict[str, bytes]) -> None:
    import re

    vtp = seeds[".vtp"].decode("latin-1")
    huge = re.sub(r'NumberOfPoints="\d+"', 'NumberOfPoints="2000000000"', vtp, count=1)
    w.add("vtp_points_huge", ".vtp", "mesh", "header claims 2e9 points", huge.encode("latin-1"))
    w.add("vtp_points_negative", ".vtp", "mesh", "negative point count",
          re.sub(r'NumberOfPoints="\d+"', 'NumberOfPoints="-4"', vtp, count=1).encode("latin-1"))
    w.add("vtp_polys_huge", ".vtp", "mesh", "header claims 1e9 polygons",
          re.sub(r'NumberOfPolys="\d+"', 'NumberOfPolys="1000000000"', vtp,
                 count=1).encode("latin-1"))
    w.add("vtp_not_xml", ".vtp", "mesh", "text that is not XML", "<VTKFile type=")
    ascii_vtp = ('<?xml version="1.0"?>\n<VTKFile type="PolyData" version="1.0" '
                 'byte_order="LittleEndian">\n<PolyData>\n<Piece NumberOfPoints="3" '
                 'NumberOfPolys="1">\n<Points><DataArray type="Float32" NumberOfComponents="3" '
                 'format="ascii">0 0 0 1 0 0 0 1 0</DataArray></Points>\n<Polys>'
                 '<DataArray type="Int64" Name="connectivity" format="ascii">0 1 {bad}'
                 '</DataArray><DataArray type="Int64" Name="offsets" format="ascii">3'
                 '</DataArray></Polys>\n</Piece>\n</PolyData>\n</VTKFile>\n')
    w.add("vtp_index_past_end", ".vtp", "mesh", "polygon index past the points",
          ascii_vtp.format(bad=70000))
    w.add("vtp_index_negative", ".vtp", "mesh", "negative polygon index",
          ascii_vtp.format(bad=-2))
    vtu = seeds[".vtu"].decode("latin-1")
    w.add("vtu_points_huge", ".vtu", "mesh", "header claims 2e9 points",
          re.sub(r'NumberOfPoints="\d+"', 'NumberOfPoints="2000000000"', vtu,
                 count=1).encode("latin-1"))
    w.add("vtu_cells_huge", ".vtu", "mesh", "header claims 1e9 cells",
          re.sub(r'NumberOfCells="\d+"', 'NumberOfCells="1000000000"', vtu,
                 count=1).encode("latin-1"))


def _stl(w: _Writer, seeds: dict[str, bytes]) -> None:
    binary = bytearray(seeds[".stl"])
    binary[80:84] = struct.pack("<I", 100_000_000)
    w.add("stl_count_huge", ".stl", "mesh", "binary header claims 1e8 triangles", bytes(binary))
    w.add("stl_header_only", ".stl", "mesh", "binary header, no triangles",
          seeds[".stl"][:84])
    w.add("stl_ascii_no_end", ".stl", "mesh", "ASCII STL without endsolid",
          _STL_ASCII.replace("endsolid seed\n", ""))
    w.add("stl_ascii_words", ".stl", "mesh", "ASCII STL with words for numbers",
          _STL_ASCII.replace("vertex 10 0 0", "vertex ten zero zero"))
    w.add("stl_nan", ".stl", "mesh", "NaN vertex", _STL_ASCII.replace("vertex 10 0 0",
                                                                     "vertex nan 0 0"))


def _ply(w: _Writer) -> None:
    p = _PLY_ASCII
    cases = {
        "vertex_count_huge": p.replace("element vertex 4", "element vertex 4000000000"),
        "face_count_huge": p.replace("element face 4", "element face 1000000000"),
        "count_negative": p.replace("element vertex 4", "element vertex -4"),
        "index_past_end": p.replace("3 1 2 3\n", "3 1 2 300\n"),
        "index_huge": p.replace("3 1 2 3\n", "3 1 2 100000000000000000000\n"),
        "index_negative": p.replace("3 1 2 3\n", "3 1 2 -3\n"),
        "scalar_vertex_indices": p.replace("property list uchar int vertex_indices",
                                           "property int vertex_indices"),
        "list_count_over": p.replace("3 1 2 3\n", "7 1 2 3\n"),
        "unknown_type": p.replace("property float x", "property quaternion x"),
        "no_end_header": p.replace("end_header\n", ""),
        "no_format": p.replace("format ascii 1.0\n", ""),
        "bad_format": p.replace("format ascii 1.0", "format ebcdic 1.0"),
        "words": p.replace("10 0 0", "ten 0 0"),
        "nan_vertex": p.replace("10 0 0", "nan 0 0"),
        "no_xyz": p.replace("property float x\n", "property float u\n"),
        "missing_rows": p.replace("3 0 3 2\n3 1 2 3\n", ""),
        "property_before_element": p.replace("ply\nformat ascii 1.0\n",
                                             "ply\nformat ascii 1.0\nproperty float w\n"),
    }
    for name, text in cases.items():
        w.add(f"ply_{name}", ".ply", "mesh", name.replace("_", " "), text)
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
              "property float y\nproperty float z\nelement face 1\n"
              "property list uchar int vertex_indices\nend_header\n").encode()
    vertices = np.zeros((3, 3), "<f4").tobytes()
    w.add("ply_binary_list_count_255", ".ply", "mesh", "binary list count 255 for 3 values",
          header + vertices + bytes([255]) + struct.pack("<3i", 0, 1, 2))
    w.add("ply_binary_index_past_end", ".ply", "mesh", "binary face index past the vertices",
          header + vertices + bytes([3]) + struct.pack("<3i", 0, 1, 2_000_000_000))
    w.add("ply_binary_cut", ".ply", "mesh", "binary data cut in the vertices",
          header + vertices[:20])


def _obj(w: _Writer) -> None:
    o = _OBJ
    cases = {
        "index_past_end": o.replace("f 2 3 4", "f 2 3 40"),
        "index_huge": o.replace("f 2 3 4", "f 2 3 100000000000000000000"),
        "index_zero": o.replace("f 2 3 4", "f 2 3 0"),
        "relative_past_start": o.replace("f 2 3 4", "f -1 -2 -9"),
        "vertex_two_coords": o.replace("v 0 0 10", "v 0 0"),
        "vertex_words": o.replace("v 0 0 10", "v zero 0 10"),
        "vertex_nan": o.replace("v 0 0 10", "v nan 0 10"),
        "face_words": o.replace("f 2 3 4", "f two 3 4"),
        "face_two_vertices": o.replace("f 2 3 4", "f 2 3"),
        "faces_only": "f 1 2 3\nf 1 3 4\n",
        "vertices_only": "v 0 0 0\nv 1 0 0\nv 0 1 0\n",
        "binary_inside": o[:20] + "\x00\x01\x02" + o[20:],
    }
    for name, text in cases.items():
        w.add(f"obj_{name}", ".obj", "mesh", name.replace("_", " "), text)


def _gifti(w: _Writer, seeds: dict[str, bytes]) -> None:
    text = seeds[".gii"].decode("utf-8")
    w.add("gii_no_triangles", ".gii", "mesh", "no TRIANGLE array",
          text.replace("NIFTI_INTENT_TRIANGLE", "NIFTI_INTENT_SHAPE"))
    w.add("gii_no_pointset", ".gii", "mesh", "no POINTSET array",
          text.replace("NIFTI_INTENT_POINTSET", "NIFTI_INTENT_SHAPE"))
    w.add("gii_bad_xml", ".gii", "mesh", "XML cut in a tag", text[: text.find("<DataArray") + 5])
    raw = gzip.compress(seeds[".gii"], mtime=0)
    crc = bytearray(raw)
    crc[-8] ^= 0xFF  # the CRC-32 of the uncompressed data
    w.add("gii_gz_crc", ".gii.gz", "mesh", "gzip CRC does not match", bytes(crc))
    w.add("gii_gz_not_gzip", ".gii.gz", "mesh", "not gzip data", seeds[".gii"])


def _nifti(w: _Writer, seeds: dict[str, bytes]) -> None:
    raw = seeds[".nii"]

    def with_dims(dims: tuple[int, ...], body: bytes = b"") -> bytes:
        header = bytearray(raw[:352])
        header[40:56] = struct.pack("<8h", len(dims), *dims, *([1] * (7 - len(dims))))
        return bytes(header) + body

    w.add("nii_dims_huge", ".nii", "volume", "header claims 30000^3 voxels",
          with_dims((30000, 30000, 30000))[:400])
    w.add("nii_dims_1400", ".nii", "volume", "1 kB claiming 1400^3 voxels",
          with_dims((1400, 1400, 1400), b"\x00" * 700))
    w.add("nii_gz_dims_huge", ".nii.gz", "volume", "gzip of a header claiming 30000^3",
          gzip.compress(with_dims((30000, 30000, 30000)), mtime=0))
    w.add("nii_dims_zero", ".nii", "volume", "a zero dimension",
          with_dims((8, 0, 8), raw[352:]))
    w.add("nii_dims_negative", ".nii", "volume", "a negative dimension",
          with_dims((8, -8, 8), raw[352:]))
    w.add("nii_4d", ".nii", "volume", "4D with 2 volumes",
          with_dims((8, 8, 4, 2), raw[352:]))
    bad_type = bytearray(raw)
    bad_type[70:72] = struct.pack("<h", 1792)  # complex256
    w.add("nii_complex", ".nii", "volume", "complex voxels", bytes(bad_type))
    bad_type[70:72] = struct.pack("<h", 9999)
    w.add("nii_unknown_type", ".nii", "volume", "unknown datatype code", bytes(bad_type))
    singular = bytearray(raw)
    singular[252:254] = struct.pack("<h", 0)  # qform_code 0
    singular[254:256] = struct.pack("<h", 1)  # sform_code 1
    singular[280:328] = b"\x00" * 48          # sform rows all zero
    w.add("nii_sform_singular", ".nii", "volume", "singular sform", bytes(singular))
    nan_affine = bytearray(singular)
    nan_affine[280:284] = struct.pack("<f", float("nan"))
    w.add("nii_sform_nan", ".nii", "volume", "NaN in the sform", bytes(nan_affine))
    pair = bytearray(raw)
    pair[344:348] = b"ni1\x00"
    w.add("nii_pair_header", ".nii", "volume", "a .hdr of a .hdr/.img pair", bytes(pair))
    gz = bytearray(seeds[".nii.gz"])
    gz[-8] ^= 0x5A
    w.add("nii_gz_crc", ".nii.gz", "volume", "gzip CRC does not match the data", bytes(gz))
    gz = bytearray(seeds[".nii.gz"])
    gz[-4] ^= 0x01
    w.add("nii_gz_isize", ".nii.gz", "volume", "gzip length field does not match", bytes(gz))
    middle = bytearray(seeds[".nii.gz"])
    middle[len(middle) // 2] ^= 0xFF
    w.add("nii_gz_flipped", ".nii.gz", "volume", "one byte of the deflate stream flipped",
          bytes(middle))
    w.add("nii_gz_uncompressed", ".nii.gz", "volume", ".nii.gz holding plain NIfTI", raw)


def _points(w: _Writer) -> None:
    csv_cases = {
        "header_missing": "1,2,3\n4,5,6\n",
        "header_other": "a,b,c\n1,2,3\n",
        "words": "x,y,z\n1,2,3\n4,abc,6\n",
        "nan": "x,y,z\n1,2,3\nnan,5,6\n",
        "inf": "x,y,z\n1,2,3\n4,inf,6\n",
        "short_row": "x,y,z,nx,ny,nz\n1,2,3,0,0,1\n4,5,6,0\n",
        "header_only": "x,y,z\n",
        "lps_words": "label,l,p,s\nF-1,1,two,3\n",
        "ras_short": "label,r,a,s\nF-1,1,2\n",
        "all_undefined": "label,l,p,s,defined\nF-1,1,2,3,0\n",
        "quote_open": 'x,y,z\n"1,2,3\n',
        "latin1": "x,y,z\n1,2,3\n".encode("utf-8").decode("utf-8") + "\xe9\n",
    }
    for name, text in csv_cases.items():
        data = text.encode("latin-1") if name == "latin1" else text.encode()
        w.add(f"csv_{name}", ".csv", "points", name.replace("_", " "), data)
    w.add("tsv_words", ".tsv", "points", "TSV with words", "x\ty\tz\n1\tb\t3\n")
    w.add("tsv_header_other", ".tsv", "points", "TSV header names no coordinates",
          "u\tv\tw\n1\t2\t3\n")
    fcsv_head = ("# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"
                 "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n")
    fcsv = {
        "words": fcsv_head + "1,1,two,3,0,0,0,1,1,1,0,F-1,,\n",
        "short": fcsv_head + "1,1\n",
        "system_unknown": fcsv_head.replace("LPS", "IJK") + "1,1,2,3,0,0,0,1,1,1,0,F-1,,\n",
        "no_points": fcsv_head,
        "no_xyz_columns": fcsv_head.replace("id,x,y,z", "id,a,b,c") +
        "1,1,2,3,0,0,0,1,1,1,0,F-1,,\n",
        "nan": fcsv_head + "1,nan,2,3,0,0,0,1,1,1,0,F-1,,\n",
    }
    for name, text in fcsv.items():
        w.add(f"fcsv_{name}", ".fcsv", "points", name.replace("_", " "), text)
    markups = {
        "not_json": '{"markups": [',
        "deep": _deep_json(),
        "no_markups": json.dumps({"something": 1}),
        "markups_not_list": json.dumps({"markups": {"a": 1}}),
        "markup_not_object": json.dumps({"markups": [3]}),
        "system_unknown": json.dumps(_markups([[1, 2, 3]], "IJK")),
        "position_words": json.dumps(_markups([["a", "b", "c"]])),
        "position_2d": json.dumps(_markups([[1, 2]])),
        "position_nan": json.dumps(_markups([[1, 2, 3]])).replace("[1, 2, 3]", "[NaN, 2, 3]"),
        "points_not_list": json.dumps({"markups": [{"controlPoints": 5}]}),
        "point_not_object": json.dumps({"markups": [{"controlPoints": [7]}]}),
        "only_previews": json.dumps({"markups": [{"controlPoints": [
            {"position": [], "positionStatus": "preview"}]}]}),
        "orientation_words": json.dumps({"markups": [{"controlPoints": [
            {"position": [1, 2, 3], "orientation": ["a"] * 9}]}]}),
        "top_level_list": json.dumps([1, 2, 3]),
    }
    for name, text in markups.items():
        w.add(f"mrk_{name}", ".mrk.json", "points", name.replace("_", " "), text)
    w.add("json_markups_deep", ".json", "points", "deep JSON as .json points", _deep_json())


def _models(w: _Writer) -> None:
    folder = w.folder

    def npz(name: str, damage: str, arrays: dict, header) -> None:
        path = folder / f"model_{name}.npz"
        _write_npz(path, arrays, header)
        w.cases.append(Case(f"model_{name}", path, "model", damage))

    npz("complex_mean", "complex mean", _model_arrays(mean=_small_model().mean + 1j),
        _model_header())
    npz("string_factors", "text factors", _model_arrays(factors=np.array(["a", "b"])),
        _model_header())
    npz("string_coef_var", "text coef_var", _model_arrays(coef_var=np.array(["1", "2"])),
        _model_header())
    npz("singular_transform", "singular world transform",
        _model_arrays(world_transform=np.diag([1.0, 1.0, 0.0, 1.0])), _model_header())
    npz("projective_transform", "world transform with a projective row",
        _model_arrays(world_transform=np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                                 [0.5, 0, 0, 1]])), _model_header())
    npz("nan_mean", "NaN in the mean", _model_arrays(mean=np.full((6, 3), np.nan)),
        _model_header())
    npz("faces_float", "float faces", _model_arrays(faces=_small_model().faces + 0.5),
        _model_header())
    npz("faces_out_of_range", "faces past the vertices",
        _model_arrays(faces=_small_model().faces + 100), _model_header())
    npz("shape_mismatch", "factors for another vertex count",
        _model_arrays(factors=np.zeros((2, 7, 3))), _model_header())
    npz("coef_count_mismatch", "coef_var for another factor count",
        _model_arrays(coef_var=np.ones(5)), _model_header())
    npz("header_count_mismatch", "header n_vertices disagrees",
        _model_arrays(), _model_header(n_vertices=99))
    npz("header_deep", "100,000-deep JSON header", _model_arrays(), _deep_json())
    npz("header_not_json", "header is not JSON", _model_arrays(), "{format: nope")
    npz("header_list", "header is a JSON list", _model_arrays(), "[1, 2]")
    npz("no_header", "no header", _model_arrays(), None)
    npz("wrong_format", "another format name", _model_arrays(), _model_header(format="other"))
    npz("version_2", "format version 2", _model_arrays(), _model_header(format_version=2))
    npz("units_m", "metres", _model_arrays(), _model_header(units="m"))
    npz("missing_mean", "no mean array",
        {k: v for k, v in _model_arrays().items() if k != "mean"}, _model_header())
    npz("params_list", "params is a list", _model_arrays(), _model_header(params=[1]))
    # an .npy member whose header claims shape (1e12, 3): written by hand
    path = folder / "model_member_shape_huge.npz"
    _write_npz(path, _model_arrays(), _model_header())
    with zipfile.ZipFile(path, "a") as archive:
        header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000000, 3), }"
        header = header + " " * (117 - len(header)) + "\n"
        archive.writestr("extra.npy", b"\x93NUMPY\x01\x00" + struct.pack("<H", 118) +
                         header.encode("latin-1") + b"\x00" * 48)
    w.cases.append(Case("model_member_shape_huge", path, "model",
                        "an .npy member claiming shape (1e12, 3)"))
    # a zip bomb: 24 MB of zeros in a ~25 kB member, written without holding it in memory
    path = folder / "model_zip_bomb.npz"
    _write_npz(path, _model_arrays(), _model_header())
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        n = 3 << 20
        header = f"{{'descr': '<f8', 'fortran_order': False, 'shape': ({n},), }}"
        header = header + " " * (117 - len(header)) + "\n"
        with archive.open("bomb.npy", "w", force_zip64=True) as member:
            member.write(b"\x93NUMPY\x01\x00" + struct.pack("<H", 118) + header.encode())
            zeros = bytes(1 << 20)
            for _ in range(n * 8 >> 20):
                member.write(zeros)
    w.cases.append(Case("model_zip_bomb", path, "model", "zip bomb: 24 MB of zeros"))


def _statismo_models(w: _Writer) -> None:
    """statismo .h5 files cut short (HDF5 finds EOF before its end-of-allocation) and with
    their superblock damaged, from our writer's file and Scalismo's real ones."""
    from core.io.statismo import write_statismo

    ours = w.folder / "seed_model.h5"
    write_statismo(ours, _small_model())
    real = Path(__file__).resolve().parent / "data" / "real" / "statismo"
    seeds = {"ours": ours.read_bytes(),
             "scalismo_tetra": (real / "scalismo_TetraMeshModel2.h5").read_bytes()}
    for label, raw in seeds.items():
        for fraction in (0.02, 0.3, 0.7, 0.97, 0.999):
            w.add(f"statismo_{label}_cut_{int(fraction * 1000)}", ".h5", "model",
                  f"statismo file ({label}) cut at {fraction:.1%}", _cut(raw, fraction))
        w.add(f"statismo_{label}_superblock", ".h5", "model", "superblock overwritten",
              raw[:8] + _garbage(label, 40) + raw[48:])
    w.add("statismo_scalismo_truncated_as_published", ".h5", "model",
          "Scalismo's TetraMeshModel1.h5 (truncated as published)",
          (real / "scalismo_TetraMeshModel1.h5").read_bytes())


def _sessions(w: _Writer) -> None:
    base = {"format": "ssm-studio-session", "format_version": 1, "image": None,
            "model": None, "points": [[1, 2, 3]], "fit": {}}
    cases = {
        "deep": _deep_json(),
        "not_json": "{'format': 1",
        "list": "[]",
        "other_format": {**base, "format": "other"},
        "version_text": {**base, "format_version": "1"},
        "version_future": {**base, "format_version": 99},
        "points_words": {**base, "points": [["a", "b", "c"]]},
        "points_2d": {**base, "points": [[1, 2]]},
        "points_nan": {**base, "points": [[1, 2, "NaN"]]},
        "normals_mismatch": {**base, "normals": [[0, 0, 1], [0, 0, 1]]},
        "slices_bad_plane": {**base, "point_slices": [["oblique", 3]]},
        "slices_mismatch": {**base, "point_slices": [["axial", 3], ["axial", 4]]},
        "pose_singular": {**base, "pose": [[0] * 4] * 4},
        "pose_3x3": {**base, "pose": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        "coef_matrix": {**base, "coef": [[1, 2], [3, 4]]},
        "fit_method_unknown": {**base, "fit": {"method": "magic"}},
        "fit_prior_text": {**base, "fit": {"prior_weight": "heavy"}},
        "fit_prior_negative": {**base, "fit": {"prior_weight": -1}},
        "fit_list": {**base, "fit": [1]},
        "window_three": {**base, "window": [1, 2, 3]},
        "crosshair_2d": {**base, "crosshair": [1, 2]},
        "image_number": {**base, "image": 5},
        "packed_bad_base64": {**base, "points": {"dtype": "<f8", "shape": [1, 3],
                                                 "base64": "@@@"}},
        "packed_object_dtype": {**base, "points": {"dtype": "O", "shape": [1, 3],
                                                   "base64": "AAAA"}},
        "packed_shape_mismatch": {**base, "points": {"dtype": "<f8", "shape": [5, 3],
                                                     "base64": "AAAAAAAAAAA="}},
        "huge_number": {**base, "points": [[1e400, 2, 3]]},
    }
    for name, doc in cases.items():
        text = doc if isinstance(doc, str) else json.dumps(doc).replace("Infinity", "1e400")
        w.add(f"session_{name}", ".json", "session", name.replace("_", " "), text)


def generate(folder: Path) -> list[Case]:
    """Write every damaged input into ``folder``; returns the cases (>= 200)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    seeds = _seed_bytes(folder)
    w = _Writer(folder)
    _generic(w, seeds)
    _legacy_vtk(w)
    _xml_vtk(w, seeds)
    _stl(w, seeds)
    _ply(w)
    _obj(w)
    _gifti(w, seeds)
    _nifti(w, seeds)
    _points(w)
    _models(w)
    _statismo_models(w)
    _sessions(w)
    names = [c.name for c in w.cases]
    assert len(names) == len(set(names)), "case names must be unique"
    return w.cases


def good_files(folder: Path) -> dict[str, Path]:
    """Valid inputs for the CLI cases (a model, points, an image, corresponded meshes)."""
    import nibabel as nib

    from core.io import TriMesh, save_mesh, save_model, save_points

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    model = _small_model()
    save_model(folder / "good_model.npz", model)
    save_points(folder / "good_points.csv", model.mean[:4] + 0.5)
    nib.save(nib.Nifti1Image(np.zeros((24, 24, 24), np.uint8), np.diag([2.0, 2, 2, 1]) +
                             np.array([[0, 0, 0, -20], [0, 0, 0, -40], [0, 0, 0, -10],
                                       [0, 0, 0, 0]])), str(folder / "good_image.nii.gz"))
    meshes = []
    rng = np.random.default_rng(3)
    for i in range(3):
        mesh = TriMesh(model.mean + rng.normal(scale=0.3, size=model.mean.shape), model.faces)
        save_mesh(folder / f"good_mesh_{i}.vtk", mesh)
        meshes.append(folder / f"good_mesh_{i}.vtk")
    return {"model": folder / "good_model.npz", "points": folder / "good_points.csv",
            "image": folder / "good_image.nii.gz", "meshes": meshes}


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "fuzz-corpus")
    corpus = generate(out)
    for case in corpus:
        print(f"{case.kind:8s} {case.path.name:45s} {case.damage}")
    print(f"{len(corpus)} cases in {out}")
