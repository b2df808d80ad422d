"""Point sets: CSV (``x,y,z[,nx,ny,nz]``, world RAS mm) and 3D Slicer's point files.

Read: SSM Studio's CSV; Slicer's control-point tables (.csv/.tsv with ``l,p,s`` (LPS) or
``r,a,s`` (RAS) columns: the header declares the coordinate system), its fiducial lists
(.fcsv) and markups JSON (.mrk.json, or a .json that is one; ``coordinateSystem`` LPS or RAS,
empty read as LPS as Slicer does; points in ``preview`` state skipped with a note).
Written: CSV (RAS) and markups JSON (LPS, as Slicer writes).
"""

from __future__ import annotations

import csv
import json
import os
import warnings
from pathlib import Path
from typing import cast

import numpy as np

from core.errors import DataFileError, DataFileWarning, display_path, require_file, warnings_as_notes, why
from core.io.atomic import atomic_write_json, atomic_write_text
from core.io.limits import coordinate_problem
from core.io.registry import FileFormat, file_suffix, lookup, register
from core.types.pointset import PointSet

POINT_SUFFIXES = (".csv", ".tsv", ".fcsv", ".mrk.json", ".json")


def load_points(path: str | os.PathLike) -> PointSet:
    """Read a point set from CSV (``x,y,z[,nx,ny,nz]`` with header) or Slicer .mrk.json.

    Raises
    ------
    DataFileError
        Not found, unknown format, bad header, non-numeric or NaN values, no points.
    """
    path = require_file(path)
    fmt = lookup(path, "points")
    if fmt is None or fmt.read is None:
        raise DataFileError(path, f"unsupported point-set format '{file_suffix(path)}' (use .csv "
                                  "or .mrk.json)")
    with warnings_as_notes(path):
        pts = cast(PointSet, fmt.read(path))
    if len(pts) == 0:
        raise DataFileError(path, "no points in file")
    problem = coordinate_problem(pts.points, "points")
    if problem:
        raise DataFileError(path, problem)
    if pts.normals is not None and not np.all(np.isfinite(pts.normals)):
        raise DataFileError(path, "normals contain NaN or infinite values")
    return pts


# coordinate columns a table may use, and whether they are LPS (Slicer's export: l,p,s)
_COORDINATE_COLUMNS = ((("x", "y", "z"), "RAS"), (("r", "a", "s"), "RAS"),
                       (("l", "p", "s"), "LPS"))
_FALSE_WORDS = {"0", "false", "no", "n", "f"}


def _read_table(path: Path, delimiter: str | None) -> list[tuple[int, list[str]]]:
    """Non-blank rows (line number, cells) of a CSV/TSV file; comma or tab by the header."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: Excel's BOM
            text = fh.read()
    except UnicodeDecodeError:
        raise DataFileError(path, "not a text CSV file (not UTF-8 text)") from None
    if "\x00" in text:
        raise DataFileError(path, "not a text CSV file (binary data)")
    if delimiter is None:
        first = next((ln for ln in text.splitlines() if ln.strip()), "")
        delimiter = "\t" if "\t" in first and "," not in first else ","
    try:
        reader = csv.reader(text.splitlines(), delimiter=delimiter)
        return [(n, r) for n, r in enumerate(reader, start=1)
                if r and any(c.strip() for c in r)]
    except csv.Error as exc:
        raise DataFileError(path, f"malformed CSV ({exc})") from None


def _load_points_csv(path: Path, delimiter: str | None = None) -> PointSet:
    """A table with a header naming its coordinate columns.

    ``x,y,z`` (world RAS mm, optionally ``nx,ny,nz`` normals) as SSM Studio writes it, or a
    3D Slicer control-point table (``label,l,p,s,defined,...`` in LPS, or ``r,a,s`` in RAS):
    the header declares the coordinate system. Rows whose ``defined`` column is false are
    skipped with a note.
    """
    rows = _read_table(path, delimiter)
    if not rows:
        raise DataFileError(path, "no header line")
    header = [c.strip().lower() for c in rows[0][1]]
    found = next(((names, space) for names, space in _COORDINATE_COLUMNS
                  if all(n in header for n in names)), None)
    if found is None:
        got = ",".join(rows[0][1])[:80]
        raise DataFileError(path, f"header must start with x,y,z (or name Slicer's l,p,s or "
                                  f"r,a,s columns; got '{got}')")
    names, space = found
    columns = [header.index(n) for n in names]
    has_normals = names == ("x", "y", "z") and all(n in header for n in ("nx", "ny", "nz"))
    if has_normals:
        columns += [header.index(n) for n in ("nx", "ny", "nz")]
    defined = header.index("defined") if "defined" in header else None
    need = max(columns) + 1
    values, skipped = [], 0
    for line, row in rows[1:]:
        if defined is not None and len(row) > defined and \
                row[defined].strip().lower() in _FALSE_WORDS:
            skipped += 1
            continue
        if len(row) < need:
            raise DataFileError(path, f"line {line} has {len(row)} values, every row needs "
                                      f"{need} ({','.join(header[:need])})")
        try:
            values.append([float(row[c]) for c in columns])
        except ValueError:
            bad = next(row[c] for c in columns if not _is_float(row[c]))
            raise DataFileError(path, f"non-numeric value '{bad.strip()[:40]}' on line "
                                      f"{line}") from None
    if skipped:
        _note(path, f"{skipped} point{'s' if skipped > 1 else ''} marked not defined "
                    "skipped")
    table = np.array(values, dtype=np.float64).reshape(-1, len(columns))
    flip = _LPS_FLIP if space == "LPS" else np.ones(3)
    return PointSet(table[:, :3] * flip, table[:, 3:6] if has_normals else None)


def _load_points_tsv(path: Path) -> PointSet:
    return _load_points_csv(path, delimiter="\t")


def _note(path: Path, text: str) -> None:
    warnings.warn(DataFileWarning(f"{display_path(path)}: {text}"), stacklevel=3)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


_LPS_FLIP = np.array([-1.0, -1.0, 1.0])
_FCSV_COLUMNS = "id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID"


def _load_points_fcsv(path: Path) -> PointSet:
    """3D Slicer's fiducial CSV (.fcsv): ``# CoordinateSystem = LPS|RAS|0|1`` and
    ``# columns = id,x,y,z,...`` comment lines, then one row per point.

    Files without a CoordinateSystem line come from Slicer before 4.11, which wrote RAS.
    """
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise DataFileError(path, "not a text .fcsv file (not UTF-8 text)") from None
    space, columns, rows = "RAS", _FCSV_COLUMNS.split(","), []
    for number, line in enumerate(text.splitlines(), start=1):
        if line.startswith("#"):
            key, _, value = line[1:].partition("=")
            key, value = key.strip().lower(), value.strip()
            if key == "coordinatesystem":
                named = {"0": "RAS", "ras": "RAS", "1": "LPS", "lps": "LPS"}.get(value.lower())
                if named is None:
                    raise DataFileError(path, f"unknown CoordinateSystem '{value[:20]}' on line "
                                              f"{number} (LPS or RAS)")
                space = named
            elif key == "columns":
                columns = [c.strip().lower() for c in value.split(",")]
            continue
        if line.strip():
            rows.append((number, next(csv.reader([line]))))
    if not all(c in columns for c in "xyz"):
        raise DataFileError(path, "the '# columns' line names no x, y, z columns")
    index = [columns.index(c) for c in "xyz"]
    points = []
    for number, row in rows:
        if len(row) <= max(index):
            raise DataFileError(path, f"line {number} has {len(row)} values, x, y, z are "
                                      f"columns {index[0] + 1}-{index[2] + 1}")
        try:
            points.append([float(row[i]) for i in index])
        except ValueError:
            raise DataFileError(path, f"non-numeric coordinate on line {number}") from None
    flip = _LPS_FLIP if space == "LPS" else np.ones(3)
    return PointSet(np.array(points, dtype=np.float64).reshape(-1, 3) * flip)


def _read_json(path: Path) -> object:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFileError(path, f"not valid JSON ({why(exc)})") from None
    except RecursionError:
        raise DataFileError(path, "JSON nested too deeply to be read") from None


def is_markups_file(path: str | os.PathLike) -> bool:
    """Whether a .json file is a 3D Slicer markups file (not, e.g., a session)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return False
    return b'"markups"' in head or b"markups-schema" in head


def markups_name(path: str | os.PathLike) -> str | None:
    """The name a 3D Slicer markups file gives its (first) node, or None without one
    (markups schema v1.0.3: ``markups[i].name``; older files have none)."""
    try:
        doc = _read_json(Path(path))
    except (DataFileError, OSError):
        return None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if isinstance(markups, list):
        for markup in markups:
            name = markup.get("name") if isinstance(markup, dict) else None
            if isinstance(name, str) and name.strip():
                return name.strip()
    return None


def _load_points_markups(path: Path) -> PointSet:
    doc = _read_json(path)
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(doc, dict) or not isinstance(markups, list) or not markups:
        raise DataFileError(path, "not a Slicer markups file (no 'markups' list)")
    points, normals, previews = [], [], 0
    for markup in markups:
        if not isinstance(markup, dict):
            raise DataFileError(path, "not a Slicer markups file (a markup is not an object)")
        # Slicer reads a missing or empty coordinateSystem as LPS
        system = str(markup.get("coordinateSystem") or "LPS").upper()
        if system not in ("LPS", "RAS"):
            raise DataFileError(path, f"unknown coordinateSystem '{system[:20]}' (LPS or RAS)")
        flip = _LPS_FLIP if system == "LPS" else np.ones(3)
        control_points = markup.get("controlPoints", [])
        if not isinstance(control_points, list):
            raise DataFileError(path, "'controlPoints' is not a list")
        for number, cp in enumerate(control_points, start=1):
            if not isinstance(cp, dict):
                raise DataFileError(path, f"control point {number} is not an object")
            label = str(cp.get("label", number))[:40]
            status = cp.get("positionStatus")
            if status in ("undefined", "missing"):
                continue  # a placeholder Slicer keeps for points not placed yet
            if status == "preview":
                previews += 1  # being placed when the file was saved (often no position)
                continue
            try:
                pos = np.asarray(cp.get("position"), dtype=np.float64)
            except (TypeError, ValueError):
                raise DataFileError(path, f"control point {label} has a non-numeric "
                                          "position") from None
            if pos.shape != (3,):
                raise DataFileError(path, f"control point {label} has no 3D position")
            points.append(pos * flip)
            orient = cp.get("orientation")
            try:
                orient = np.asarray(orient, dtype=np.float64) if orient is not None else None
            except (TypeError, ValueError):
                raise DataFileError(path, f"control point {label} has a non-numeric "
                                          "orientation") from None
            if orient is not None and orient.size == 9:
                # Slicer's orientation is a row-major 3x3 matrix whose columns are the point's
                # axes; the 3rd column is the normal direction (that is how save_points writes it).
                normals.append(orient.reshape(3, 3)[:, 2] * flip)
            else:
                normals.append(None)
    if previews:
        _note(path, f"{previews} control point{'s' if previews > 1 else ''} in 'preview' "
                    "state (being placed, no position) skipped")
    has_normals = bool(points) and all(n is not None for n in normals) and \
        doc.get("ssmStudioNormals", False) is not False
    return PointSet(np.array(points).reshape(-1, 3),
                    np.array(normals) if has_normals else None)


def save_points(path: str | os.PathLike, points: PointSet | np.ndarray,
                normals: np.ndarray | None = None) -> None:
    """Write points (world RAS mm) as CSV or Slicer markups JSON (LPS, as Slicer writes)."""
    path = Path(path)
    pts = points if isinstance(points, PointSet) else PointSet(points, normals)
    if not np.all(np.isfinite(pts.points)) or \
            (pts.normals is not None and not np.all(np.isfinite(pts.normals))):
        raise DataFileError(path, "cannot save points or normals with NaN or infinite values")
    fmt = lookup(path, "points")
    if fmt is None or fmt.write is None:
        raise DataFileError(path, f"unsupported point-set format '{file_suffix(path)}' (use .csv "
                                  "or .mrk.json)")
    fmt.write(path, pts)


def _save_points_csv(path: Path, pts: PointSet) -> None:
    lines = ["x,y,z,nx,ny,nz" if pts.normals is not None else "x,y,z"]
    data = pts.points if pts.normals is None else np.hstack([pts.points, pts.normals])
    lines += [",".join(f"{v:.6f}" for v in row) for row in data]
    atomic_write_text(path, "\n".join(lines) + "\n")


def _save_points_markups(path: Path, pts: PointSet) -> None:
    cps = []
    for i, p in enumerate(pts.points):
        cp = {"id": str(i + 1), "label": f"P-{i + 1}",
              "position": (p * _LPS_FLIP).tolist(), "selected": True, "locked": False,
              "visibility": True, "positionStatus": "defined"}
        if pts.normals is not None:
            n = pts.normals[i] * _LPS_FLIP
            cp["orientation"] = _frame_with_z(n).ravel().tolist()
        cps.append(cp)
    doc = {
        "@schema": "https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/"
                   "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
        "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
                     "controlPoints": cps}],
    }
    if pts.normals is not None:
        doc["ssmStudioNormals"] = "orientation column 3 holds each point's surface normal"
    atomic_write_json(path, doc)


def _frame_with_z(n: np.ndarray) -> np.ndarray:
    """A rotation matrix (3, 3) whose third column is the unit vector along ``n``."""
    z = n / (np.linalg.norm(n) or 1.0)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


register(FileFormat(".csv", "points", "CSV point table", read=_load_points_csv,
                    write=_save_points_csv))
register(FileFormat(".tsv", "points", "tab-separated point table", read=_load_points_tsv))
register(FileFormat(".fcsv", "points", "3D Slicer fiducial list", read=_load_points_fcsv))
for _suffix in (".mrk.json", ".json"):
    register(FileFormat(_suffix, "points", "3D Slicer markups", read=_load_points_markups,
                        write=_save_points_markups))
