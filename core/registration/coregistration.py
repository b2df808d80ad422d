"""A second image of the same patient (T2, FLAIR, CT) brought onto the first image's grid.

Interactive segmentation tools (ITK-SNAP's "additional images", 3D Slicer's background /
foreground layers) show a second scan of the patient over the first one, blended or as a
checkerboard, so the user can draw where a structure is best seen. Two scans of one patient
differ by a rigid motion (the head moved between series; another scanner): when the two grids
differ, the second image is registered rigidly onto the first with the one image registration
engine, :func:`core.registration.volumes.register_volumes` (Mattes mutual information, Mattes et al.,
IEEE TMI 2003, so T1/T2/CT contrasts register; multi-resolution, centre-of-mass start), then
resampled (trilinear) onto the first image's voxel grid. On that common grid one slice sampler
geometry serves both images: a view's slice of the second image covers exactly the pixels of
the first, and a point drawn on either is the same world point of the first image's space.

Display composites of two windowed slices (``uint8``): :func:`blend` (linear, opacity of the
image on top) and :func:`checkerboard_mask` (squares of a fixed size in mm in the slice plane,
so the pattern stays put while zooming and does not depend on the voxel size).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from core.geometry.planes import SliceImage
from core.runtime.progress import ProgressCallback, report
from core.types.volume import Volume

__all__ = ["CoRegistered", "same_grid", "coregister", "blend", "checkerboard_mask"]


@dataclass
class CoRegistered:
    """The second image on the first image's grid.

    Attributes
    ----------
    volume : Volume
        The second image resampled on the reference grid (shape and affine of the reference);
        NaN where the second image has no data.
    transform : (4, 4) float
        RAS matrix mapping the second image's world onto the reference's world (column vectors;
        identity when the grids were the same).
    registered : bool
        True when :func:`core.registration.volumes.register_volumes` computed ``transform`` (False for
        identical grids or a given transform, e.g. from a session).
    metric : float or None
        Final Mattes mutual information of the registration (lower is better).
    seconds : float
        Wall time of the registration (0 without one).
    """

    volume: Volume
    transform: np.ndarray
    registered: bool
    metric: float | None = None
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"transform": np.asarray(self.transform).tolist(), "registered": self.registered,
                "metric": self.metric, "seconds": self.seconds}


def same_grid(a: Volume, b: Volume, atol_mm: float = 1e-3) -> bool:
    """True when two images share shape and voxel -> world affine (to ``atol_mm``)."""
    return tuple(a.shape[:3]) == tuple(b.shape[:3]) and \
        np.allclose(np.asarray(a.affine, float), np.asarray(b.affine, float), atol=atol_mm)


def coregister(reference: Volume, second: Volume, transform: np.ndarray | None = None, *,
               progress: ProgressCallback | None = None, **options) -> CoRegistered:
    """Bring ``second`` onto ``reference``'s grid (see the module docstring).

    Parameters
    ----------
    reference : Volume
        The first image (the one the segmentation is exported on).
    second : Volume
        The other image (3D; the first volume of a 4D image is used).
    transform : (4, 4) float, optional
        A known second-world -> reference-world matrix (a saved session); no registration.
    progress : callable ``progress(fraction, message)``; may raise ``core.runtime.progress.Cancelled``.
    **options
        Passed to :func:`core.registration.volumes.register_volumes` (e.g. ``levels_mm``).

    Returns
    -------
    CoRegistered
    """
    from core.registration.volumes import register_volumes, resample

    data = np.asarray(second.data)
    if data.ndim == 4:
        data = data[..., 0]
    if data.ndim != 3:
        raise ValueError(f"{second.path or 'second image'}: expected a 3D image, got "
                         f"{data.ndim} dimensions")
    registered, metric, seconds = False, None, 0.0
    if transform is None and same_grid(reference, second):
        report(progress, 1.0, "same grid: no registration needed")
        volume = Volume(np.asarray(data, dtype=np.float32), np.asarray(reference.affine, float),
                        path=second.path)
        return CoRegistered(volume, np.eye(4), False)
    if transform is None:
        def sub(fraction: float, message: str = "") -> None:
            report(progress, 0.95 * fraction, f"registering (rigid): {message}")

        result = register_volumes(Volume(data, second.affine), reference, "rigid",
                                  progress=sub, **options)
        transform, registered = result.transform, True
        metric, seconds = float(result.metric), float(result.seconds)
    transform = np.asarray(transform, dtype=np.float64)
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        raise ValueError("the second image's transform must be a finite 4x4 matrix")
    report(progress, 0.96, "resampling onto the first image's grid")
    on_grid = resample(data, second.affine, transform, reference.shape[:3], reference.affine,
                       default=np.nan)
    report(progress, 1.0, "done")
    volume = Volume(on_grid, np.asarray(reference.affine, float), path=second.path)
    return CoRegistered(volume, transform, registered, metric, seconds)


def blend(bottom: np.ndarray, top: np.ndarray, opacity: float) -> np.ndarray:
    """``(1 - opacity) bottom + opacity top`` of two uint8 images (same shape), rounded."""
    a = float(np.clip(opacity, 0.0, 1.0))
    out = (1.0 - a) * bottom.astype(np.float32) + a * top.astype(np.float32)
    return np.rint(out).astype(np.uint8)


def checkerboard_mask(slice_image: SliceImage, size_mm: float) -> np.ndarray:
    """(H, W) bool: True on the squares that show the bottom image, False on the others.

    Squares are ``size_mm`` wide in the slice plane's (U, V) mm coordinates, anchored at
    U = V = 0, so every view and zoom shows one pattern fixed in the world.
    """
    size = float(size_mm)
    if not size > 0:
        raise ValueError(f"checkerboard squares must be larger than 0 mm; got {size_mm}")
    h, w = slice_image.data.shape
    u, v = slice_image.pixel_to_plane(np.arange(w), np.arange(h))
    cols = np.floor(np.asarray(u) / size).astype(np.int64)
    rows = np.floor(np.asarray(v) / size).astype(np.int64)
    return ((rows[:, None] + cols[None, :]) % 2) == 0
