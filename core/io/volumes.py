"""Volumes: the suffix dispatch for every image format (NIfTI in :mod:`core.io.nifti`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import core.io.nifti  # noqa: F401  (registers .nii and .nii.gz)
from core.io.errors import DataFileError, require_file
from core.io.registry import file_suffix, lookup, suffixes
from core.types.volume import Volume


def load_volume(path: str | os.PathLike) -> Volume:
    """Read a 3D image; the reader is chosen by suffix (see :func:`core.io.nifti.load_nifti`).

    Raises
    ------
    DataFileError
        Not found, empty, unknown suffix, or whatever the format's reader refuses.
    """
    path = require_file(path)
    fmt = lookup(path, "volume")
    if fmt is None or fmt.read is None:
        raise DataFileError(path, f"not a NIfTI file name (expected "
                                  f"{' or '.join(suffixes('volume'))}, got "
                                  f"'{file_suffix(path) or path.name}')")
    return fmt.read(path)


def save_volume(path: str | os.PathLike, data: np.ndarray, affine: np.ndarray) -> None:
    """Write a 3D array with its voxel -> world affine; format by suffix."""
    path = Path(path)
    fmt = lookup(path, "volume")
    if fmt is None or fmt.write is None:
        raise DataFileError(path, f"volumes are written as {' or '.join(suffixes('volume'))}")
    fmt.write(path, data, affine)
