"""Build a shape model from training meshes: (correspond ->) align -> factorise -> model file.

INPUT: meshes already in correspondence (same vertex count and triangles, vertex i homologous;
e.g. the output of ``ssm-studio correspond``), or raw meshes of any topology with
``--correspond`` (runs the correspondence pipeline first). Folders stand for the mesh files in
them. The corresponded shapes are aligned (``--align sync`` transformation synchronisation,
default; ``gpa``; or ``none``) with ``--transform`` (similarity by default), then factorised:

- ``pca``: principal components (``--factors M`` or ``--variance 0.95``);
- ``lsf``: local-support factors (Bernard et al., CVPR 2016; ``--param lambda_=64`` etc.);
- ``splocs``: sparse localised deformation components (Neumann et al., 2013);
- ``varimax``: varimax-rotated PCA.

The model file (``.npz``, format of ``core.io.save_model``) keeps the mean, factors, prior
variances, triangles and a world placement: the transform from the model frame to the
training shapes' average pose, so the mean appears where the training shapes were (e.g. on
the structure in the MRI they came from).

With ``--correspond``, ``--scheduler ADDRESS`` (or ``local:N``) runs the per-shape
correspondence jobs as Dask tasks on a cluster. The workers read the raw inputs by path and
keep the groomed ones in a scratch folder next to the model file (``.MODEL.npz.scratch``,
removed at the end), so this process holds the corresponded shapes only (the model is fitted
to all of them at once; they are what it needs). The model file is written at the end only:
SIGINT/SIGTERM stop the workers and exit 130/143 with no model written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from core.build.pipeline import build_model, load_training_meshes, parse_param_values, training_mesh_paths
from core.cli._options import add_preparation_options, add_scheduler_option
from core.io import DataFileError, save_model
from core.models import METHODS
from core.runtime.parallel import use_scheduler
from core.runtime.progress import StderrProgress

COMMAND = "build-model"
HELP = "build a shape model (PCA, local-support LSF, SPLOCS, Varimax) from training meshes"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="corresponded meshes (or raw meshes with --correspond); folders allowed")
    parser.add_argument("--method", choices=METHODS, default="pca", help="model (default pca)")
    parser.add_argument("--factors", type=int, default=None, metavar="M",
                        help="number of factors (lsf: maximum number before pruning/splitting)")
    parser.add_argument("--variance", type=float, default=None, metavar="F",
                        help="pca only: keep the fewest modes explaining this fraction (e.g. 0.95)")
    parser.add_argument("--out", required=True, type=Path, help="model file to write (.npz)")
    add_preparation_options(parser)
    parser.add_argument("--reference", default="auto",
                        help="correspondence reference: auto (default), an input index, or a mesh file")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="method parameter, e.g. --param lambda_=64 --param max_iter=300 "
                             "(repeatable)")
    parser.add_argument("--no-mirror-check", action="store_true",
                        help="with --correspond: keep inputs whose mirror image fits the others "
                             "better (as correspond --no-mirror-check): for a population in "
                             "which a chiral feature takes either sign")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (correspondence)")
    add_scheduler_option(parser)


def reference_option(value: str):
    """--reference: "auto", an input index or a mesh file."""
    if value == "auto":
        return "auto"
    if value.isdigit():
        return int(value)
    from core.io import DataFileError, load_meshes

    loaded, failures = load_meshes([value], isolate=True)  # a reader crash is reported
    if failures:
        raise DataFileError(value, failures[value])
    return loaded[0][1]


def _streamed_inputs(args: argparse.Namespace) -> tuple[list, dict]:
    """The raw inputs as paths the workers read, and the correspondence options that keep
    the groomed inputs in a scratch folder next to the model file (removed at the end): this
    process holds only the corresponded shapes, which the model needs."""
    from core.correspondence.store import InputFile

    paths = training_mesh_paths(args.inputs)

    def unreadable(index: int, problem: str) -> None:  # as before: no model, one line
        raise DataFileError(paths[index], problem)

    return ([InputFile(str(p), p.name) for p in paths],
            {"scratch": args.out.parent / f".{args.out.name}.scratch", "on_unreadable": unreadable})


def run(args: argparse.Namespace) -> int:
    if not args.out.name.lower().endswith(".npz"):
        raise ValueError(f"{args.out}: the model file must end in .npz")
    params = parse_param_values(args.param)
    if args.variance is not None:
        if args.method != "pca":
            raise ValueError("--variance applies to --method pca only")
        params["variance_retained"] = args.variance
    if args.factors is not None and args.factors < 1:
        raise ValueError(f"--factors must be at least 1, got {args.factors}")
    if args.scheduler is not None and not args.correspond:
        raise ValueError("--scheduler applies to build-model --correspond (its per-shape jobs)")
    if args.no_mirror_check and not args.correspond:
        raise ValueError("--no-mirror-check applies to build-model --correspond")
    options = None
    if args.correspond:
        meshes, options = _streamed_inputs(args)
        if args.no_mirror_check:
            options["mirror_check"] = False
    else:
        with StderrProgress("read meshes") as progress:
            meshes = load_training_meshes(args.inputs, progress=progress, isolate=True,
                                          vertex_order=True)
    reference = reference_option(args.reference) if args.correspond else "auto"
    with use_scheduler(args.scheduler), StderrProgress(f"build {args.method} model") as progress:
        result = build_model(meshes, correspond=args.correspond, reference=reference,
                             align=args.align, transform=args.transform, method=args.method,
                             n_factors=args.factors, method_params=params, n_jobs=args.jobs,
                             progress=progress, correspond_options=options)
    save_model(args.out, result.model)
    model = result.model
    for name, reason in result.failures.items():
        print(f"skipped {name}: {reason}", file=sys.stderr)
    if result.correspondence is not None:
        from core.correspondence.safeguard import describe as describe_safeguard

        for line in describe_safeguard(result.correspondence.safeguard):
            print(f"  safeguard: {line}")
    times = ", ".join(f"{k} {v:.1f} s" for k, v in result.timings.items())
    print(f"{args.out}: {model.method} model, {model.n_factors} factors, {model.n_vertices} "
          f"vertices, {len(result.names)} training shapes ({times})")
    return 0
