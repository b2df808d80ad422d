"""Register several images into one unbiased common space (transformation synchronisation).

Multi-image registration of the thesis' chapter 7 (Bernard et al., MICCAI workshop on spectral
analysis in medical imaging, 2015): pairwise registrations of the images (``core.registration.volumes``:
Mattes mutual information, multi-resolution; ``--pairs all`` or each image with its K nearest,
``knn:K``), then the numerically stable transformation synchronisation of ``core.alignment.transforms``
(``--method sync``, default): transitively consistent transforms into a common space that no
image is the reference of. ``--method reference`` registers every image to ``--reference``
(default: the first), the classic, biased baseline.

Writes ``DIR/transforms.json`` (per image the 4x4 RAS matrix mapping its world into the common
space; every pairwise transform (image j -> image i) with its metric, its residual against the
synchronised result, and whether it was used or dropped as an outlier and why), every image
resampled into the common space (``DIR/resampled/``) and their mean, the unbiased template
(``DIR/template.nii.gz``). An unreadable image, or one no registration links to the others,
is reported and left out; the rest complete (exit code 1). ``--scheduler`` runs the pairwise
registrations as Dask tasks.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from core.cli._options import add_scheduler_option
from core.cli.register import add_registration_options, registration_kwargs
from core.io import atomic_write_json
from core.registration.multi_image import METHODS, parse_pairs, register_images
from core.runtime.parallel import use_scheduler
from core.runtime.progress import StderrProgress

COMMAND = "register-images"
HELP = "register images into one unbiased common space (pairwise + synchronisation) and average them"

REPORT_NAME = "transforms.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", metavar="IMG", help="images to register")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--method", choices=METHODS, default="sync",
                        help="sync (default: pairwise + synchronisation) or reference")
    parser.add_argument("--reference", default=None, metavar="IMG",
                        help="reference image for --method reference (default: the first)")
    parser.add_argument("--pairs", default="all", help="all (default) or knn:K")
    parser.add_argument("--spacing", type=float, default=None,
                        help="common grid spacing in mm (default: the finest input spacing)")
    parser.add_argument("--outlier-mm", type=float, default=3.0,
                        help="pairs disagreeing with the synchronised result by more than this "
                             "(and the others' spread) are dropped (default %(default)s mm)")
    add_registration_options(parser)
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: CPU count)")
    add_scheduler_option(parser)


def run(args: argparse.Namespace) -> int:
    kwargs = registration_kwargs(args)
    parse_pairs(args.pairs)
    if args.method == "reference" and args.pairs != "all":
        raise ValueError("--pairs applies to --method sync only")
    reference = None
    if args.reference is not None:
        if args.method != "reference":
            raise ValueError("--reference applies to --method reference only")
        names = [str(Path(p).resolve()) for p in args.images]
        ref = str(Path(args.reference).resolve())
        if ref not in names:
            raise ValueError(f"--reference {args.reference} is not one of the images")
        reference = names.index(ref)
    if args.spacing is not None and not args.spacing > 0:
        raise ValueError(f"--spacing must be positive, got {args.spacing}")
    with use_scheduler(args.scheduler), StderrProgress("register-images") as progress:
        result = register_images(args.images, args.transform, method=args.method,
                                 reference=reference, pairs=args.pairs, out_dir=args.out,
                                 spacing=args.spacing, outlier_mm=args.outlier_mm,
                                 n_jobs=args.jobs, registration=kwargs, progress=progress)
    report = result.to_dict()
    report["inputs"] = [str(p) for p in args.images]
    atomic_write_json(args.out / REPORT_NAME, report)
    n_ok = sum(result.ok)
    dropped = [p for p in result.pairs if not p["used"]]
    print(f"{args.out}: {n_ok}/{len(args.images)} images in the common space ({args.method}, "
          f"{args.transform}), {len(result.pairs) - len(dropped)}/{len(result.pairs)} pairs used, "
          f"template {result.outputs.get('template')}, {result.timings['total']:.1f} s")
    for k, problem in result.image_errors.items():
        print(f"ssm-studio register-images: {args.images[k]}: {problem}", file=sys.stderr)
    for p in dropped:
        print(f"ssm-studio register-images: pair {args.images[p['j']]} -> {args.images[p['i']]}: "
              f"{p['note']}", file=sys.stderr)
    return 1 if result.image_errors else 0
