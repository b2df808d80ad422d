"""Evaluate model-building methods on training meshes (Bernard et al., CVPR 2016, section 3.1).

INPUT: corresponded meshes (or raw meshes with ``--correspond``); they are aligned as in
``build-model``. For every method in ``--methods``: reconstruction error (training shapes),
generalisation (leave-one-out refit), specificity (random model instances vs. the closest
training shape) and sparse reconstruction (left-out shape fitted from 5% of its vertices),
each per shape as average and maximum vertex distance in mm, plus compactness. Leave-one-out
folds run in ``--jobs`` processes. ``--loo fixed`` (default) reuses the shapes aligned (and
corresponded) once with all of them; ``--loo refit`` is the true leave-one-out: every fold
re-aligns its training shapes (and, with ``--correspond``, re-corresponds them and the left-out
mesh). ``--noise-var`` fixes the sparse fit's sigma^2 for every method. ``--json`` writes all
per-shape values, ``--plot`` the boxplots (one panel per measure, like the paper's Figure 4). A
summary table (means over shapes) is printed.

``--scheduler ADDRESS`` (or ``local:N``) runs the folds (and the correspondence) as Dask
tasks on a cluster. Nothing is written before the end: SIGINT/SIGTERM stop the workers and exit
130/143 with no output.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from core.build.pipeline import (
    align,
    correspond,
    corresponded_shapes,
    load_training_meshes,
    parse_param_values,
)
from core.cli._options import add_preparation_options, add_scheduler_option
from core.evaluation import Realign, Recorrespond, evaluate_methods, plot_metrics, summary_table, to_json
from core.io import atomic_write_json
from core.models import METHODS, model_class
from core.runtime.parallel import use_scheduler
from core.runtime.progress import StderrProgress

COMMAND = "evaluate"
HELP = "evaluate model methods: reconstruction, generalisation, specificity, sparse reconstruction"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="corresponded meshes (or raw meshes with --correspond); folders allowed")
    parser.add_argument("--methods", default="pca,lsf,splocs,varimax",
                        help=f"comma-separated methods ({','.join(METHODS)}); default all")
    parser.add_argument("--factors", type=int, default=None, metavar="M",
                        help="number of factors for every method (default: each method's own)")
    parser.add_argument("--json", type=Path, default=None, help="write all results as JSON")
    parser.add_argument("--plot", type=Path, default=None, help="write the boxplot figure (.png/.pdf/.svg)")
    add_preparation_options(parser)
    parser.add_argument("--param", action="append", default=[], metavar="METHOD.NAME=VALUE",
                        help="parameter of one method, e.g. --param lsf.lambda_=32 (repeatable)")
    parser.add_argument("--samples", type=int, default=1000,
                        help="random shapes for specificity (default 1000)")
    parser.add_argument("--sparse-fraction", type=float, default=0.05,
                        help="fraction of vertices known in sparse reconstruction (default 0.05)")
    parser.add_argument("--noise-var", type=float, default=None,
                        help="sigma^2 (mm^2) of the sparse fit, the same for every method "
                             "(default: each fold model's residual variance)")
    parser.add_argument("--loo", choices=("fixed", "refit"), default="fixed",
                        help="leave-one-out: fixed (shapes prepared once with all; default) or "
                             "refit (true leave-one-out: each fold re-aligns, and with "
                             "--correspond re-corresponds)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="processes for leave-one-out folds (default: all cores)")
    add_scheduler_option(parser)


def run(args: argparse.Namespace) -> int:
    # one Dask client (or none) for the correspondence and the folds alike
    with use_scheduler(args.scheduler):
        return _evaluate(args)


def _evaluate(args: argparse.Namespace) -> int:
    methods = [model_class(m).method for m in args.methods.split(",") if m.strip()]
    if not methods:
        raise ValueError("--methods lists no method")
    per_method: dict[str, dict] = {m: {} for m in methods}
    for name, value in parse_param_values(args.param).items():
        if "." not in name:
            raise ValueError(f"--param expects METHOD.NAME=VALUE, got {name}")
        method, pname = name.split(".", 1)
        method = model_class(method).method
        if method not in per_method:
            raise ValueError(f"--param {name}: method {method} is not in --methods")
        per_method[method][pname] = value
    for suffix_path in (args.plot,):
        if suffix_path is not None and suffix_path.suffix.lower() not in (".png", ".pdf", ".svg"):
            raise ValueError(f"{suffix_path}: the plot must be .png, .pdf or .svg")
    with StderrProgress("read meshes") as progress:
        meshes = load_training_meshes(args.inputs, progress=progress, isolate=True,
                                      vertex_order=not args.correspond)
    raw = meshes
    if args.correspond:
        with StderrProgress("correspond") as progress:
            corr = correspond(meshes, n_jobs=args.jobs, progress=progress)
        meshes = [m for m in corr.meshes if m is not None]
    _, shapes, faces = corresponded_shapes(meshes)
    with StderrProgress("align") as progress:
        aligned = align(shapes, method=args.align, transform=args.transform, progress=progress)
    folds: Recorrespond | Realign | None = None
    if args.loo == "refit" and args.correspond:
        folds = Recorrespond([m for m, c in zip(raw, corr.meshes) if c is not None],
                             reference=_kept_index(corr), method=args.align,
                             transform=args.transform)
    elif args.loo == "refit":
        folds = Realign(shapes, faces, method=args.align, transform=args.transform)
    with StderrProgress("evaluate") as progress:
        results = evaluate_methods(methods, aligned.aligned, faces, n_factors=args.factors,
                                   params=per_method, n_jobs=args.jobs, random_state=args.seed,
                                   n_samples=args.samples, sparse_fraction=args.sparse_fraction,
                                   noise_var=args.noise_var, folds=folds, progress=progress)
    loo = {"fixed": "leave-one-out on the shapes prepared once",
           "refit": "true leave-one-out (each fold re-aligned"
                    + (" and re-corresponded)" if args.correspond else ")")}[args.loo]
    print(f"{len(shapes)} shapes, {shapes.shape[1]} vertices; means over shapes, mm; {loo}")
    print(summary_table(results))
    if args.json is not None:
        atomic_write_json(args.json, to_json(results))
        print(f"wrote {args.json}")
    if args.plot is not None:
        plot_metrics(results, args.plot, title=f"{len(shapes)} shapes")
        print(f"wrote {args.plot}")
    return 0


def _kept_index(corr) -> int:
    """Index of the chosen reference among the meshes that were corresponded."""
    if corr.reference_index is None:
        return 0
    return sum(1 for m in corr.meshes[:corr.reference_index] if m is not None)
