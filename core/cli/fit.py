"""Fit a shape model to contour points and write the fitted surface.

Reads a model (.npz from ``ssm-studio build-model``, or a statismo/Scalismo .h5) and points in
world RAS mm (CSV with header ``x,y,z[,nx,ny,nz]`` or a 3D Slicer markups .mrk.json), runs the
reconstruction engine (``core.reconstruction.fit_points``: anisotropic or isotropic GMM, or ICP,
with the model's Gaussian prior and a similarity/rigid/no pose) and writes the fitted mesh
(.vtk, .vtp, .stl, .ply, .obj, .gii). ``--json`` also writes the coefficients, the pose, the
per-iteration objective, the stopping reason, the mean point-to-surface residual and
``warnings``: why the fit looks implausible, by the same policy as the GUI
(:mod:`core.reconstruction.plausibility`); they are also printed as one ``warning:`` line.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from core.io import TriMesh, atomic_write_json, load_model, load_points, save_mesh
from core.io.registry import split_member
from core.reconstruction import METHODS, POSES, FitResult, fit_points
from core.reconstruction.fit import PRIOR_WEIGHT, placement_at
from core.reconstruction.plausibility import plausibility_warnings

COMMAND = "fit"
HELP = "fit a shape model to contour points (GMM or ICP) and write the fitted surface"


def add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by ``fit`` and ``segment``."""
    parser.add_argument("--model", required=True,
                        help="shape model (.npz, or a statismo/Scalismo .h5; FILE.h5#GROUP for "
                             "one model of a file that holds several, e.g. face.h5#shape)")
    parser.add_argument("--model-space", choices=("lps", "ras"), default=None,
                        help=".h5 models: world coordinates of the file (default: what it "
                             "records, else LPS as statismo/ITK)")
    parser.add_argument("--points", required=True,
                        help="contour points in world RAS mm (.csv x,y,z[,nx,ny,nz] or .mrk.json)")
    parser.add_argument("--method", choices=METHODS, default="gmm-aniso",
                        help="gmm-aniso (default): surface-aware GMM; gmm-iso; icp")
    parser.add_argument("--pose", choices=POSES, default="similarity",
                        help="transform fitted on top of the model's placement (default similarity)")
    parser.add_argument("--prior-weight", type=float, default=PRIOR_WEIGHT,
                        help=f"weight of the shape prior (default {PRIOR_WEIGHT:g})")
    parser.add_argument("--outlier-weight", type=float, default=0.0,
                        help="uniform outlier weight in [0, 1) (default 0)")
    parser.add_argument("--max-iter", type=int, default=100, help="EM iteration limit (default 100)")
    parser.add_argument("--placement", default=None,
                        help="where the model is placed before fitting (the start and the centre of "
                             "the pose prior): 'x,y,z' moves the model's mean shape centre to that "
                             "world point (like the GUI's Place here), or a file with a 4x4 model -> "
                             "world matrix (.txt/.csv rows, .npy, or .json), or 'points' (the "
                             "model's centre at the points' centre); default: the model's "
                             "stored placement")
    parser.add_argument("--pose-spread", type=float, default=1.0,
                        help="spread of the pose prior around the placement, times the default "
                             "(3 deg, 1 mm, 3%% scale); 0 = no pose prior (default 1)")
    parser.add_argument("--no-normals", action="store_true",
                        help="ignore the normals in the points file")
    parser.add_argument("--json", type=Path, default=None,
                        help="also write the fit result (coefficients, pose, objective) as JSON")


def placement_from_arg(text: str | None, model) -> np.ndarray | str | None:
    """The --placement value as a 4x4 model -> world matrix (None: the model's own;
    "points": at the points' centre, resolved by ``fit_points``)."""
    if text is None:
        return None
    if text == "points" and not Path(text).exists():
        return "points"
    parts = text.split(",")
    if len(parts) == 3 and not Path(text).exists():
        try:
            target = np.array([float(v) for v in parts])
        except ValueError:
            raise ValueError(f"--placement {text!r}: expected x,y,z in mm or a matrix file") from None
        return placement_at(model, target)
    path = Path(text)
    if not path.exists():
        raise ValueError(f"{path}: file not found (--placement)")
    try:
        if path.suffix.lower() == ".npy":
            matrix = np.load(path, allow_pickle=False)
        elif path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            matrix = np.asarray(data.get("placement", data.get("matrix")) if isinstance(data, dict)
                                else data, dtype=np.float64)
        else:
            matrix = np.loadtxt(path, delimiter="," if path.suffix.lower() == ".csv" else None)
        matrix = np.asarray(matrix, dtype=np.float64)
    except (ValueError, OSError, TypeError) as exc:
        raise ValueError(f"{path}: not a 4x4 matrix ({exc})") from None
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ValueError(f"{path}: expected a finite 4x4 matrix, got shape {matrix.shape}")
    return matrix


def fit_from_args(args: argparse.Namespace, placement_of=None):
    """Load the model and points named in ``args`` and fit; returns (model, FitResult).

    ``placement_of(model)``, if given, returns the placement to use (``segment --auto-place``).
    """
    if getattr(args, "model_space", None) and \
            split_member(args.model)[0].suffix.lower() in (".h5", ".hdf5"):
        from core.io import read_statismo

        model = read_statismo(args.model, space=args.model_space.upper())
    else:
        model = load_model(args.model)
    points = load_points(args.points)
    normals = None if args.no_normals else points.normals
    if placement_of is not None:
        placement = placement_of(model)
    else:
        placement = placement_from_arg(getattr(args, "placement", None), model)
    try:
        result = fit_points(model, points.points, normals, method=args.method, pose=args.pose,
                            prior_weight=args.prior_weight, outlier_weight=args.outlier_weight,
                            max_iter=args.max_iter, placement=placement,
                            pose_spread=getattr(args, "pose_spread", 1.0))
    except ValueError as exc:
        raise ValueError(f"{args.points}: {exc}") from None
    return model, result


def write_json(path: Path | None, result: FitResult, **extra) -> None:
    if path is not None:
        atomic_write_json(path, {**result.to_dict(), "warnings": list(fit_warnings(result)),
                                 **extra})


def fit_warnings(result: FitResult) -> tuple[str, ...]:
    """The fit's own warnings (points far from the placement: the pose, not the shape, is
    uncertain) and why it looks implausible by the GUI's policy
    (core.reconstruction.plausibility)."""
    implausible = plausibility_warnings(result.plausibility())
    return (*result.warnings,
            *((f"implausible fit: {'; '.join(implausible)}",) if implausible else ()))


def warn_if_implausible(command: str, result: FitResult) -> None:
    """One warning line on stderr each, as the GUI flags the fit."""
    for warning in fit_warnings(result):
        print(f"ssm-studio {command}: warning: {warning}", file=sys.stderr)


def summary(result: FitResult) -> str:
    return (f"{result.method}, pose {result.pose_mode}: {result.n_points} points, "
            f"{result.n_iter} iterations ({result.stop_reason}), mean residual "
            f"{result.residual_mm:.2f} mm, scale {result.scale:.3f}, {result.elapsed_s * 1000:.0f} ms")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_fit_arguments(parser)
    parser.add_argument("--out", required=True, type=Path,
                        help="fitted surface (.vtk, .vtp, .stl, .ply, .obj or .gii)")


def run(args: argparse.Namespace) -> int:
    model, result = fit_from_args(args)
    save_mesh(args.out, TriMesh(result.vertices, model.faces, Path(args.out).stem))
    write_json(args.json, result, model=str(args.model), points=str(args.points),
               mesh=str(args.out))
    print(f"{args.out}: {summary(result)}")
    warn_if_implausible("fit", result)
    return 0
