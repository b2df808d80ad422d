"""Fit a shape model to contour points and voxelise the fitted surface on an image's grid.

Like ``ssm-studio fit``, then the fitted (closed) surface is turned into a uint8 label map with
the image's shape and affine (``core.geometry.segmentation.voxelize``: ray parity in voxel-index space,
so oblique images are handled). The image may be NIfTI, NRRD, MetaImage or a DICOM series
(a folder, or one of its files; ``--series UID`` picks one of a folder's series, otherwise
the one with most files is used and named). The label map's format follows ``--out``:
NIfTI (with the image's own sform, qform and codes when the image is NIfTI, so viewers that
read the qform where nibabel reads the sform agree; else the affine as both), NRRD or MHA (the
same geometry in LPS), or ``.seg.nrrd``, a 3D Slicer Segmentation carrying the structure's
``--name`` and ``--color``. 3D Slicer and ITK-SNAP open each aligned with the image.

``--auto-place`` registers the image to the models' template first (``--template``, default the
bundled MNI T1; affine, mutual information) and places the model through that transform
(``core.registration.placement``) instead of using the model's stored placement.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from core.cli.fit import add_fit_arguments, fit_from_args, summary, warn_if_implausible, write_json
from core.geometry.segmentation import mask_volume_mm3, voxelize
from core.io import TriMesh, load_volume, save_mesh, save_volume

COMMAND = "segment"
HELP = "fit a shape model to contour points and write the label map on the image's grid"

LABEL_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".seg.nrrd", ".mha")


def _color(text: str) -> tuple[float, float, float]:
    """An RGB colour: three numbers 0-1 (``0.9,0.7,0.2``) or ``#rrggbb``."""
    text = text.strip()
    try:
        if text.startswith("#") and len(text) == 7:
            return tuple(int(text[i:i + 2], 16) / 255.0 for i in (1, 3, 5))  # type: ignore[return-value]
        values = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise argparse.ArgumentTypeError(f"'{text}' is not a colour (r,g,b in 0-1 or #rrggbb)")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_fit_arguments(parser)
    parser.add_argument("--image", required=True,
                        help="the image the points were drawn on: .nii/.nii.gz, .nrrd/.nhdr, "
                             ".mha/.mhd, or a DICOM series (folder or one of its files)")
    parser.add_argument("--series", default=None, metavar="UID",
                        help="DICOM folder with several series: the SeriesInstanceUID to read")
    parser.add_argument("--out", required=True, type=Path,
                        help="label map: .nii, .nii.gz, .nrrd, .mha, or .seg.nrrd (3D Slicer "
                             "Segmentation with --name and --color)")
    parser.add_argument("--label", type=int, default=1, help="label value inside (1..255, default 1)")
    parser.add_argument("--name", default=None,
                        help="structure name stored in a .seg.nrrd (default: the model file's name)")
    parser.add_argument("--color", type=_color, default=(0.9, 0.7, 0.2),
                        help="structure colour in a .seg.nrrd: r,g,b in 0-1 or #rrggbb")
    parser.add_argument("--mesh-out", type=Path, default=None, help="also write the fitted surface")
    parser.add_argument("--auto-place", action="store_true",
                        help="place the model by registering the image to the model's template "
                             "(affine, mutual information) instead of --placement")
    parser.add_argument("--template", default=None,
                        help="template image for --auto-place (default: the bundled MNI ICBM152 "
                             "T1, the demo models' space)")


def save_label_map(path: Path, mask, affine, label: int, name: str, color, like=None) -> None:
    """Write a label map by extension (``.seg.nrrd`` with its segment description)."""
    if path.name.lower().endswith(".seg.nrrd"):
        from core.io.nrrd import Segment, write_segmentation

        write_segmentation(path, mask, affine, [Segment(label, name, tuple(color))])
    else:
        save_volume(path, mask, affine, like=like)


def run(args: argparse.Namespace) -> int:
    out_name = args.out.name.lower()
    if not out_name.endswith(LABEL_SUFFIXES):
        raise ValueError(f"{args.out}: label maps are written as "
                         f"{', '.join(LABEL_SUFFIXES)} (by extension)")
    if not 1 <= args.label <= 255:
        raise ValueError(f"--label {args.label}: must be 1..255")

    def notify(message: str) -> None:
        print(f"ssm-studio segment: {message}", file=sys.stderr)

    image = load_volume(args.image, series=args.series, notify=notify)  # fail early, before fitting
    placement_of, registration = None, None
    if args.auto_place:
        if args.placement is not None:
            raise ValueError("--auto-place and --placement exclude each other")
        from core.registration.placement import placement_through, register_to_template
        from core.runtime.progress import StderrProgress

        registration = register_to_template(image, args.template,
                                            progress=StderrProgress("registering"))
        notify(f"registered {args.image} to the template in {registration.seconds:.1f} s "
               f"(metric {registration.metric:.3f})")

        def placement_of(model):
            return placement_through(model, registration.transform)
    elif args.template is not None:
        raise ValueError("--template goes with --auto-place")
    model, result = fit_from_args(args, placement_of)
    mask = voxelize(result.vertices, model.faces, image, label=args.label)
    name = args.name or Path(str(args.model)).name.split(".")[0]
    save_label_map(args.out, mask, image.affine, args.label, name, args.color, like=image)
    if args.mesh_out is not None:
        save_mesh(args.mesh_out, TriMesh(result.vertices, model.faces, Path(args.mesh_out).stem))
    volume_mm3 = mask_volume_mm3(mask, image.affine)
    extra = {} if registration is None else {"auto_placement": registration.to_dict()}
    write_json(args.json, result, model=str(args.model), points=str(args.points),
               image=str(args.image), mask=str(args.out), mask_volume_mm3=volume_mm3, **extra)
    print(f"{args.out}: {summary(result)}; mask {volume_mm3 / 1000:.2f} cm^3")
    warn_if_implausible("segment", result)
    if volume_mm3 == 0:
        print(f"ssm-studio segment: warning: the fitted surface does not overlap {args.image}")
    return 0
