"""Register a patient image to the models' template image (affine, mutual information).

Linear registration of IMAGE (moving) onto TEMPLATE (fixed; default: the bundled MNI ICBM152
2009a T1, the space of the demo models) with ``core.registration.volumes``: Mattes mutual information,
a multi-resolution pyramid in mm (default 8, 4, 2 mm), centre-of-mass initialisation.

Writes ``--out transform.json``: a JSON object whose ``"transform"`` is the 4x4 RAS matrix
mapping image world -> template world, acting on column vectors (``x_template = T @ [x, 1]``;
a model in template space is placed on the image with ``inv(T)``), plus the inputs
(``"image"``, ``"template"``), ``"transform_class"``, the final ``"metric"`` (Mattes mutual
information, negative, lower is better), its value after initialisation, iterations and time.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from core.io import atomic_write_json, load_volume
from core.registration.volumes import DEFAULT_LEVELS_MM, TRANSFORMS, default_template_path, register_volumes
from core.runtime.progress import StderrProgress

COMMAND = "register"
HELP = "register an image to the template (affine, mutual information): writes transform.json"


def add_registration_options(parser: argparse.ArgumentParser, default_transform: str = "affine") -> None:
    """Options of the registration engine shared by ``register`` and ``register-images``."""
    parser.add_argument("--transform", choices=TRANSFORMS, default=default_transform,
                        help=f"transformation class (default {default_transform})")
    parser.add_argument("--levels", default=",".join(f"{r:g}" for r in DEFAULT_LEVELS_MM),
                        metavar="MM,MM,...",
                        help="pyramid resolutions in mm, coarse to fine (default %(default)s)")
    parser.add_argument("--samples", type=int, default=20000,
                        help="voxels sampled for the metric per level (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default 0)")


def registration_kwargs(args: argparse.Namespace) -> dict:
    """Engine keyword arguments from :func:`add_registration_options`' options."""
    try:
        levels = [float(v) for v in str(args.levels).split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--levels expects comma-separated mm values, got {args.levels!r}") from None
    if not levels or any(not v > 0 for v in levels):
        raise ValueError(f"--levels expects positive mm values, got {args.levels!r}")
    if args.samples < 100:
        raise ValueError(f"--samples must be at least 100, got {args.samples}")
    return {"levels_mm": levels, "n_samples": int(args.samples), "random_state": int(args.seed)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--image", required=True, type=Path, help="image to register (moving)")
    parser.add_argument("--template", type=Path, default=None,
                        help="template image (fixed; default: the bundled MNI ICBM152 T1)")
    parser.add_argument("--out", required=True, type=Path, help="transform file to write (.json)")
    add_registration_options(parser)
    parser.add_argument("--threads", type=int, default=None, help="threads (default: all cores)")


def run(args: argparse.Namespace) -> int:
    kwargs = registration_kwargs(args)
    template_path = args.template if args.template is not None else default_template_path()
    image = load_volume(args.image)
    template = load_volume(template_path)
    with StderrProgress("register") as progress:
        result = register_volumes(image, template, args.transform, threads=args.threads,
                                  progress=progress, **kwargs)
    out = {"transform": result.transform.tolist(),
           "convention": "4x4 RAS mm, maps image world -> template world, column vectors",
           "image": str(args.image), "template": str(template_path)}
    out.update({k: v for k, v in result.to_dict().items() if k != "transform"})
    atomic_write_json(args.out, out)
    print(f"{args.out}: {args.transform} {args.image} -> {template_path}, metric "
          f"{result.initial_metric:.4f} -> {result.metric:.4f}, {result.seconds:.1f} s")
    return 0
