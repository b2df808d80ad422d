"""Voxelise a closed triangle surface into a label map on an image's voxel grid.

The fitted surface (world RAS mm) becomes a uint8 mask on the grid of the image it was drawn
on, saved with that image's affine so 3D Slicer and ITK-SNAP open it aligned. Oblique and
anisotropic affines are handled exactly: the mesh is mapped into continuous voxel-index space
(``inverse(affine)``), where the grid is the integer lattice.

Method (vectorised ray parity): for every triangle, the voxel columns (i, j) whose centre
line along k crosses it are enumerated from its (i, j) bounding box and tested with 2D edge
functions; the crossing depth k_c is interpolated with the barycentric weights. A crossing
toggles every voxel centre with k > k_c, so a cumulative sum along k modulo 2 labels the
voxels inside (the even-odd rule; valid for a closed surface, also with several components or
cavities). Ray positions are offset by a tiny irrational fraction of a voxel so that no ray
passes exactly through a mesh edge or vertex (which would count a crossing twice). Work is
limited to the mesh's bounding box. Cost: O(F + crossings + box voxels).
"""

from __future__ import annotations

import numpy as np

_RAY_OFFSET = (1.7e-5 * np.sqrt(2.0), 1.3e-5 * np.sqrt(3.0))


def voxelize(vertices: np.ndarray, faces: np.ndarray, shape, affine: np.ndarray | None = None,
             label: int = 1) -> np.ndarray:
    """Label map (I, J, K) uint8 of the voxels whose centres lie inside the closed surface.

    Parameters
    ----------
    vertices : (N, 3) float array
        Surface vertices in world coordinates (mm).
    faces : (F, 3) int array
        Triangles; the surface should be closed (watertight).
    shape : (3,) ints, or a ``core.io.Volume``
        Grid size; with a Volume, its shape and affine are used.
    affine : (4, 4) array
        Voxel index -> world transform (required unless ``shape`` is a Volume).
    label : int
        Value written inside (1..255).

    Returns
    -------
    (I, J, K) uint8 ndarray
    """
    if hasattr(shape, "affine") and hasattr(shape, "shape"):
        affine = shape.affine if affine is None else affine
        shape = shape.shape
    if affine is None:
        raise ValueError("voxelize needs the image affine (or a Volume)")
    shape = tuple(int(s) for s in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"grid shape must be 3 positive sizes, got {shape}")
    if not 1 <= int(label) <= 255:
        raise ValueError("label must be in 1..255")
    affine = np.asarray(affine, dtype=np.float64)
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if not np.all(np.isfinite(vertices)):
        raise ValueError("surface vertices contain NaN or infinite values")
    out = np.zeros(shape, dtype=np.uint8)
    if len(faces) == 0:
        return out

    inv = np.linalg.inv(affine)
    ijk = vertices @ inv[:3, :3].T + inv[:3, 3]  # continuous voxel indices
    lo = np.maximum(np.floor(ijk.min(axis=0)).astype(np.int64) - 1, 0)
    hi = np.minimum(np.ceil(ijk.max(axis=0)).astype(np.int64) + 1, np.array(shape) - 1)
    if np.any(hi < lo):
        return out  # the surface lies outside the grid
    box = hi - lo + 1
    tri = ijk[faces] - lo  # (F, 3 corners, 3) in box coordinates
    ti, tj, tk = tri[..., 0], tri[..., 1], tri[..., 2]
    di, dj = _RAY_OFFSET
    # columns (i, j) with centre (i + di, j + dj) inside each triangle's (i, j) bounding box
    i0 = np.maximum(np.ceil(ti.min(axis=1) - di).astype(np.int64), 0)
    i1 = np.minimum(np.floor(ti.max(axis=1) - di).astype(np.int64), box[0] - 1)
    j0 = np.maximum(np.ceil(tj.min(axis=1) - dj).astype(np.int64), 0)
    j1 = np.minimum(np.floor(tj.max(axis=1) - dj).astype(np.int64), box[1] - 1)
    width = np.maximum(j1 - j0 + 1, 0)
    counts = np.maximum(i1 - i0 + 1, 0) * width
    total = int(counts.sum())
    if total == 0:
        return out
    face_id = np.repeat(np.arange(len(faces)), counts)
    local = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
    w = width[face_id]
    ci = i0[face_id] + local // w
    cj = j0[face_id] + local % w
    px, py = ci + di, cj + dj
    ax, ay, az = ti[face_id, 0], tj[face_id, 0], tk[face_id, 0]
    bx, by, bz = ti[face_id, 1], tj[face_id, 1], tk[face_id, 1]
    cx, cy, cz = ti[face_id, 2], tj[face_id, 2], tk[face_id, 2]
    # 2D edge functions (twice the signed sub-triangle areas)
    wa = (bx - px) * (cy - py) - (cx - px) * (by - py)
    wb = (cx - px) * (ay - py) - (ax - px) * (cy - py)
    wc = (ax - px) * (by - py) - (bx - px) * (ay - py)
    area = wa + wb + wc
    inside = (((wa >= 0) & (wb >= 0) & (wc >= 0)) | ((wa <= 0) & (wb <= 0) & (wc <= 0))) & (
        np.abs(area) > 1e-14)
    if not inside.any():
        return out
    ci, cj = ci[inside], cj[inside]
    kc = (wa[inside] * az[inside] + wb[inside] * bz[inside] + wc[inside] * cz[inside]) / area[inside]
    first = np.clip(np.floor(kc).astype(np.int64) + 1, 0, box[2])  # first voxel centre above
    toggles = np.zeros((box[0], box[1], box[2] + 1), dtype=np.int32)
    np.add.at(toggles, (ci, cj, first), 1)
    mask = (np.cumsum(toggles[:, :, :-1], axis=2) % 2).astype(bool)
    out[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1][mask] = label
    return out


def mask_volume_mm3(mask: np.ndarray, affine: np.ndarray) -> float:
    """Volume (mm^3) of the non-zero voxels of a label map with the given affine."""
    return float(np.count_nonzero(mask) * abs(np.linalg.det(np.asarray(affine)[:3, :3])))
