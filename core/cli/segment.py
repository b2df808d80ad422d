"""Fit a shape model to contour points and voxelise the fitted surface on an image's grid.

Like ``ssm-studio fit``, then the fitted (closed) surface is turned into a uint8 label map with
the image's shape and affine (``core.segmentation.voxelize``: ray parity in voxel-index space,
so oblique images are handled), written as NIfTI with that affine in sform and qform: 3D Slicer
and ITK-SNAP open it aligned with the image.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from core.cli.fit import add_fit_arguments, fit_from_args, summary, write_json
from core.io import TriMesh, load_volume, save_mesh, save_volume
from core.segmentation import mask_volume_mm3, voxelize

COMMAND = "segment"
HELP = "fit a shape model to contour points and write the label map on the image's grid"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_fit_arguments(parser)
    parser.add_argument("--image", required=True, help="the image the points were drawn on (.nii/.nii.gz)")
    parser.add_argument("--out", required=True, type=Path, help="label map (.nii or .nii.gz)")
    parser.add_argument("--label", type=int, default=1, help="label value inside (1..255, default 1)")
    parser.add_argument("--mesh-out", type=Path, default=None, help="also write the fitted surface")


def run(args: argparse.Namespace) -> int:
    image = load_volume(args.image)  # fail early on a bad image, before fitting
    model, result = fit_from_args(args)
    mask = voxelize(result.vertices, model.faces, image, label=args.label)
    save_volume(args.out, mask, image.affine)
    if args.mesh_out is not None:
        save_mesh(args.mesh_out, TriMesh(result.vertices, model.faces, Path(args.mesh_out).stem))
    volume_mm3 = mask_volume_mm3(mask, image.affine)
    write_json(args.json, result, model=str(args.model), points=str(args.points),
               image=str(args.image), mask=str(args.out), mask_volume_mm3=volume_mm3)
    print(f"{args.out}: {summary(result)}; mask {volume_mm3 / 1000:.2f} cm^3")
    if volume_mm3 == 0:
        print(f"ssm-studio segment: warning: the fitted surface does not overlap {args.image}")
    return 0
