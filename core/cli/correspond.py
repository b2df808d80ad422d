"""Establish dense correspondences between training meshes (Bernard et al., SPIE MI 2016).

Every input mesh is re-expressed with the vertices and faces of one reference mesh: rigid and
nonrigid Coherent Point Drift (rustcpd engine), a linear assignment on the CPD posterior, and
fairing on the target surface (``core.correspondence``), after grooming every input
(``core.correspondence.grooming``: largest piece kept, small holes filled, orientation fixed, remeshed to a
common ``--vertices``; each step reported per shape and switchable off) and followed by
``--refine`` groupwise passes to the mean shape; the remesh and each pass are kept only
where the model's leave-one-out generalisation against the raw inputs says they help
(``core.correspondence.safeguard``; ``--no-safeguard`` keeps them regardless).
``--reference auto`` takes the most typical input (coarse, repaired and unrepresentative ones
excluded; the reason is in the report), or the most compact of ``--n-references``
candidates; ``--reference PATH`` uses that mesh (it must be one closed surface).

Writes ``DIR/<input name>`` for every input that succeeded (same format as the input; .vtk for
formats that cannot be written or cannot keep vertex order, such as STL: the report's
``output`` says which), all with the reference's faces and vertex i homologous across files,
and ``DIR/correspondence.json``: the chosen reference, per-shape residual (symmetric mean
surface distance to the input, mm), timings, parameters, and every failed input with its reason.
Inputs that cannot be read or used are reported and skipped; the others are still written
(each file is read in a child process, so a reader crash on a damaged file costs that file only).
Exit code 0 when all succeeded, 1 when some failed.

Each output is written as soon as it is final (during the last refinement pass), so a run
stopped by SIGINT or SIGTERM leaves every finished shape and a ``correspondence.json`` saying
``"interrupted": "SIGINT"`` (or ``"SIGTERM"``), ``"complete": false`` and which shapes were
written; it exits 130 (143). Stopped after the reference-based pass but before a shape's
refinement finished, that shape's reference-based result is in ``DIR/provisional/`` (each is
written there as soon as known and removed when the shape's final output is written; listed
as ``"provisional"`` in the report: usable, but not refined groupwise). ``--jobs N`` runs the
per-shape jobs in N worker processes; ``--scheduler ADDRESS`` (or ``local:N``) runs them as
Dask tasks on a cluster.

The client streams: the workers read the input files by path, keep the groomed inputs in
``DIR/.correspond-scratch/`` (with the corresponded vertices of each pass, one row file the
client writes as results arrive and the GPA mean is streamed from), which is removed at the
end; this process holds per-shape scalars only, so its memory stays flat in the number of
shapes (``benchmarks/bench_cluster.py --part C``). On a cluster the workers must see the
inputs and ``DIR`` at the same paths (a shared filesystem).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from core.cli._options import add_scheduler_option, say_changed_formats
from core.correspondence import DEFAULT_CPD_PARAMS, establish_correspondence
from core.correspondence.safeguard import describe as describe_safeguard
from core.correspondence.store import SCRATCH_NAME
from core.io import DataFileError, TriMesh, atomic_write_json, load_meshes, save_mesh
from core.io.meshes import order_keeping_suffixes
from core.runtime.parallel import Terminated, signals_deferred, use_scheduler
from core.runtime.progress import StderrProgress

COMMAND = "correspond"
HELP = "bring training meshes into correspondence with one reference topology (CPD + assignment)"

REPORT_NAME = "correspondence.json"


def _cpd_params(args: argparse.Namespace) -> dict:
    """The pairwise step's settings given on the command line."""
    return {"w": args.w, "beta": args.beta, "lam": args.lam, "tolerance": args.tolerance,
            "max_iterations": args.max_iterations, "refine_deformation": args.refine_deformation,
            "mirror_check": not args.no_mirror_check}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("meshes", nargs="+", metavar="MESH", help="training meshes")
    parser.add_argument("--reference", default="auto",
                        help="'auto' (default: best of --n-references candidates) or a mesh file")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--n-references", type=int, default=1,
                        help="candidate references tried with --reference auto (default 1: the "
                             "most typical input; more: the most compact model of that many)")
    parser.add_argument("--vertices", type=int, default=None,
                        help="common vertex count every input (reference included) is remeshed "
                             "to (default: the median input count)")
    parser.add_argument("--refine", type=int, default=1,
                        help="groupwise refinement passes: correspond again to the mean shape "
                             "(default 1; 0: plain reference-based)")
    parser.add_argument("--refine-deformation", choices=("normal_offsets", "cpd"),
                        default=DEFAULT_CPD_PARAMS["refine_deformation"],
                        help="how a refinement pass moves the mean onto each shape: an affine "
                             "map and smooth offsets along its normals (default), or nonrigid "
                             "CPD (the former pass)")
    parser.add_argument("--no-groom", action="store_true",
                        help="no grooming at all (inputs must be single closed surfaces)")
    for step, what in (("largest-piece", "keep only the largest connected piece"),
                       ("fill-holes", "fill small holes"), ("fix-orientation", "fix face orientation"),
                       ("remesh", "remesh to the common vertex count")):
        parser.add_argument(f"--no-{step}", action="store_true", help=f"grooming: do not {what}")
    parser.add_argument("--no-safeguard", action="store_true",
                        help="keep the remesh and every refinement pass even where the model's "
                             "leave-one-out generalisation against the raw inputs says they do "
                             "not help (core.correspondence.safeguard; the report's 'safeguard' "
                             "says what was tried and kept)")
    parser.add_argument("--no-mirror-check", action="store_true",
                        help="keep inputs whose mirror image fits the others better (by default "
                             "left out as a left/right mix-up): for a population in which a "
                             "chiral feature takes either sign")
    parser.add_argument("--selection", choices=("compactness", "residual"), default="compactness",
                        help="how --reference auto ranks candidates (default compactness)")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: CPU count)")
    add_scheduler_option(parser)
    parser.add_argument("--w", type=float, default=DEFAULT_CPD_PARAMS["w"],
                        help="CPD outlier weight in [0, 1) (default %(default)s)")
    parser.add_argument("--beta", type=float, default=DEFAULT_CPD_PARAMS["beta"],
                        help="CPD kernel width, unit-RMS-radius units (default %(default)s)")
    parser.add_argument("--lam", type=float, default=DEFAULT_CPD_PARAMS["lam"],
                        help="CPD regularisation lambda (default %(default)s)")
    parser.add_argument("--tolerance", type=float, default=DEFAULT_CPD_PARAMS["tolerance"],
                        help="CPD tolerance (default %(default)s)")
    parser.add_argument("--max-iterations", type=int, default=DEFAULT_CPD_PARAMS["max_iterations"],
                        help="nonrigid CPD iteration limit (default %(default)s)")


def _output_path(out_dir: Path, source: Path, used: set[str]) -> Path:
    name = source.name
    lower = name.lower()
    if not any(lower.endswith(s) for s in order_keeping_suffixes()):
        name = name.split(".", 1)[0] + ".vtk"  # STL loses vertex order; .vtu/.gii.gz no writer
    base, n = name, 1
    while name in used:  # two inputs with the same file name in different folders
        n += 1
        stem, dot, suffix = base.partition(".")
        name = f"{stem}_{n}{dot}{suffix}"
    used.add(name)
    return out_dir / name


PROVISIONAL_DIR = "provisional"


def _write_interrupted_report(args: argparse.Namespace, paths: list[Path], written: dict,
                              load_failures: dict, exc: BaseException,
                              provisional: dict | None = None) -> None:
    """correspondence.json of a run stopped by SIGINT/SIGTERM: the shapes that were finished
    and written (each output is complete: saves are atomic), and the reference-based results
    written to ``provisional/`` for shapes whose refinement had not finished."""
    how = "SIGTERM" if isinstance(exc, Terminated) else "SIGINT"
    args.out.mkdir(parents=True, exist_ok=True)
    provisional = provisional or {}
    report = {"interrupted": how, "complete": False, "n_written": len(written),
              "n_provisional": len(provisional), "n_inputs": len(args.meshes),
              "shapes": [{"name": str(p), "output": written.get(str(p)),
                          "provisional": provisional.get(str(p))} for p in paths],
              "failures": dict(load_failures), "inputs": [str(p) for p in args.meshes]}
    atomic_write_json(args.out / REPORT_NAME, report)
    extra = (f", {len(provisional)} more as reference-based results in "
             f"{args.out / PROVISIONAL_DIR}" if provisional else "")
    print(f"\nssm-studio correspond: stopped by {how}: {len(written)}/{len(paths)} shapes were "
          f"finished and written{extra}; see {args.out / REPORT_NAME}", file=sys.stderr)


def run(args: argparse.Namespace) -> int:
    # The workers read the inputs by path (each in a child process: a reader crash costs
    # that file only) and keep the groomed inputs and the correspondences of every pass in
    # a scratch folder inside --out, removed at the end: this process holds per-shape
    # scalars only, its memory flat in the number of shapes.
    paths = [Path(p) for p in args.meshes]
    names = [str(p) for p in paths]
    reference: str | int | TriMesh = "auto"
    if args.reference != "auto":
        ref_path = Path(args.reference)
        resolved = [p.resolve() for p in paths]
        if ref_path.resolve() in resolved:
            reference = resolved.index(ref_path.resolve())
        else:
            ref_loaded, ref_failure = load_meshes([ref_path], isolate=True)
            if ref_failure:
                raise DataFileError(ref_path, ref_failure[str(ref_path)])
            reference = ref_loaded[0][1]
            reference.name = str(ref_path)
    params = _cpd_params(args)
    groom: bool | dict = False if args.no_groom else {
        "largest_piece": not args.no_largest_piece, "fill_holes": not args.no_fill_holes,
        "fix_orientation": not args.no_fix_orientation, "remesh": not args.no_remesh}
    used: set[str] = set()
    out_paths = [_output_path(args.out, path, used) for path in paths]
    written: dict[str, str] = {}
    provisional: dict[str, str] = {}   # reference-based results of shapes not final yet
    unreadable: dict[str, str] = {}    # known as soon as read: for an interrupted run's report

    def write_shape(index: int, mesh: TriMesh) -> None:
        # streaming: each output as soon as it is final, so an interrupted run keeps it; the
        # file and its entry in the report go together (a signal waits for both)
        with signals_deferred():
            save_mesh(out_paths[index], TriMesh(mesh.vertices, mesh.faces, out_paths[index].stem),
                      vertex_order=True)
            written[names[index]] = str(out_paths[index])
            stale = provisional.pop(names[index], None)
            if stale is not None:
                Path(stale).unlink(missing_ok=True)

    def write_provisional(index: int, mesh: TriMesh) -> None:
        # written as it comes (not kept in memory): what a stopped run leaves for the shapes
        # whose refinement had not finished; replaced by the final output as it arrives
        target = args.out / PROVISIONAL_DIR / out_paths[index].name
        with signals_deferred():
            target.parent.mkdir(parents=True, exist_ok=True)
            save_mesh(target, TriMesh(mesh.vertices, mesh.faces, target.stem), vertex_order=True)
            provisional[names[index]] = str(target)

    try:  # from the output folder's creation on, an interruption leaves a report
        args.out.mkdir(parents=True, exist_ok=True)
        with use_scheduler(args.scheduler), StderrProgress("correspond") as progress:
            result = establish_correspondence(
                paths, reference, n_references=args.n_references, n_jobs=args.jobs,
                progress=progress, selection=args.selection, groom=groom,
                vertices=args.vertices, refine=args.refine, on_shape=write_shape,
                on_provisional=write_provisional, safeguard=not args.no_safeguard,
                on_unreadable=lambda i, problem: unreadable.__setitem__(names[i], problem),
                scratch=args.out / SCRATCH_NAME, keep_meshes=False, **params)
    except (KeyboardInterrupt, Terminated) as exc:
        readable = [p for p in paths if str(p) not in unreadable]
        _write_interrupted_report(args, readable, written, unreadable, exc, provisional)
        raise
    _remove_empty(args.out / PROVISIONAL_DIR)
    report = _complete_report(result, names, written)
    report["inputs"] = [str(p) for p in args.meshes]
    report["complete"] = True
    atomic_write_json(args.out / REPORT_NAME, report)
    n_ok = len(written)
    _print_summary(args, result, report, n_ok)
    say_changed_formats("correspond", written)
    if n_ok == 0:
        raise ValueError("no mesh could be corresponded (see " + str(args.out / REPORT_NAME) + ")")
    return 1 if report["failures"] else 0


def _print_summary(args, result, report: dict, n_ok: int) -> None:
    """What was written, what the safeguard kept, and each failure (on stderr)."""
    mean = report["mean_residual_mm"]
    print(f"{args.out}: {n_ok}/{len(args.meshes)} meshes corresponded to {result.reference_name} "
          f"({len(result.faces)} triangles), mean residual "
          f"{'n/a' if mean is None else f'{mean:.3f} mm'}, {result.timings['total']:.1f} s")
    for line in describe_safeguard(result.safeguard):
        print(f"  safeguard: {line}")
    for name, problem in report["failures"].items():
        print(f"ssm-studio correspond: {name}: {problem}", file=sys.stderr)


def _complete_report(result, names: list[str], written: dict) -> dict:
    """correspondence.json of a finished run: the readable inputs in input order, then the
    unreadable ones (``result.unreadable``: their problem, no output), the reference's index
    among the readable."""
    unreadable = result.unreadable
    report = result.to_report(names)
    report["shapes"] = [entry for entry in report["shapes"] if entry["name"] not in unreadable]
    for entry in report["shapes"]:
        entry["output"] = written.get(entry["name"])
    index = report["reference_index"]
    if index is not None:
        report["reference_index"] = index - sum(n in unreadable for n in names[:index])
    failures = {k: v for k, v in report["failures"].items() if k not in unreadable}
    for name, problem in unreadable.items():
        report["shapes"].append({"name": name, "ok": False, "residual_mm": None, "seconds": None,
                                 "error": problem, "output": None})
        failures[name] = problem
    report["failures"] = failures
    return report


def _remove_empty(folder: Path) -> None:
    with contextlib.suppress(OSError):
        folder.rmdir()  # only when empty: every provisional result was replaced
