"""A structure's label map: the fitted surface voxelised on the image grid, plus manual edits.

The model gives the segmentation (``core.geometry.segmentation.voxelize``: voxel centres inside the
closed surface); where the user insists, a brush adds voxels and an eraser removes them, as in
ITK-SNAP's and 3D Slicer's paint tools. The edits are kept *apart* from the model's result
(:class:`ManualEdits`: the voxels painted in and the voxels erased), so that they survive every
refit, are saved with the session, and are reported in exports as manual edits: the exported
label map is ``(model | added) & ~erased`` and a second map marks 1 = added by hand,
2 = erased by hand.

The brush is round, of radius ``r`` mm in the slice plane, and one voxel thick: it covers the
voxels whose centres lie within ``r`` of the cursor in the plane and within half the slice
spacing of the plane (:func:`brush_voxels`), i.e. what the user sees painted on that slice.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.geometry.segmentation import mask_volume_mm3, voxelize

__all__ = ["ManualEdits", "brush_voxels", "structure_label_map", "mask_volume_mm3"]


def _flat(values: Any) -> np.ndarray:
    return np.unique(np.asarray(values, dtype=np.int64).reshape(-1))


def _runs(flat: np.ndarray) -> list[list[int]]:
    """Sorted unique indices -> ``[[start, length], ...]`` (compact for brush strokes)."""
    if len(flat) == 0:
        return []
    breaks = np.flatnonzero(np.diff(flat) != 1) + 1
    starts = np.concatenate([[0], breaks])
    lengths = np.diff(np.concatenate([starts, [len(flat)]]))
    return [[int(flat[s]), int(n)] for s, n in zip(starts, lengths)]


def _from_runs(runs: Any, size: int, what: str) -> np.ndarray:
    runs = np.asarray(runs, dtype=np.int64).reshape(-1, 2) if len(runs) else \
        np.zeros((0, 2), dtype=np.int64)
    if np.any(runs[:, 1] < 1) or np.any(runs[:, 0] < 0) or \
            np.any(runs[:, 0] + runs[:, 1] > size):
        msg = f"manual edits: {what} voxels outside the image grid"
        raise ValueError(msg)
    if len(runs) == 0:
        return np.zeros(0, dtype=np.int64)
    total = int(runs[:, 1].sum())
    offsets = np.arange(total) - np.repeat(np.cumsum(runs[:, 1]) - runs[:, 1], runs[:, 1])
    return np.unique(np.repeat(runs[:, 0], runs[:, 1]) + offsets)


@dataclass(frozen=True)
class ManualEdits:
    """Voxels painted in (``added``) and erased (``removed``) by hand on one image grid.

    Immutable: :meth:`paint` returns a new object (so undo can keep the old one).

    Attributes
    ----------
    shape : (3,) tuple of int
        The image grid.
    added, removed : (A,), (R,) int64 ndarray
        Sorted, disjoint flat (C-order) voxel indices.
    """

    shape: tuple[int, int, int]
    added: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    removed: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "added", _flat(self.added))
        object.__setattr__(self, "removed", _flat(self.removed))

    def __bool__(self) -> bool:
        return bool(len(self.added) or len(self.removed))

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def paint(self, voxels: np.ndarray, erase: bool = False) -> ManualEdits:
        """These flat voxel indices painted in (or erased): the latest stroke wins."""
        voxels = _flat(voxels)
        if len(voxels) and (voxels[0] < 0 or voxels[-1] >= self.size):
            msg = f"voxel index outside the image grid {self.shape}"
            raise ValueError(msg)
        if erase:
            return ManualEdits(self.shape, np.setdiff1d(self.added, voxels, assume_unique=True),
                               np.union1d(self.removed, voxels))
        return ManualEdits(self.shape, np.union1d(self.added, voxels),
                           np.setdiff1d(self.removed, voxels, assume_unique=True))

    def apply(self, mask: np.ndarray, label: int = 1) -> np.ndarray:
        """``(mask | added) & ~removed`` as a new uint8 map with ``label`` inside."""
        mask = np.asarray(mask)
        if mask.shape != self.shape:
            msg = f"label map of shape {mask.shape} for edits on a {self.shape} grid"
            raise ValueError(msg)
        out = (mask != 0).astype(np.uint8).reshape(-1)
        out[self.added] = 1
        out[self.removed] = 0
        return (out * np.uint8(label)).reshape(self.shape)

    def edit_map(self) -> np.ndarray:
        """uint8 grid: 1 where voxels were added by hand, 2 where erased by hand, else 0."""
        out = np.zeros(self.size, dtype=np.uint8)
        out[self.added] = 1
        out[self.removed] = 2
        return out.reshape(self.shape)

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (runs ``[start, length]`` of flat indices) for session files."""
        return {"shape": list(self.shape), "added": _runs(self.added),
                "removed": _runs(self.removed)}

    @classmethod
    def from_json(cls, data: dict[str, Any], shape: Sequence[int] | None = None) -> ManualEdits:
        """Read :meth:`to_json`'s dict; ``shape`` (the image's) must match the stored one."""
        stored = tuple(int(s) for s in data.get("shape", ()))
        if len(stored) != 3 or min(stored) < 1:
            msg = f"manual edits: bad grid shape {data.get('shape')!r}"
            raise ValueError(msg)
        if shape is not None and tuple(int(s) for s in shape) != stored:
            msg = (f"manual edits were painted on a {stored} grid but the image is "
                   f"{tuple(shape)}")
            raise ValueError(msg)
        size = int(np.prod(stored))
        added = _from_runs(data.get("added", []), size, "added")
        removed = _from_runs(data.get("removed", []), size, "erased")
        return cls(stored, np.setdiff1d(added, removed), removed)


def brush_voxels(shape: Sequence[int], affine: np.ndarray, center: np.ndarray,
                 normal: np.ndarray, radius_mm: float, thickness_mm: float) -> np.ndarray:
    """Flat indices of the voxels a round brush covers on one slice.

    Voxel centres ``x`` with ``|(x - center) . n| <= thickness_mm / 2`` and in-plane distance
    ``|| (x - center) - ((x - center) . n) n || <= radius_mm`` (world mm; ``n`` the unit slice
    normal). A brush smaller than a voxel still covers the voxel under the cursor.
    """
    affine = np.asarray(affine, dtype=np.float64)
    size = np.asarray(shape, dtype=np.int64)
    center = np.asarray(center, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    inverse = np.linalg.inv(affine)
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    reach = float(radius_mm) + float(spacing.max())
    c = inverse[:3, :3] @ center + inverse[:3, 3]
    half = np.ceil(reach / spacing).astype(np.int64)
    lo = np.maximum(np.floor(c).astype(np.int64) - half, 0)
    hi = np.minimum(np.ceil(c).astype(np.int64) + half, size - 1)
    if np.any(hi < lo):
        return np.zeros(0, dtype=np.int64)
    grid = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)],
                                indexing="ij"), axis=-1).reshape(-1, 3)
    d = grid @ affine[:3, :3].T + affine[:3, 3] - center
    along = d @ n
    in_plane = np.linalg.norm(d - along[:, None] * n, axis=1)
    inside = (np.abs(along) <= thickness_mm / 2 + 1e-9) & (in_plane <= radius_mm + 1e-9)
    if not inside.any():  # tiny brush: the voxel under the cursor
        nearest = np.clip(np.rint(c).astype(np.int64), 0, size - 1)
        return np.ravel_multi_index(tuple(nearest[:, None]), tuple(size))
    return np.ravel_multi_index(tuple(grid[inside].T), tuple(size))


def structure_label_map(vertices: np.ndarray | None, faces: np.ndarray | None,
                        shape: Sequence[int], affine: np.ndarray,
                        edits: ManualEdits | None = None, label: int = 1) -> np.ndarray:
    """The label map a user sees and exports: the surface voxelised, with the manual edits."""
    if vertices is None or faces is None:
        mask = np.zeros(tuple(int(s) for s in shape), dtype=np.uint8)
    else:
        mask = voxelize(vertices, faces, shape, affine, label=1)
    if edits:
        mask = edits.apply(mask)
    return mask * np.uint8(label) if label != 1 else mask

