"""The 3D image type: voxel values with their voxel -> world (RAS, mm) affine.

Read and written by :mod:`core.io.volumes`; used by segmentation, slicing and the GUI.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class NiftiOrientation:
    """The two orientation records of a NIfTI header, kept so that an image written on
    the grid of another (a label map) gets exactly that image's header.

    ITK (and so ITK-SNAP and 3D Slicer) and nibabel do not always pick the same one of the
    two (nibabel: sform when its code is set; ITK: the qform unless the sform code is 1 in
    some versions), so a mask is only seen on its image in every viewer when both records
    and their codes are copied. Codes: 0 unknown, 1 scanner, 2 aligned, 3 Talairach, 4 MNI.
    """

    sform: np.ndarray
    sform_code: int
    qform: np.ndarray
    qform_code: int
    pixdim: np.ndarray  # pixdim[0:4] as stored (qfac and voxel sizes)


@dataclass
class Volume:
    """A 3D image with its voxel -> world (RAS, mm) affine.

    Attributes
    ----------
    data : (I, J, K) ndarray
        Voxel values, indexed [i, j, k].
    affine : (4, 4) float ndarray
        Maps homogeneous voxel indices (i, j, k, 1) to world RAS mm (column vectors).
    path : Path or None
        Where it was read from.
    orientation : NiftiOrientation or None
        The sform/qform records of the NIfTI file it was read from (None otherwise).
    """

    data: np.ndarray
    affine: np.ndarray
    path: Path | None = None
    orientation: NiftiOrientation | None = None

    def __post_init__(self) -> None:
        self.affine = np.asarray(self.affine, dtype=np.float64)
        if self.data.ndim != 3:
            raise ValueError(f"a volume must be 3D, got shape {self.data.shape}")
        if self.affine.shape != (4, 4) or abs(np.linalg.det(self.affine[:3, :3])) < 1e-12:
            raise ValueError("the affine must be an invertible 4x4 matrix")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.data.shape)  # type: ignore[return-value]

    @property
    def spacing(self) -> np.ndarray:
        """Voxel size along i, j, k in mm (column norms of the affine), (3,)."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def orientation_known(self) -> bool:
        """False for a NIfTI file with neither sform nor qform (both codes 0): its affine is
        nibabel's voxel-size-only fallback, so left and right cannot be told apart."""
        o = self.orientation
        return o is None or o.sform_code > 0 or o.qform_code > 0

    @property
    def is_oblique(self) -> bool:
        """True when the voxel axes are not aligned with the world axes."""
        direction = self.affine[:3, :3] / self.spacing
        return bool(np.any(np.abs(np.abs(direction).max(axis=0) - 1.0) > 1e-6))

    def voxel_to_world(self, ijk: np.ndarray) -> np.ndarray:
        """Map voxel indices (..., 3) (fractional allowed) to world RAS mm (..., 3)."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ self.affine[:3, :3].T + self.affine[:3, 3]

    def world_to_voxel(self, xyz: np.ndarray) -> np.ndarray:
        """Map world RAS mm (..., 3) to fractional voxel indices (..., 3)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        inv = np.linalg.inv(self.affine)
        return xyz @ inv[:3, :3].T + inv[:3, 3]

    def contains_voxel(self, ijk: np.ndarray) -> np.ndarray:
        """Whether rounded voxel indices (..., 3) fall inside the grid, (...,) bool."""
        idx = np.rint(np.asarray(ijk)).astype(np.int64)
        return np.all((idx >= 0) & (idx < np.array(self.shape)), axis=-1)

    def value_at(self, xyz: np.ndarray) -> float | None:
        """Intensity of the voxel nearest to world point ``xyz`` (3,), None if outside."""
        ijk = np.rint(self.world_to_voxel(xyz)).astype(np.int64)
        if not self.contains_voxel(ijk):
            return None
        return float(self.data[tuple(ijk)])

    def world_bounds(self) -> np.ndarray:
        """Axis-aligned world bounding box of the voxel centres, (2, 3): min and max."""
        corners = np.array(np.meshgrid(*[[0, s - 1] for s in self.shape], indexing="ij"))
        pts = self.voxel_to_world(corners.reshape(3, -1).T)
        return np.stack([pts.min(axis=0), pts.max(axis=0)])

    def axis_codes(self) -> tuple[str, str, str]:
        """nibabel-style orientation codes of the voxel axes, e.g. ('R', 'A', 'S')."""
        import nibabel as nib

        return tuple(nib.aff2axcodes(self.affine))
