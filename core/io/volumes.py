"""Volumes: the suffix dispatch for every image format.

NIfTI in :mod:`core.io.nifti`; NRRD/NHDR and MetaImage (MHA/MHD) in :mod:`core.io.itk_image`
and :mod:`core.io.nrrd` (with 3D Slicer's ``.seg.nrrd``: one with overlapping layers opens as
one map of segment numbers, with a note; :func:`core.io.nrrd.read_segmentation` gives each
segment whole); DICOM series in
:mod:`core.io.dicom` (a folder, a ``.dcm`` file, or any file with the DICOM marker).
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable
from pathlib import Path
from typing import cast

import numpy as np

import core.io.dicom  # noqa: F401  (registers .dcm)
import core.io.itk_image  # noqa: F401  (registers .mha, .mhd)
import core.io.nifti  # noqa: F401  (registers .nii and .nii.gz)
import core.io.nrrd  # noqa: F401  (registers .nrrd, .seg.nrrd, .nhdr)
from core.errors import DataFileError, require_file, warnings_as_notes
from core.io.registry import file_suffix, lookup, suffixes
from core.types.volume import Volume


def is_dicom_path(path: str | os.PathLike) -> bool:
    """Whether ``path`` is read as a DICOM series: a folder, or a file that is not one of the
    other image formats and has a ``.dcm`` name or the DICOM marker (DICOM files often have
    no extension)."""
    path = Path(path)
    fmt = lookup(path, "volume")
    if fmt is not None:
        return fmt.suffix == ".dcm"  # a folder named like another format is refused as a folder
    return path.is_dir() or (path.is_file() and core.io.dicom.is_dicom_file(path))


def load_volume(path: str | os.PathLike, series: str | None = None,
                notify: Callable[[str], None] | None = None) -> Volume:
    """Read a 3D image; the reader is chosen by suffix (see :func:`core.io.nifti.load_nifti`).

    A DICOM folder or file (:func:`is_dicom_path`) is read by :func:`core.io.dicom.read_dicom`:
    ``series`` picks a SeriesInstanceUID, and ``notify(message)`` is told which series was
    taken when a folder holds several and ``series`` is None.

    Raises
    ------
    DataFileError
        Not found, empty, unknown suffix, or whatever the format's reader refuses.
    """
    if Path(path).exists() and is_dicom_path(path):
        return core.io.dicom.read_dicom(path, series=series, notify=notify)
    path = require_file(path)
    if series is not None:
        raise DataFileError(path, "a series UID applies to a DICOM folder or file only")
    fmt = lookup(path, "volume")
    if fmt is None or fmt.read is None:
        raise DataFileError(path, f"not an image file name (expected "
                                  f"{', '.join(suffixes('volume'))} or a DICOM folder; got "
                                  f"'{file_suffix(path) or path.name}')")
    try:
        with warnings_as_notes(path):
            return cast(Volume, fmt.read(path))
    except MemoryError:
        raise DataFileError(path, "not enough memory to read this image") from None


def save_volume(path: str | os.PathLike, data: np.ndarray, affine: np.ndarray, *,
                like: Volume | None = None) -> None:
    """Write a 3D array with its voxel -> world affine; format by suffix.

    ``like``: the image the array lies on (for a label map): its header's orientation
    records are reused where the format has them (see :func:`core.io.nifti.save_nifti`).
    """
    path = Path(path)
    fmt = lookup(path, "volume")
    if fmt is None or fmt.write is None:
        writable = [s for s in suffixes("volume")
                    if (known := lookup(Path("x" + s), "volume")) is not None and known.write]
        raise DataFileError(path, f"volumes are written as {', '.join(writable)}")
    if like is not None and "like" in inspect.signature(fmt.write).parameters:
        fmt.write(path, data, affine, like=like)
    else:
        fmt.write(path, data, affine)
