"""Remove the pose of corresponded meshes: GPA or transformation synchronisation.

Inputs must be corresponded (same vertex count, vertex i homologous; e.g. the output of
``ssm-studio correspond``), in a format that keeps vertex order (STL inputs are refused).
``--method sync`` (default) makes all pairwise least-squares transforms transitively consistent
with the spectral method of Bernard et al., CVPR 2015 (no reference shape);
``--method sync-sparse`` does the same on the graph of each shape's 10 nearest (time and memory
linear in the number of shapes: thousands of them); ``--method gpa`` runs iterative generalised
Procrustes analysis. ``--transform``: similarity (default), rigid (rotation det +1 and translation),
euclidean (orthogonal, reflections allowed) or affine.

Writes ``DIR/<input name>`` (the aligned mesh) for every input and ``DIR/transforms.json``:
per shape the 4x4 matrix that maps the input into the common frame (homogeneous column
vectors, ``x_aligned = T @ [x, 1]``), its RMS distance to the mean (mm), and any input that was
skipped with the reason.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from core.alignment.transforms import METHODS, TRANSFORMS, align_shapes
from core.cli._options import say_changed_formats
from core.correspondence import mesh_problem
from core.io import TriMesh, atomic_write_json, load_meshes, save_mesh
from core.io.meshes import order_keeping_suffixes
from core.runtime.progress import StderrProgress

COMMAND = "align"
HELP = "align corresponded meshes (GPA or transformation synchronisation) and write the transforms"

REPORT_NAME = "transforms.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("meshes", nargs="+", metavar="MESH", help="corresponded meshes")
    parser.add_argument("--method", choices=METHODS, default="sync",
                        help="sync (default, reference-free), sync-sparse (sync on each shape's "
                             "10 nearest, for thousands of shapes) or gpa")
    parser.add_argument("--transform", choices=TRANSFORMS, default="similarity",
                        help="transformation class (default similarity)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")


def run(args: argparse.Namespace) -> int:
    # corresponded inputs: a format that loses vertex order (STL) is refused by name
    loaded, failures = load_meshes(args.meshes, isolate=True, vertex_order=True)
    meshes: list[tuple[Path, TriMesh]] = []
    for path, mesh in loaded:
        problem = mesh_problem(mesh)
        if problem and "not used by any triangle" not in problem:
            failures[str(path)] = problem
            continue
        meshes.append((path, mesh))
    if meshes:
        counts = [m.n_vertices for _, m in meshes]
        n = max(set(counts), key=counts.count)  # the majority vertex count
        for path, mesh in list(meshes):
            if mesh.n_vertices != n:
                failures[str(path)] = (f"has {mesh.n_vertices} vertices, the others {n}: meshes "
                                       "must be corresponded first (ssm-studio correspond)")
                meshes.remove((path, mesh))
    if len(meshes) < 2:
        raise ValueError("at least 2 usable corresponded meshes are needed"
                         + ("; " + "; ".join(f"{k}: {v}" for k, v in failures.items()) if failures else ""))
    shapes = np.stack([m.vertices for _, m in meshes])
    with StderrProgress("align") as progress:
        result = align_shapes(shapes, method=args.method, transform=args.transform,
                              progress=progress)
    args.out.mkdir(parents=True, exist_ok=True)
    entries = []
    used: set[str] = set()
    for k, (path, mesh) in enumerate(meshes):
        keeps = any(path.name.lower().endswith(s) for s in order_keeping_suffixes())
        name = path.name if keeps else path.name.split(".", 1)[0] + ".vtk"
        if name in used:
            name = f"{k:03d}_{name}"
        used.add(name)
        out_path = args.out / name
        save_mesh(out_path, TriMesh(result.aligned[k], mesh.faces, out_path.stem),
                  vertex_order=True)
        entries.append({"name": str(path), "output": str(out_path),
                        "transform": result.transforms[k].tolist(),
                        "rmsd_to_mean_mm": float(result.rmsd_[k])})
    atomic_write_json(args.out / REPORT_NAME, {
        "method": args.method, "transform": args.transform,
        "convention": "T maps the input mesh into the common frame: x_aligned = T @ [x, y, z, 1] "
                      "(4x4, column vectors)",
        "n_iter": int(result.n_iter_), "converged": bool(result.converged_),
        "shapes": entries, "failures": failures})
    print(f"{args.out}: {len(meshes)} meshes aligned ({args.method}, {args.transform}), "
          f"mean RMS distance to the mean {float(np.mean(result.rmsd_)):.3f} mm")
    for name, problem in failures.items():
        print(f"ssm-studio align: {name}: {problem}", file=sys.stderr)
    say_changed_formats("align", {e["name"]: e["output"] for e in entries})
    return 1 if failures else 0
