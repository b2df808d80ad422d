"""GIfTI surfaces (.gii): pointset + triangle arrays, through nibabel."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.io.atomic import atomic_path
from core.io.errors import DataFileError, why
from core.types.trimesh import TriMesh


def load_gifti(path: Path) -> TriMesh:
    import nibabel as nib

    try:
        img = nib.load(str(path))
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
    return TriMesh(points[0].data, tris[0].data, path.name)


def save_gifti(path: Path, mesh: TriMesh, point_data: dict | None = None) -> None:
    """Write vertices (float32) and triangles (int32) as a GIfTI surface."""
    import nibabel as nib

    img = nib.gifti.GiftiImage(darrays=[
        nib.gifti.GiftiDataArray(mesh.vertices.astype(np.float32), intent="NIFTI_INTENT_POINTSET"),
        nib.gifti.GiftiDataArray(mesh.faces.astype(np.int32), intent="NIFTI_INTENT_TRIANGLE"),
    ])
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))
