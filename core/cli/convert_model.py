"""Convert a shape model between SSM Studio's ``.npz`` and statismo/Scalismo's ``.h5``.

The formats are chosen by extension (``IN`` and ``OUT``: ``.npz``, ``.h5``/``.hdf5``). The
mapping is exact and documented in :mod:`core.io.statismo`: statismo's orthonormal
basis and variances become our factors and ``coef_var``; our non-orthonormal factors are
written by their covariance (same Gaussian). ``--space`` says whether the ``.h5`` holds LPS
(statismo's and ITK's physical space, the default) or RAS world coordinates.
``IN`` may be ``FILE.h5#GROUP``: one model of a file that holds several (a scalismo-faces
morphable model's ``#shape``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from core.io import load_model, read_statismo, save_model, write_statismo
from core.io.registry import split_member

COMMAND = "convert-model"
HELP = "convert a shape model between .npz (SSM Studio) and .h5 (statismo/Scalismo)"

MODEL_SUFFIXES = (".npz", ".h5", ".hdf5")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", type=Path, metavar="IN",
                        help="model to read (.npz or .h5; FILE.h5#GROUP for one model of a "
                             "file that holds several, e.g. face.h5#shape)")
    parser.add_argument("output", type=Path, metavar="OUT", help="model to write (.npz or .h5)")
    parser.add_argument("--space", choices=("lps", "ras"), default=None,
                        help="world coordinates of the .h5 side (default: what the file says, "
                             "else LPS as statismo/ITK)")


def run(args: argparse.Namespace) -> int:
    source = split_member(args.input)[0]
    for path in (source, args.output):
        if path.suffix.lower() not in MODEL_SUFFIXES:
            raise ValueError(f"{path}: not a model file name (expected .npz, .h5 or .hdf5)")
    if source.resolve() == args.output.resolve():
        raise ValueError(f"{args.output}: output and input are the same file")
    space = args.space.upper() if args.space else None
    if source.suffix.lower() == ".npz":
        model = load_model(args.input)
    else:
        model = read_statismo(args.input, space=space)
    if args.output.suffix.lower() == ".npz":
        save_model(args.output, model)
    else:
        write_statismo(args.output, model, space=space or "LPS")
    noise = model.info.get("noise_variance")
    print(f"{args.output}: {model.n_vertices} vertices, {len(model.faces)} triangles, "
          f"{model.n_factors} factors ({model.method})"
          + (f", noise variance {noise:.4g} mm^2" if noise is not None else ""))
    return 0
