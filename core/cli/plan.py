"""Compute the DBS plan report of a saved session, headless (as the GUI's Export plan does).

Reads a session written by the segmentation workspace (its structures' models, fitted
coefficients and poses, and the ``info.planning`` block: AC, PC, midline point, per structure
a target and an entry point) and writes ``--out plan.json``: the structure table (volume mm^3,
centroid in world and AC-PC coordinates), the AC-PC frame, and for each trajectory its length,
ring and arc angles and where it enters and leaves every structure. ``--export DIR`` also
writes every plan file the GUI writes (structure table CSV, multi-label map as .seg.nrrd and
NIfTI + ITK-SNAP labels on the session's image grid, Slicer markups, one mesh per structure).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from core.io import load_volume
from core.planning.report import export_plan, plan_from_session, plan_report, save_plan_report
from core.session.document import load_session

COMMAND = "plan"
HELP = "compute the plan report (structures, AC-PC, trajectories) of a saved session"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--session", required=True, help="session file (.json) from the workspace")
    parser.add_argument("--out", required=True, type=Path, help="plan report (.json)")
    parser.add_argument("--export", type=Path, default=None, metavar="DIR",
                        help="also write every plan file (label maps, markups, meshes) into DIR")


def run(args: argparse.Namespace) -> int:
    session = load_session(args.session)
    try:
        structures, frame = plan_from_session(session)
    except ValueError as exc:
        raise ValueError(f"{args.session}: {exc}") from None
    if not structures:
        raise ValueError(f"{args.session}: no structure has a model: nothing to plan")
    image = session.image_path.name if session.image_path else None
    report = plan_report(structures, frame, image)
    save_plan_report(args.out, report)
    if args.export is not None:
        volume = load_volume(session.image_path) if session.image_path else None
        export_plan(args.export, structures, volume, frame, image)
    n_traj = sum("trajectory" in row for row in report["structures"])
    acpc = "with" if frame is not None else "without"
    print(f"{args.out}: {len(structures)} structure(s), {n_traj} trajectory(ies), {acpc} AC-PC frame")
    return 0
