"""The DBS plan of one patient as data and files: report, structure table, label map, markups.

A plan is the patient's fitted structures (world RAS surfaces), the AC-PC landmarks and, per
structure, a target and an entry point (``core.planning.frames`` has the geometry). This module turns
it into what planning and navigation tools read:

- a JSON report (structure table, AC-PC frame, trajectories with length, ring/arc angles and
  where each trajectory enters and leaves every structure);
- a CSV structure table (volume mm^3, centroid in world RAS and AC-PC);
- a multi-label map on the image grid, one label value per structure: as a 3D Slicer
  Segmentation (``.seg.nrrd``, names and colours) and as NIfTI with an ITK-SNAP label
  description file next to it (names and colours; ITK-SNAP's documented text format);
- the plan as 3D Slicer markups: a point list (AC, PC, midline, targets, entries; LPS as
  Slicer writes) and one line markup per trajectory, in a single ``.mrk.json`` file as Slicer's
  markups schema allows;
- per trajectory, with a lead type (``core.planning.lead``), the contacts' positions and structures, and
  the plan's warnings (``core.planning.frames.trajectory_warnings``: target outside its structure, the
  path crossing or grazing another structure or the ventricles);
- when the image came from a DICOM series, every structure as DICOM SEG and RTSTRUCT
  referencing that series (``core.io.dicom_export``).
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.errors import DataFileError
from core.geometry.segmentation import voxelize
from core.io import TriMesh, atomic_write_json, atomic_write_text, save_mesh
from core.io.model_library import structure_info
from core.planning.frames import (
    ACPCFrame,
    Trajectory,
    anchored_point,
    anchored_point_weights,
    path_distances,
    structure_row,
    trajectory_warnings,
    volume_centroid,
)

REPORT_FORMAT = "ssm-studio-plan"
REPORT_VERSION = 1
_LPS = np.array([-1.0, -1.0, 1.0])
MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/main/Modules/Loadable/"
                  "Markups/Resources/Schema/markups-schema-v1.0.3.json#")


@dataclass
class PlannedStructure:
    """One fitted structure of the plan (world RAS mm)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float] = (0.95, 0.65, 0.10)
    target: np.ndarray | None = None   # world; None: no target planned for this structure
    entry: np.ndarray | None = None    # world; with a target, defines the trajectory
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def trajectory(self) -> Trajectory | None:
        if self.target is None or self.entry is None:
            return None
        return Trajectory(self.entry, self.target)


def model_target(model_mean: np.ndarray, faces: np.ndarray, fitted_model_frame: np.ndarray,
                 stored_target=None) -> np.ndarray:
    """Default target in the model frame that moves with the fitted surface.

    With a target stored in the model file (model frame, relative to the mean shape) it is
    anchored to the mean's nearest vertices and carried to the fitted shape; otherwise it is
    the fitted shape's volume centroid. ``fitted_model_frame`` (N, 3) is the fitted instance
    before the pose; map the result to world with the fit's pose.
    """
    if stored_target is None:
        return volume_centroid(fitted_model_frame, faces)
    idx, w = anchored_point_weights(model_mean, stored_target)
    return anchored_point(fitted_model_frame, idx, w)


def planned_structure(name: str, model, coef=None, pose=None, color=None, target=None,
                      entry=None) -> PlannedStructure:
    """A fitted structure of the plan from its model, coefficients and pose (model -> world).

    Without a ``target``, the model's default target (:func:`model_target`) on the fitted shape.
    """
    pose = model.world_transform if pose is None else np.asarray(pose, dtype=np.float64)
    local = model.instance(coef)
    world = local @ pose[:3, :3].T + pose[:3, 3]
    info = structure_info(model)
    if target is None:
        t = model_target(model.mean, model.faces, local, info.target)
        target = t @ pose[:3, :3].T + pose[:3, 3]
    return PlannedStructure(name, world, model.faces, tuple(color or info.color),
                            target=np.asarray(target, dtype=np.float64),
                            entry=None if entry is None else np.asarray(entry, dtype=np.float64))


def plan_from_session(session) -> tuple[list[PlannedStructure], ACPCFrame | None]:
    """The structures and AC-PC frame of a saved session (``core.session.document.Session``).

    Reads the session's structures (``session.structures`` when it has several, else its one
    model at the top level) and the ``info.planning`` block written by the workspace
    (``ac``, ``pc``, ``midline`` and per structure index a ``target`` and an ``entry``).
    Raises ValueError (naming what is wrong) for a session without a model or a bad block.
    """
    from core.io import load_model

    records = getattr(session, "structures", None) or []
    if not records:
        if session.model_path is None:
            raise ValueError("the session has no model: nothing to plan")
        records = [{"name": "", "model": session.model_path, "coef": session.coef,
                    "pose": session.pose}]
    planning = session.info.get("planning") or {}
    if not isinstance(planning, dict):
        raise ValueError("info.planning is not a JSON object")
    per = {}
    for item in planning.get("structures", []):
        index = int(item.get("structure", -1))
        if not 0 <= index < len(records):
            raise ValueError(f"info.planning refers to structure {index + 1}, the session has "
                             f"{len(records)}")
        per[index] = item
    structures = []
    for i, rec in enumerate(records):
        path = _field(rec, "model_path") or _field(rec, "model")
        if path is None:
            continue
        model = load_model(path)
        name, side = _field(rec, "name"), _field(rec, "side")
        # as the workspace labels its structures: "name (side)"
        name = (f"{name} ({side})" if side else name) if name else structure_info(model, path).label
        color = _field(rec, "color")
        item = per.get(i, {})
        structures.append(planned_structure(name, model, _field(rec, "coef"), _field(rec, "pose"),
                                            tuple(color) if color is not None else None,
                                            item.get("target"), item.get("entry")))
    frame = None
    if all(planning.get(k) is not None for k in ("ac", "pc", "midline")):
        frame = ACPCFrame.from_points(planning["ac"], planning["pc"], planning["midline"])
    return structures, frame


def template_to_image(session) -> np.ndarray | None:
    """Template world -> image world (4x4) of a session whose library models were placed
    automatically or by hand: ``placement @ inv(model.world_transform)`` of the first
    structure with a placement and a model in the demo template's space (None without one).
    ``session`` has ``structures`` (session records, or the GUI's structures whose ``model``
    is the loaded :class:`~core.models.shape_model.ShapeModel`, read from its path otherwise)."""
    from core.io import load_model
    from core.io.model_library import MNI_TEMPLATE_SPACE
    from core.models.shape_model import ShapeModel

    for rec in getattr(session, "structures", None) or []:
        placement = _field(rec, "placement")
        path = _field(rec, "model_path") or _field(rec, "model")
        if placement is None or path is None:
            continue
        loaded = _field(rec, "model")
        model = loaded if isinstance(loaded, ShapeModel) else load_model(path)
        if structure_info(model, path).template_space == MNI_TEMPLATE_SPACE:
            return np.asarray(placement, dtype=np.float64) @ np.linalg.inv(model.world_transform)
    return None


def _field(record, key: str):
    """A structure record's field: a dict (session document) or an object with attributes."""
    return record.get(key) if isinstance(record, dict) else getattr(record, key, None)


def _vec(a) -> list[float] | None:
    return None if a is None else [float(v) for v in np.asarray(a).reshape(3)]


@dataclass(frozen=True)
class LeadChoice:
    """The lead put on every trajectory of a plan: type key, tip depth past the target (mm),
    rotation of directional segments (degrees); see ``core.planning.lead.place_lead``."""

    lead: str
    depth_mm: float = 0.0
    rotation_deg: float = 0.0


def trajectory_report(traj: Trajectory, structures: list[PlannedStructure],
                      frame: ACPCFrame | None, extend_mm: float = 10.0, *,
                      own: PlannedStructure | None = None, lead: LeadChoice | None = None,
                      volume=None, avoid: tuple = ()) -> dict[str, Any]:
    """Length, angles and per-structure (enter, leave) depths of one trajectory; its
    warnings and the distance to every structure along the path (``own``: the trajectory's
    structure; ``avoid``: further surfaces checked, e.g. the ventricles); with ``lead``, the
    lead's contacts (``core.planning.lead.lead_report``)."""
    out: dict[str, Any] = {"entry": _vec(traj.entry), "target": _vec(traj.target),
                           "length_mm": traj.length, "direction": _vec(traj.direction)}
    if frame is not None:
        out["entry_acpc"] = _vec(frame.to_acpc(traj.entry))
        out["target_acpc"] = _vec(frame.to_acpc(traj.target))
        out.update(traj.angles(frame))
    out["crossings"] = [
        {"structure": s.name, "enter_mm": a, "leave_mm": b}
        for s in structures for a, b in traj.segments_inside(s.vertices, s.faces, extend_mm)]
    out["crossings"].sort(key=lambda c: c["enter_mm"])
    checked = list(structures) + list(avoid)
    out["path_distances"] = path_distances(traj, [s for s in checked if s is not own])
    out["warnings"] = trajectory_warnings(traj, own, checked)
    if lead is not None:
        from core.planning.lead import lead_report, place_lead

        placed = place_lead(traj, lead.lead, lead.depth_mm, lead.rotation_deg)
        out["lead"] = lead_report(placed, structures, frame, volume)
    return out


def plan_report(structures: list[PlannedStructure], frame: ACPCFrame | None = None,
                image: str | None = None, *, lead: LeadChoice | None = None, volume=None,
                avoid: tuple = ()) -> dict[str, Any]:
    """The whole plan as a JSON-ready dict (see the module docstring); ``warnings`` lists
    every trajectory's warnings with the structure whose trajectory it is."""
    doc: dict[str, Any] = {"format": REPORT_FORMAT, "format_version": REPORT_VERSION,
                           "units": "mm", "coordinates": "world RAS"}
    if image:
        doc["image"] = image
    if frame is not None:
        doc["acpc"] = {"ac": _vec(frame.ac), "pc": _vec(frame.pc), "midline": _vec(frame.midline),
                       "mcp": _vec(frame.origin), "ac_pc_distance_mm": frame.ac_pc_distance,
                       "world_to_acpc": frame.matrix().tolist()}
    rows = []
    for s in structures:
        row = structure_row(s.name, s.vertices, s.faces, frame)
        row["color"] = list(s.color)
        if s.target is not None:
            row["target_world"] = _vec(s.target)
            if frame is not None:
                row["target_acpc"] = _vec(frame.to_acpc(s.target))
        traj = s.trajectory
        if traj is not None:
            row["trajectory"] = trajectory_report(traj, structures, frame, own=s, lead=lead,
                                                  volume=volume, avoid=avoid)
        rows.append(row)
    doc["structures"] = rows
    doc["checked_surfaces"] = [a.name for a in avoid]
    doc["warnings"] = [{"trajectory": row["name"], **w} for row in rows
                       for w in row.get("trajectory", {}).get("warnings", [])]
    return doc


def save_plan_report(path: str | os.PathLike, report: dict[str, Any]) -> None:
    atomic_write_json(path, report)


def structure_table_csv(report: dict[str, Any]) -> str:
    """The structure table of a report as CSV text (one row per structure)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    header = ["name", "volume_mm3", "centroid_r", "centroid_a", "centroid_s",
              "centroid_lat", "centroid_ap", "centroid_vert"]
    writer.writerow(header)
    for row in report["structures"]:
        acpc = row.get("centroid_acpc") or ["", "", ""]
        writer.writerow([row["name"], f"{row['volume_mm3']:.1f}",
                         *(f"{v:.3f}" for v in row["centroid_world"]),
                         *(f"{v:.3f}" if v != "" else "" for v in acpc)])
    return buf.getvalue()


def save_structure_table(path: str | os.PathLike, report: dict[str, Any]) -> None:
    atomic_write_text(path, structure_table_csv(report))


def contacts_csv(report: dict[str, Any]) -> str:
    """Every lead contact of a report as CSV (one row per trajectory and contact): centre in
    world RAS, AC-PC and voxel coordinates, the structure it lies in and the signed distance
    to the nearest structure's surface (negative inside)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["trajectory", "lead", "contact", "r", "a", "s", "lat", "ap", "vert",
                     "i", "j", "k", "structure", "nearest_structure", "distance_mm"])
    for row in report["structures"]:
        lead = row.get("trajectory", {}).get("lead")
        for c in (lead or {}).get("contacts", []):
            acpc = c.get("acpc") or ["", "", ""]
            voxel = c.get("voxel") or ["", "", ""]
            writer.writerow([row["name"], lead["type"], c["contact"],
                             *(f"{v:.3f}" for v in c["world"]),
                             *(f"{v:.3f}" if v != "" else "" for v in acpc),
                             *(f"{v:.3f}" if v != "" else "" for v in voxel),
                             c.get("structure") or "", c.get("nearest_structure") or "",
                             "" if c.get("distance_mm") is None else f"{c['distance_mm']:.3f}"])
    return buf.getvalue()


def multi_label_map(structures: list[PlannedStructure], volume) -> np.ndarray:
    """uint8 label map on ``volume``'s grid: structure i gets label i + 1.

    Where two surfaces overlap, the voxel keeps the earlier structure's label (the structure
    list's order is the user's priority), so every voxel has one label.
    """
    if len(structures) > 255:
        raise ValueError("a uint8 label map holds at most 255 structures")
    labels = np.zeros(volume.shape, dtype=np.uint8)
    for i, s in enumerate(structures):
        mask = voxelize(s.vertices, s.faces, volume) > 0
        labels[mask & (labels == 0)] = i + 1
    return labels


def itksnap_label_description(structures: list[PlannedStructure]) -> str:
    """ITK-SNAP's label description text: 'IDX R G B A VIS MSH "LABEL"', label 0 clear."""
    lines = ["################################################",
             "# ITK-SnAP Label Description File (written by SSM Studio)",
             "# IDX   -R-  -G-  -B-  -A--  VIS MSH  LABEL",
             "################################################",
             '    0     0    0    0        0  0  0    "Clear Label"']
    for i, s in enumerate(structures, start=1):
        r, g, b = (int(round(255 * c)) for c in s.color)
        name = s.name.replace('"', "'")
        lines.append(f"{i:5d} {r:5d} {g:4d} {b:4d}        1  1  1    \"{name}\"")
    return "\n".join(lines) + "\n"


def _control_point(index: int, label: str, world) -> dict[str, Any]:
    return {"id": str(index), "label": label,
            "position": (np.asarray(world, dtype=np.float64) * _LPS).tolist(),
            "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0, -0.0, 0.0, 0.0, 1.0],
            "selected": True, "locked": False, "visibility": True, "positionStatus": "defined"}


def plan_markups(structures: list[PlannedStructure], frame: ACPCFrame | None) -> dict[str, Any]:
    """3D Slicer markups document: the plan's points as a point list, each trajectory a line."""
    points: list[tuple[str, np.ndarray]] = []
    if frame is not None:
        points += [("AC", frame.ac), ("PC", frame.pc), ("Midline", frame.midline)]
    for s in structures:
        if s.target is not None:
            points.append((f"{s.name} target", s.target))
        if s.entry is not None:
            points.append((f"{s.name} entry", s.entry))
    markups: list[dict[str, Any]] = [{
        "type": "Fiducial", "name": "SSM Studio plan", "coordinateSystem": "LPS",
        "coordinateUnits": "mm",
        "controlPoints": [_control_point(i, label, p) for i, (label, p) in
                          enumerate(points, start=1)]}]
    for s in structures:
        traj = s.trajectory
        if traj is None:
            continue
        markups.append({
            "type": "Line", "name": f"{s.name} trajectory", "coordinateSystem": "LPS",
            "coordinateUnits": "mm",
            "controlPoints": [_control_point(1, "entry", traj.entry),
                              _control_point(2, "target", traj.target)]})
    return {"@schema": MARKUPS_SCHEMA, "markups": markups}


def save_plan_markups(path: str | os.PathLike, structures: list[PlannedStructure],
                      frame: ACPCFrame | None) -> None:
    atomic_write_json(path, plan_markups(structures, frame))


def all_structures_outputs(folder: str | os.PathLike, structures: list[PlannedStructure],
                           volume, stem: str = "plan", dicom_series: list | None = None,
                           meshes: bool = True) -> list[Path]:
    """The files :func:`export_all_structures` would write with these arguments (so a caller
    can ask before overwriting an earlier export)."""
    folder = Path(folder)
    names = []
    if volume is not None:
        names += [f"{stem}_labels.seg.nrrd", f"{stem}_labels.nii.gz", f"{stem}_labels.txt"]
        if dicom_series:
            names += [f"{stem}_structures.seg.dcm", f"{stem}_structures.rtstruct.dcm"]
    if meshes:
        names += [f"{stem}_{i:02d}_{_safe_name(s.name, i)}.vtk"
                  for i, s in enumerate(structures, start=1)]
    return [folder / name for name in names]


def _safe_name(name: str, index: int) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_") or f"structure{index}"


def export_all_structures(folder: str | os.PathLike, structures: list[PlannedStructure],
                          volume, stem: str = "plan", dicom_series: list | None = None,
                          meshes: bool = True, progress=None, notes: list[str] | None = None) -> list[Path]:
    """Every structure at once (the GUI's *Export all*): on ``volume``'s grid the multi-label
    map as ``<stem>_labels.seg.nrrd`` (3D Slicer: names, colours) and ``<stem>_labels.nii.gz``
    + ``<stem>_labels.txt`` (ITK-SNAP labels); with ``dicom_series`` (the source series' files,
    when the image came from DICOM) ``<stem>_structures.seg.dcm`` (DICOM SEG) and
    ``<stem>_structures.rtstruct.dcm`` (RTSTRUCT) referencing it; with ``meshes`` one surface
    per structure, ``<stem>_NN_<name>.vtk``. Returns the paths written. ``progress(fraction,
    message)`` (``core.runtime.progress``) is called before each file; cancelling through it
    stops before the next file. With ``notes`` (a list), a source series the DICOM objects
    cannot reference (:class:`core.errors.DataFileError`, e.g. no Frame of Reference UID) adds
    a one-line note there and the other files are still written; without, it raises."""
    from core.io import save_volume
    from core.io.nrrd import Segment, write_segmentation

    report = progress or (lambda fraction, message="": None)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    if volume is not None:
        report(0.0, "label map of every structure")
        label_map = multi_label_map(structures, volume)
        report(0.5, "3D Slicer segmentation and NIfTI label map")
        segmentation = folder / f"{stem}_labels.seg.nrrd"
        write_segmentation(segmentation, label_map, volume.affine,
                           [Segment(i + 1, s.name, s.color) for i, s in enumerate(structures)])
        labels = folder / f"{stem}_labels.nii.gz"
        save_volume(labels, label_map, volume.affine)
        names = folder / f"{stem}_labels.txt"
        atomic_write_text(names, itksnap_label_description(structures))
        written += [segmentation, labels, names]
        if dicom_series:
            from core.io.dicom_export import ExportStructure, export_structures_dicom

            report(0.7, "DICOM SEG and RTSTRUCT")
            exports = [ExportStructure(s.name, s.color, s.vertices, s.faces) for s in structures]
            try:
                written += export_structures_dicom(folder, exports, label_map, volume.affine,
                                                   list(dicom_series), stem=f"{stem}_structures")
            except DataFileError as exc:
                if notes is None:
                    raise
                notes.append(f"DICOM SEG and RTSTRUCT not written: {exc}")
    if meshes:
        report(0.9, "surface meshes")
        for i, s in enumerate(structures, start=1):
            safe = _safe_name(s.name, i)
            path = folder / f"{stem}_{i:02d}_{safe}.vtk"
            save_mesh(path, TriMesh(s.vertices, s.faces, safe))
            written.append(path)
    return written


def export_plan(folder: str | os.PathLike, structures: list[PlannedStructure], volume,
                frame: ACPCFrame | None, image: str | None = None,
                stem: str = "plan", meshes: bool = True, *, lead: LeadChoice | None = None,
                avoid: tuple = (), dicom_series: list | None = None) -> list[Path]:
    """Write every plan file into ``folder``; returns the paths written.

    ``<stem>.json`` (report), ``<stem>_structures.csv``, ``<stem>.mrk.json`` (markups) and,
    with an image volume, the multi-label map twice: ``<stem>_labels.seg.nrrd`` (a 3D Slicer
    Segmentation with each structure's name and colour) and ``<stem>_labels.nii.gz`` +
    ``<stem>_labels.txt`` (ITK-SNAP label descriptions); with ``meshes``, one surface per
    structure, ``<stem>_NN_<name>.vtk`` (world RAS, ``SPACE=RAS`` in the header); with
    ``dicom_series`` also DICOM SEG and RTSTRUCT (:func:`export_all_structures`). ``lead`` and
    ``avoid`` go into the report (:func:`plan_report`); with ``lead`` also
    ``<stem>_contacts.csv`` (:func:`contacts_csv`).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    report = plan_report(structures, frame, image, lead=lead, volume=volume, avoid=avoid)
    written = [folder / f"{stem}.json", folder / f"{stem}_structures.csv",
               folder / f"{stem}.mrk.json"]
    save_plan_report(written[0], report)
    save_structure_table(written[1], report)
    save_plan_markups(written[2], structures, frame)
    if lead is not None:
        written.append(folder / f"{stem}_contacts.csv")
        atomic_write_text(written[-1], contacts_csv(report))
    return written + export_all_structures(folder, structures, volume, stem, dicom_series, meshes)
