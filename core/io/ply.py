"""Stanford PLY meshes (.ply), ascii and binary: a numpy reader of our own.

VTK's PLY reader crashes on truncated files; this one checks every size against the data.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import DataFileError
from core.io.atomic import atomic_path
from core.io.polygons import polygons_to_triangles
from core.io.vtk_meshes import space_in_text
from core.types.trimesh import TriMesh

# PLY scalar type names (both spellings of the PLY spec) -> numpy type codes.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
              "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
              "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]]  # (name, value type, list count type or None)


# the header ends at a line that is "end_header" itself (a comment may mention the word)
_END_HEADER = re.compile(rb"(?:^|\n)end_header[ \t]*(\r?\n|$)")


def _parse_ply_header(path: Path, raw: bytes) -> tuple[str, list[_PlyElement], int]:
    match = _END_HEADER.search(raw)
    if not raw.startswith(b"ply") or match is None:
        what = "no 'end_header' line" if raw.startswith(b"ply") else "does not start with 'ply'"
        raise DataFileError(path, f"not a PLY file or truncated header ({what})")
    end = match.start() + (1 if raw[match.start():match.start() + 1] == b"\n" else 0)
    body_start = match.end()
    try:
        lines = raw[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise DataFileError(path, "PLY header is not ASCII text") from None
    fmt, elements = "", []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append(_PlyElement(words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1].properties.append((words[4], _PLY_TYPES[words[3]],
                                                _PLY_TYPES[words[2]]))
            elif words[0] == "property":
                elements[-1].properties.append((words[2], _PLY_TYPES[words[1]], None))
            else:
                raise ValueError(words[0])
        except (IndexError, KeyError, ValueError):
            raise DataFileError(path, f"bad PLY header line {number}: '{line[:80]}'") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DataFileError(path, f"unknown PLY format '{fmt}'")
    if any(e.count < 0 for e in elements):
        raise DataFileError(path, "negative element count in PLY header")
    return fmt, elements, body_start


def _ply_binary_element(path: Path, body: memoryview, pos: int, element: _PlyElement,
                        order: str) -> tuple[Mapping[str, np.ndarray | list], int]:
    """Read one element's records from binary PLY data starting at byte ``pos``."""
    props = element.properties
    n = element.count
    truncated = DataFileError(path, f"truncated PLY file (element '{element.name}' needs more "
                                    "data than the file holds)")
    if all(count_type is None for _, _, count_type in props):
        dtype = np.dtype([(name, order + t) for name, t, _ in props])
        if pos + n * dtype.itemsize > len(body):
            raise truncated
        rec = np.frombuffer(body, dtype=dtype, count=n, offset=pos)
        return {name: rec[name] for name, _, _ in props}, pos + n * dtype.itemsize
    # Lists: first try "every list has the length of the first one" (all triangles),
    # checked afterwards; otherwise walk the records one by one.
    if n == 0:
        return {name: np.zeros((0, 3)) for name, _, _ in props}, pos
    fields: list[tuple] = []   # (name, dtype) or (name, dtype, (length,))
    probe = pos
    for name, value_type, count_type in props:
        if count_type is None:
            fields.append((name, order + value_type))
            probe += np.dtype(value_type).itemsize
            continue
        if probe + np.dtype(count_type).itemsize > len(body):
            raise truncated
        length = int(np.frombuffer(body, dtype=order + count_type, count=1, offset=probe)[0])
        fields.append((name + "#n", order + count_type))
        fields.append((name, order + value_type, (length,)))
        probe += np.dtype(count_type).itemsize + length * np.dtype(value_type).itemsize
    dtype = np.dtype(fields)
    if pos + n * dtype.itemsize <= len(body):
        rec = np.frombuffer(body, dtype=dtype, count=n, offset=pos)
        uniform = all(np.all(rec[name + "#n"] == rec.dtype[name].shape[0])
                      for name, _, count_type in props if count_type is not None)
        if uniform:
            return {name: rec[name] for name, _, _ in props}, pos + n * dtype.itemsize
    out: dict[str, list] = {name: [] for name, _, _ in props}
    for _ in range(n):
        for name, value_type, count_type in props:
            if count_type is not None:
                size = np.dtype(count_type).itemsize
                if pos + size > len(body):
                    raise truncated
                length = int(np.frombuffer(body, dtype=order + count_type, count=1, offset=pos)[0])
                pos += size
            else:
                length = 1
            size = np.dtype(value_type).itemsize * length
            if pos + size > len(body):
                raise truncated
            values = np.frombuffer(body, dtype=order + value_type, count=length, offset=pos)
            out[name].append(values if count_type is not None else values[0])
            pos += size
    return out, pos


def _ply_ascii_element(path: Path, lines: list[bytes], start: int,
                       element: _PlyElement) -> tuple[Mapping[str, np.ndarray | list], int]:
    n = element.count
    rows = lines[start:start + n]
    if len(rows) < n:
        raise DataFileError(path, f"truncated PLY file (element '{element.name}' has "
                                  f"{len(rows)} of {n} lines)")
    try:
        tokens = [row.split() for row in rows]
        lengths = {len(t) for t in tokens}
        if len(lengths) <= 1:
            table = np.array(tokens, dtype=np.float64).reshape(n, -1)
            columns: dict[str, np.ndarray] = {}
            col = 0
            for name, _, count_type in element.properties:
                if count_type is None:
                    columns[name] = table[:, col]
                    col += 1
                else:
                    length = int(table[0, col]) if n else 0
                    if n and np.any(table[:, col] != length):
                        break  # lists of different lengths: read row by row below
                    columns[name] = table[:, col + 1:col + 1 + length]
                    col += 1 + length
            else:
                if col == table.shape[1]:
                    return columns, start + n
        out: dict[str, list] = {name: [] for name, _, _ in element.properties}
        for row in tokens:
            values = [float(v) for v in row]
            col = 0
            for name, _, count_type in element.properties:
                if count_type is None:
                    out[name].append(values[col])
                    col += 1
                else:
                    length = int(values[col])
                    out[name].append(np.array(values[col + 1:col + 1 + length]))
                    col += 1 + length
            if col != len(values):
                raise ValueError("row length does not match its list counts")
    except (ValueError, IndexError):
        raise DataFileError(path, f"PLY element '{element.name}' has non-numeric or missing "
                                  "values") from None
    return out, start + n


def load_ply(path: Path) -> tuple[TriMesh, str | None]:
    """Read a PLY surface (ascii or binary): 'vertex' x, y, z and 'face' vertex_indices.

    Returns the mesh and the ``SPACE=`` tag of its comments (3D Slicer), or None.
    """
    raw = path.read_bytes()
    fmt, elements, body_start = _parse_ply_header(path, raw)
    face_element = next((e for e in elements if e.name == "face"), None)
    if face_element is not None:
        for name, _, count_type in face_element.properties:
            if name in ("vertex_indices", "vertex_index") and count_type is None:
                raise DataFileError(path, f"PLY face property '{name}' is a scalar, a face "
                                          "needs a list of vertex indices")
    try:
        data = _read_ply_body(path, raw, fmt, elements, body_start)
    except (ValueError, TypeError, IndexError, OverflowError) as exc:
        raise DataFileError(path, f"corrupt PLY data ({' '.join(str(exc).split())[:120]})") \
            from None
    vertex = data.get("vertex")
    if vertex is None or not all(k in vertex for k in "xyz"):
        raise DataFileError(path, "PLY file has no 'vertex' element with x, y, z")
    vertices = np.column_stack([np.asarray(vertex[k], dtype=np.float64) for k in "xyz"])
    if len(vertices) == 0:
        raise DataFileError(path, "empty mesh (no vertices)")
    face = data.get("face", {})
    key = next((k for k in ("vertex_indices", "vertex_index") if k in face), None)
    if key is None:
        raise DataFileError(path, "mesh has no triangles (no 'face' element: points only)")
    faces = polygons_to_triangles(_integer_lists(path, face[key]))
    header = raw[:body_start]
    comments = b"\n".join(ln for ln in header.splitlines() if ln.startswith(b"comment"))
    return TriMesh(vertices, faces, path.name), space_in_text(comments)


def _integer_lists(path: Path, lists: np.ndarray | list) -> np.ndarray | list:
    """Face index lists as int64, refusing values no int64 holds (an ASCII '1e20')."""
    groups = [lists] if isinstance(lists, np.ndarray) else lists
    for group in groups:
        values = np.asarray(group)
        if values.size and values.dtype.kind == "f" and \
                not np.all(np.isfinite(values) & (np.abs(values) < 2.0**62)):
            raise DataFileError(path, "faces index vertices that do not exist (an index is "
                                      "out of any integer range)")
    if isinstance(lists, np.ndarray):
        return lists.astype(np.int64)
    return [np.asarray(group).astype(np.int64) for group in lists]


def _read_ply_body(path: Path, raw: bytes, fmt: str, elements: list[_PlyElement],
                   body_start: int) -> dict[str, Mapping]:
    data: dict[str, Mapping] = {}
    if fmt == "ascii":
        lines = [ln for ln in raw[body_start:].splitlines() if ln.strip()]
        line = 0
        for element in elements:
            data[element.name], line = _ply_ascii_element(path, lines, line, element)
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        body, pos = memoryview(raw)[body_start:], 0
        for element in elements:
            data[element.name], pos = _ply_binary_element(path, body, pos, element, order)
    return data


def save_ply(path: Path, mesh: TriMesh, point_data: dict | None = None, *,
             space: str = "RAS") -> None:
    """Binary PLY through VTK's writer, with a ``comment SPACE=<space>`` line."""
    from core.io.vtk_meshes import vtk, vtk_errors

    writer = vtk.vtkPLYWriter()
    writer.SetFileTypeToBinary()
    writer.AddComment(f"SSM Studio output. SPACE={space}")
    with atomic_path(path) as tmp:
        writer.SetFileName(str(tmp))
        writer.SetInputData(mesh.to_polydata())
        with vtk_errors() as errors:
            ok = writer.Write()
        if errors or not ok:
            raise DataFileError(path, f"could not be written (VTK: "
                                      f"{(errors or ['the writer failed'])[0][:200]})")
