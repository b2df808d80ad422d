"""Compute the DBS plan report of a saved session, headless (as the GUI's Export plan does).

Reads a session written by the segmentation workspace (its structures' models, fitted
coefficients and poses, and the ``info.planning`` block: AC, PC, midline point, per structure
a target and an entry point) and writes ``--out plan.json``: the structure table (volume mm^3,
centroid in world and AC-PC coordinates), the AC-PC frame, and for each trajectory its length,
ring and arc angles, where it enters and leaves every structure, the distance to every
structure along the path and the plan's warnings (target outside its structure, the path
crossing or grazing another structure or the ventricles). ``--lead TYPE`` puts a lead on every
trajectory (tip at the target, or ``--lead-depth MM`` past it) and reads out each contact in
world, AC-PC and voxel coordinates with the structure it lies in. ``--export DIR`` also
writes every plan file the GUI writes (structure table CSV, multi-label map as .seg.nrrd and
NIfTI + ITK-SNAP labels on the session's image grid, Slicer markups, one mesh per structure)
and, when the session's image is a DICOM series, DICOM SEG and RTSTRUCT referencing it.
``--json`` prints the report on stdout instead of the summary lines.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from core.io import load_volume
from core.io.atomic import json_default
from core.planning.frames import template_ventricles
from core.planning.lead import LEAD_TYPES, format_contact
from core.planning.report import (
    LeadChoice,
    export_plan,
    plan_from_session,
    plan_report,
    save_plan_report,
    template_to_image,
)
from core.session.document import load_session

COMMAND = "plan"
HELP = "compute the plan report (structures, AC-PC, trajectories, lead, warnings) of a saved session"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--session", required=True, help="session file (.json) from the workspace")
    parser.add_argument("--out", required=True, type=Path, help="plan report (.json)")
    parser.add_argument("--export", type=Path, default=None, metavar="DIR",
                        help="also write every plan file (label maps, markups, meshes; DICOM "
                             "SEG and RTSTRUCT when the image is a DICOM series) into DIR")
    parser.add_argument("--lead", choices=sorted(LEAD_TYPES), default=None, metavar="TYPE",
                        help="put this lead on every trajectory: " + ", ".join(sorted(LEAD_TYPES)))
    parser.add_argument("--lead-depth", type=float, default=0.0, metavar="MM",
                        help="lead tip this far past the target along the trajectory "
                             "(negative: short of it; default 0: tip at the target)")
    parser.add_argument("--lead-rotation", type=float, default=0.0, metavar="DEG",
                        help="turn of a directional lead's segments about its axis from anterior")
    parser.add_argument("--no-ventricles", action="store_true",
                        help="do not check the trajectories against the template's ventricles")
    parser.add_argument("--json", action="store_true", help="print the report (JSON) on stdout")


def _dicom_files(image_path: Path | None) -> list[Path] | None:
    """The source series' files when the session's image is a DICOM series, else None."""
    if image_path is None:
        return None
    from core.io.dicom import choose_series, is_dicom_file

    path = Path(image_path)
    if path.is_dir() or (path.is_file() and is_dicom_file(path)):
        return list(choose_series(path).files)
    return None


def run(args: argparse.Namespace) -> int:
    session = load_session(args.session)
    try:
        structures, frame = plan_from_session(session)
    except ValueError as exc:
        raise ValueError(f"{args.session}: {exc}") from None
    if not structures:
        raise ValueError(f"{args.session}: no structure has a model: nothing to plan")
    image = session.image_path.name if session.image_path else None
    volume = load_volume(session.image_path) if session.image_path else None
    lead = LeadChoice(args.lead, args.lead_depth, args.lead_rotation) if args.lead else None
    avoid: tuple = ()
    placement = None if args.no_ventricles else template_to_image(session)
    if placement is not None:
        avoid = (template_ventricles(placement),)
    report = plan_report(structures, frame, image, lead=lead, volume=volume, avoid=avoid)
    save_plan_report(args.out, report)
    if args.export is not None:
        export_plan(args.export, structures, volume, frame, image, lead=lead, avoid=avoid,
                    dicom_series=_dicom_files(session.image_path))
    if args.json:
        json.dump(report, sys.stdout, default=json_default, indent=1)
        print()
        return 0
    n_traj = sum("trajectory" in row for row in report["structures"])
    acpc = "with" if frame is not None else "without"
    print(f"{args.out}: {len(structures)} structure(s), {n_traj} trajectory(ies), {acpc} AC-PC frame")
    for row in report["structures"]:
        traj = row.get("trajectory")
        if traj is None:
            continue
        print(f"{row['name']}: trajectory {traj['length_mm']:.1f} mm")
        for contact in traj.get("lead", {}).get("contacts", []):
            print("  " + format_contact(contact))
    for warning in report["warnings"]:
        print(f"WARNING ({warning['trajectory']}): {warning['message']}")
    if placement is None and not args.no_ventricles:
        print("ventricles not checked: no structure of the session was placed from the template")
    return 0
