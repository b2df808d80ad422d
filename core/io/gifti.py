"""GIfTI surfaces (.gii): pointset + triangle arrays, through nibabel."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.errors import DataFileError, why
from core.io.atomic import atomic_path
from core.types.trimesh import TriMesh


def load_gifti(path: Path) -> tuple[TriMesh, None]:
    """Read a GIfTI surface (.gii, or gzipped .gii.gz as nilearn ships fsaverage).

    GIfTI has no SPACE tag: coordinates are taken as RAS (the GIfTI convention).
    """
    import nibabel as nib

    try:
        if path.name.lower().endswith(".gz"):
            img: object = nib.gifti.GiftiImage.from_bytes(_gunzip(path))
        else:
            img = nib.load(str(path))
    except DataFileError:
        raise
    except Exception as exc:
        raise DataFileError(path, f"not a readable GIfTI file ({type(exc).__name__}: "
                                  f"{why(exc, path)})") from None
    if not isinstance(img, nib.gifti.GiftiImage):
        raise DataFileError(path, "not a GIfTI image")
    points = img.get_arrays_from_intent("NIFTI_INTENT_POINTSET")
    tris = img.get_arrays_from_intent("NIFTI_INTENT_TRIANGLE")
    if not points:
        raise DataFileError(path, "GIfTI file has no surface (no POINTSET array: labels, shape "
                                  "or time-series data only?)")
    if not tris:
        raise DataFileError(path, "mesh has no triangles (GIfTI file has a POINTSET but no "
                                  "TRIANGLE array)")
    return TriMesh(points[0].data, tris[0].data, path.name), None


def _gunzip(path: Path) -> bytes:
    """The decompressed content, CRC and length checked (gzip.decompress verifies both)."""
    import gzip
    import zlib

    from core.io.limits import DEFLATE_MAX_RATIO, check_declared_size

    raw = path.read_bytes()
    if len(raw) >= 4:  # ISIZE: the uncompressed length modulo 2**32
        check_declared_size(path, int.from_bytes(raw[-4:], "little"), "its uncompressed size",
                            max_ratio=DEFLATE_MAX_RATIO)
    try:
        return gzip.decompress(raw)
    except (gzip.BadGzipFile, EOFError, zlib.error) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip data ({why(exc, path)})") from None


def save_gifti(path: Path, mesh: TriMesh, point_data: dict | None = None, *,
               space: str = "RAS") -> None:
    """Write vertices (float32) and triangles (int32) as a GIfTI surface."""
    import nibabel as nib

    img = nib.gifti.GiftiImage(darrays=[
        nib.gifti.GiftiDataArray(mesh.vertices.astype(np.float32), intent="NIFTI_INTENT_POINTSET"),
        nib.gifti.GiftiDataArray(mesh.faces.astype(np.int32), intent="NIFTI_INTENT_TRIANGLE"),
    ])
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))
