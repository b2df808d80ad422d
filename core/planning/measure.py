"""Ruler and angle measurements drawn in the slice views, and their files.

A :class:`Measurement` is a ruler (two world points, its length in mm) or an angle (three
points A, vertex B, C: the angle ABC in degrees), with the slice it was drawn on. They are
kept with the session and exported next to the contour points: as a CSV table (one row per
measurement) and as 3D Slicer markups (``.mrk.json``: ``Line`` and ``Angle`` markups in LPS,
as Slicer writes them, with the measured value).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["KINDS", "Measurement", "save_measurements", "measurements_to_json",
           "measurements_from_json"]

KINDS = {"ruler": 2, "angle": 3}
_LPS = np.array([-1.0, -1.0, 1.0])          # RAS <-> LPS
SLICER_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                 "Markups/Resources/Schema/markups-schema-v1.0.3.json#")


@dataclass(frozen=True)
class Measurement:
    """A ruler (2 points) or an angle (3 points: A, vertex, C), world RAS mm.

    ``frame`` and ``depth`` name the slice it was drawn on (e.g. "axial", 12.0).
    """

    kind: str
    points: np.ndarray
    frame: str = ""
    depth: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            msg = f"measurement must be one of {', '.join(KINDS)}; got {self.kind!r}"
            raise ValueError(msg)
        points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        if len(points) != KINDS[self.kind] or not np.all(np.isfinite(points)):
            msg = f"a {self.kind} needs {KINDS[self.kind]} finite 3D points, got {len(points)}"
            raise ValueError(msg)
        object.__setattr__(self, "points", points)

    @property
    def value(self) -> float:
        """Length (mm) of a ruler, angle (degrees, 0-180) of an angle."""
        p = self.points
        if self.kind == "ruler":
            return float(np.linalg.norm(p[1] - p[0]))
        a, b = p[0] - p[1], p[2] - p[1]
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if na < 1e-12 or nb < 1e-12:
            return 0.0
        return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))

    @property
    def unit(self) -> str:
        return "mm" if self.kind == "ruler" else "deg"

    def label(self) -> str:
        return f"{self.value:.1f} mm" if self.kind == "ruler" else f"{self.value:.1f}°"


def measurements_to_json(items: Sequence[Measurement]) -> list[dict[str, Any]]:
    """For session files."""
    return [{"kind": m.kind, "points": m.points.tolist(), "frame": m.frame,
             "depth": float(m.depth)} for m in items]


def measurements_from_json(data: Any) -> list[Measurement]:
    """Read :func:`measurements_to_json`; ValueError naming the bad entry."""
    if data is None:
        return []
    if not isinstance(data, list):
        msg = "measurements: expected a list"
        raise ValueError(msg)
    out = []
    for i, item in enumerate(data):
        try:
            out.append(Measurement(item["kind"], item["points"], str(item.get("frame", "")),
                                   float(item.get("depth", 0.0))))
        except (KeyError, TypeError, ValueError) as exc:
            msg = f"measurement {i + 1}: {exc}"
            raise ValueError(msg) from None
    return out


def _slicer_markup(m: Measurement, index: int) -> dict[str, Any]:
    points = [{"id": str(k + 1), "label": f"{m.kind}-{index + 1}-{k + 1}",
               "position": (p * _LPS).tolist(), "positionStatus": "defined"}
              for k, p in enumerate(m.points)]
    return {"type": "Line" if m.kind == "ruler" else "Angle", "coordinateSystem": "LPS",
            "coordinateUnits": "mm", "name": f"{m.kind}-{index + 1}", "controlPoints": points,
            "measurements": [{"name": "length" if m.kind == "ruler" else "angle",
                              "enabled": True, "value": m.value,
                              "units": "mm" if m.kind == "ruler" else "deg"}]}


def save_measurements(path: str | os.PathLike, items: Sequence[Measurement]) -> Path:
    """Write ``.csv`` (kind, value, unit, slice, points R/A/S) or Slicer ``.mrk.json``."""
    from core.io.atomic import atomic_write_text

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.name.lower().endswith(".mrk.json"):
        document = {"@schema": SLICER_SCHEMA,
                    "markups": [_slicer_markup(m, i) for i, m in enumerate(items)]}
        atomic_write_text(path, json.dumps(document, indent=2))
        return path
    if path.suffix.lower() != ".csv":
        msg = f"{path}: measurements are written as .csv or .mrk.json"
        raise ValueError(msg)
    rows = ["kind,value,unit,frame,depth_mm,r1,a1,s1,r2,a2,s2,r3,a3,s3"]
    for m in items:
        coords = m.points.reshape(-1).tolist() + [""] * (9 - m.points.size)
        rows.append(",".join([m.kind, f"{m.value:.4f}", m.unit, m.frame, f"{m.depth:.3f}",
                              *[c if c == "" else f"{c:.4f}" for c in coords]]))
    atomic_write_text(path, "\n".join(rows) + "\n")
    return path
