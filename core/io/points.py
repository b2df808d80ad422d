"""Point sets: CSV (``x,y,z[,nx,ny,nz]``, world RAS mm) and 3D Slicer markups JSON.

Markups are read in LPS or RAS and written in LPS, as Slicer does.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np

from core.io.atomic import atomic_write_json, atomic_write_text
from core.io.errors import DataFileError, require_file, why
from core.io.registry import FileFormat, file_suffix, lookup, register
from core.types.pointset import PointSet

POINT_SUFFIXES = (".csv", ".mrk.json", ".json")


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
    pts = fmt.read(path)
    if len(pts) == 0:
        raise DataFileError(path, "no points in file")
    if not np.all(np.isfinite(pts.points)):
        raise DataFileError(path, "points contain NaN or infinite coordinates")
    if pts.normals is not None and not np.all(np.isfinite(pts.normals)):
        raise DataFileError(path, "normals contain NaN or infinite values")
    return pts


def _load_points_csv(path: Path) -> PointSet:
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # -sig: Excel's BOM
            rows = [(n, r) for n, r in enumerate(csv.reader(fh), start=1)
                    if r and any(c.strip() for c in r)]
    except UnicodeDecodeError:
        raise DataFileError(path, "not a text CSV file (not UTF-8 text)") from None
    except csv.Error as exc:
        raise DataFileError(path, f"malformed CSV ({exc})") from None
    if not rows:
        raise DataFileError(path, "no header line")
    header = [c.strip().lower() for c in rows[0][1]]
    if header[:3] != ["x", "y", "z"]:
        got = ",".join(rows[0][1])[:80]
        raise DataFileError(path, f"header must start with x,y,z (got '{got}')")
    has_normals = header[3:6] == ["nx", "ny", "nz"]
    ncol = 6 if has_normals else 3
    values = np.empty((len(rows) - 1, ncol), dtype=np.float64)
    for i, (line, row) in enumerate(rows[1:]):
        if len(row) < ncol:
            raise DataFileError(path, f"line {line} has {len(row)} values, every row needs "
                                      f"{ncol} ({','.join(header[:ncol])})")
        try:
            values[i] = [float(c) for c in row[:ncol]]
        except ValueError:
            bad = next(c for c in row[:ncol] if not _is_float(c))
            raise DataFileError(path, f"non-numeric value '{bad.strip()[:40]}' on line "
                                      f"{line}") from None
    return PointSet(values[:, :3], values[:, 3:6] if has_normals else None)


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


_LPS_FLIP = np.array([-1.0, -1.0, 1.0])


def _load_points_markups(path: Path) -> PointSet:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataFileError(path, f"not valid JSON ({why(exc)})") from None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not markups:
        raise DataFileError(path, "not a Slicer markups file (no 'markups' list)")
    points, normals = [], []
    for markup in markups:
        if not isinstance(markup, dict):
            raise DataFileError(path, "not a Slicer markups file (a markup is not an object)")
        system = str(markup.get("coordinateSystem", "LPS")).upper()
        if system not in ("LPS", "RAS"):
            raise DataFileError(path, f"unknown coordinateSystem '{system}' (LPS or RAS)")
        flip = _LPS_FLIP if system == "LPS" else np.ones(3)
        control_points = markup.get("controlPoints", [])
        if not isinstance(control_points, list):
            raise DataFileError(path, "'controlPoints' is not a list")
        for number, cp in enumerate(control_points, start=1):
            if not isinstance(cp, dict):
                raise DataFileError(path, f"control point {number} is not an object")
            label = cp.get("label", number)
            if cp.get("positionStatus") in ("undefined", "missing"):
                continue  # a placeholder Slicer keeps for points not placed yet
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
for _suffix in (".mrk.json", ".json"):
    register(FileFormat(_suffix, "points", "3D Slicer markups", read=_load_points_markups,
                        write=_save_points_markups))
