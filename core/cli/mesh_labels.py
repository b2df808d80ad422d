"""Turn one label of label maps into closed training surfaces (world RAS mm).

For each LABELMAP (NIfTI, NRRD, Slicer .seg.nrrd, MetaImage, ...), the label given by number
or by name (a Slicer segment name in a .seg.nrrd, else a FreeSurfer colour-table name such as
Left-Caudate; --segment NAME: a Slicer segment by name or ID, also from a layered .seg.nrrd
whose segments overlap) becomes ONE closed, 2-manifold, consistently oriented surface at the label's
genus, also for manual segmentations (``core.correspondence.mesh_labels``): the largest face-connected piece
is kept (the islands dropped are counted), cavities filled, edge- and corner-only voxel
contacts resolved (the mask made well-composed), handles made by one-voxel bridges or tunnels
removed; then Surface Nets, windowed-sinc smoothing that removes the staircase without
shrinking, the image's voxel -> RAS affine, and a topology-keeping remesh to an even density
of about --vertices vertices (0: the Surface Nets resolution), checked (every edge on two
triangles, every vertex one fan, Euler characteristic 2 - 2 genus). Writes
``DIR/<file stem>_<label>.vtk`` per input and ``DIR/mesh_labels.json`` (per input: output,
vertices, voxels, genus, islands and island_voxels dropped, the voxels changed by each repair,
the topology check; or the error). A missing file, a label that is missing or empty in a file,
or one of which no closed surface can be made is reported in one line with the file and the
label; the other inputs are still done. Exit code 0 when all succeeded, 1 when some failed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from core.correspondence.mesh_labels import label_map_surface, repair_note
from core.io import atomic_write_json, save_mesh

COMMAND = "mesh-labels"
HELP = "one label of label maps -> closed surfaces in world mm (training meshes)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("label_maps", nargs="+", metavar="LABELMAP", help="label map files")
    chosen = parser.add_mutually_exclusive_group(required=True)
    chosen.add_argument("--label",
                        help="label number, or name (FreeSurfer colour table, Slicer segment)")
    chosen.add_argument("--segment", metavar="NAME",
                        help="a 3D Slicer segment by name or ID (.seg.nrrd inputs only; "
                             "overlapping segments of layered files too)")
    parser.add_argument("--vertices", type=int, default=2000,
                        help="vertex count of each surface (default %(default)s; 0: keep the "
                             "Surface Nets resolution)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")


def run(args: argparse.Namespace) -> int:
    if args.vertices < 0 or 0 < args.vertices < 20:
        raise ValueError(f"--vertices must be 0 or at least 20, got {args.vertices}")
    wanted = args.label if args.segment is None else args.segment
    if args.segment is not None:
        not_seg = [p for p in args.label_maps if not str(p).lower().endswith(".seg.nrrd")]
        if not_seg:
            raise ValueError(f"{not_seg[0]}: --segment takes a segment of a 3D Slicer "
                             ".seg.nrrd file; use --label for other label maps")
    args.out.mkdir(parents=True, exist_ok=True)
    entries, n_ok = [], 0
    for path in args.label_maps:
        start = time.perf_counter()
        info: dict = {}
        try:
            mesh = label_map_surface(path, wanted, n_vertices=args.vertices or None, info=info)
        except (ValueError, OSError) as exc:  # DataFileError and LabelError are ValueErrors
            message = " ".join(str(exc).split())
            print(f"ssm-studio {COMMAND}: {message}", file=sys.stderr)
            entries.append({"input": str(path), "ok": False, "error": message})
            continue
        out_path = args.out / f"{mesh.name}.vtk"
        save_mesh(out_path, mesh)
        n_ok += 1
        entries.append({"input": str(path), "ok": True, "output": str(out_path),
                        "vertices": int(mesh.n_vertices), "faces": int(len(mesh.faces)),
                        "seconds": round(time.perf_counter() - start, 3), **info})
        print(f"{out_path}: {mesh.n_vertices} vertices, genus {info['genus']}{repair_note(info)}")
    atomic_write_json(args.out / "mesh_labels.json",
                      {"label": wanted, "segment": args.segment is not None, "inputs": entries})
    return 0 if n_ok == len(args.label_maps) else 1
