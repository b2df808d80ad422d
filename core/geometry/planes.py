"""World-aligned slice planes of a volume: resampling, plane <-> world coordinates, labels.

The slice views of the GUI show the image in world coordinates (RAS, mm), whatever the
voxel axes are: an axial view is the plane z = const, seen from above, with patient Right
on the screen's left (radiological convention, as ITK-SNAP and 3D Slicer show it).

A :class:`PlaneFrame` is an orthonormal frame (u = screen right, v = screen up, n = u x v
or its opposite = the slice normal). A point of the plane at offset ``depth = n . x`` has
in-plane coordinates (U, V) = (u . x, v . x) and world position ``U u + V v + depth n``.

:class:`SliceSampler` extracts the slice image on that frame:

- axis-aligned affines (the voxel axes are world axes up to sign and permutation) take a
  plain voxel slice with the right transposition and flips: no interpolation, ~0.1 ms;
- oblique affines are resampled on a world-aligned grid (spacing = the smallest voxel size)
  with trilinear interpolation (``scipy.ndimage.map_coordinates``).

Image rows run from the top of the screen (largest V) down; columns from left (smallest U).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from core.io import Volume

#: Slice planes by the world axis along their normal (0 x: sagittal, 1 y: coronal, 2 z: axial):
#: the one definition of plane name <-> axis (sessions store the index).
PLANE_NAMES = ("sagittal", "coronal", "axial")
PLANE_AXIS = {name: axis for axis, name in enumerate(PLANE_NAMES)}

_AXIS_LETTERS = {(0, 1): "R", (0, -1): "L", (1, 1): "A", (1, -1): "P", (2, 1): "S", (2, -1): "I"}


@dataclass(frozen=True)
class PlaneFrame:
    """Screen axes of a slice view in world coordinates (unit vectors, (3,) each)."""

    name: str
    u: tuple[float, float, float]   # screen right
    v: tuple[float, float, float]   # screen up
    n: tuple[float, float, float]   # slice normal (Page Up moves along +n)

    @property
    def axes(self) -> np.ndarray:
        """(3, 3) rows u, v, n."""
        return np.array([self.u, self.v, self.n], dtype=np.float64)

    def to_plane(self, xyz: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> (U, V, depth) (..., 3)."""
        return np.asarray(xyz, dtype=np.float64) @ self.axes.T

    def to_world(self, uvd: np.ndarray) -> np.ndarray:
        """(U, V, depth) (..., 3) -> world points (..., 3)."""
        return np.asarray(uvd, dtype=np.float64) @ self.axes

    def depth(self, xyz: np.ndarray) -> np.ndarray:
        return np.asarray(xyz, dtype=np.float64) @ np.asarray(self.n)

    def edge_labels(self) -> dict[str, str]:
        """Anatomical letters at the screen edges: {'left', 'right', 'top', 'bottom'}."""
        return {"right": direction_letter(self.u), "left": direction_letter(-np.asarray(self.u)),
                "top": direction_letter(self.v), "bottom": direction_letter(-np.asarray(self.v))}


def direction_letter(d: ArrayLike) -> str:
    """Anatomical letter (R L A P S I) of the dominant component of world direction ``d``."""
    v = np.asarray(d, dtype=np.float64)
    axis = int(np.argmax(np.abs(v)))
    return _AXIS_LETTERS[(axis, 1 if v[axis] > 0 else -1)]


# Radiological convention: patient Right on screen left, anterior/superior up; sagittal with
# anterior on the left (nose pointing left), as in ITK-SNAP and 3D Slicer.
AXIAL = PlaneFrame("axial", (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
CORONAL = PlaneFrame("coronal", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0))
SAGITTAL = PlaneFrame("sagittal", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
FRAMES = {f.name: f for f in (AXIAL, CORONAL, SAGITTAL)}


@dataclass
class SliceImage:
    """One resampled slice.

    Attributes
    ----------
    data : (H, W) float32 ndarray
        Intensities; row 0 at the top (largest V), column 0 at the left (smallest U).
        NaN outside the volume (oblique case only).
    u0, v0 : float
        U of column 0 and V of row 0 (pixel centres, mm).
    du, dv : float
        Pixel size along U and V (mm, > 0); V decreases by ``dv`` per row.
    depth : float
        Depth (n . x) of the plane actually sampled (snapped to a voxel centre when aligned).
    inside : bool
        False when the plane misses the volume (data is then all NaN or empty).
    """

    data: np.ndarray
    u0: float
    v0: float
    du: float
    dv: float
    depth: float
    inside: bool = True

    def pixel_to_plane(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional pixel (column, row) -> (U, V) mm (pixel centres at integer indices)."""
        return self.u0 + np.asarray(col) * self.du, self.v0 - np.asarray(row) * self.dv

    def extent(self) -> tuple[float, float, float, float]:
        """(U_left, U_right, V_top, V_bottom) of the outer pixel edges, mm."""
        h, w = self.data.shape
        return (self.u0 - self.du / 2, self.u0 + (w - 0.5) * self.du,
                self.v0 + self.dv / 2, self.v0 - (h - 0.5) * self.dv)


class SliceSampler:
    """Extract world-aligned slices of one volume (see module docstring).

    Parameters
    ----------
    volume : Volume
    """

    def __init__(self, volume: Volume):
        self.volume = volume
        self.affine = np.asarray(volume.affine, dtype=np.float64)
        self.inverse = np.linalg.inv(self.affine)
        self.spacing = volume.spacing
        self.data = np.asarray(volume.data)
        self.shape = np.array(self.data.shape)
        direction = self.affine[:3, :3] / self.spacing
        self.world_axis_of_voxel = np.argmax(np.abs(direction), axis=0)      # (3,) per voxel axis
        self.sign_of_voxel = np.sign(direction[self.world_axis_of_voxel, np.arange(3)])
        self.aligned = not volume.is_oblique and len(set(self.world_axis_of_voxel.tolist())) == 3
        self.voxel_of_world_axis = np.argsort(self.world_axis_of_voxel)      # inverse permutation

    def step(self, frame: PlaneFrame) -> float:
        """Slice spacing along the frame's normal (mm)."""
        if self.aligned:
            world_axis = int(np.argmax(np.abs(frame.n)))
            return float(self.spacing[self.voxel_of_world_axis[world_axis]])
        return float(self.spacing.min())

    def snap_depth(self, frame: PlaneFrame, depth: float) -> float:
        """Depth of the nearest voxel-centre plane (aligned volumes); ``depth`` unchanged otherwise."""
        if not self.aligned:
            return float(depth)
        world_axis = int(np.argmax(np.abs(frame.n)))
        j = self.voxel_of_world_axis[world_axis]
        sign_n = np.sign(frame.n[world_axis])
        # world coordinate along the axis of voxel index k: affine[w, j] * k + affine[w, 3]
        coord = sign_n * depth
        k = np.rint((coord - self.affine[world_axis, 3]) / self.affine[world_axis, j])
        return float(sign_n * (self.affine[world_axis, j] * k + self.affine[world_axis, 3]))

    def depth_range(self, frame: PlaneFrame) -> tuple[float, float]:
        """Smallest and largest depth of the volume's voxel centres along the frame's normal."""
        corners = np.array(np.meshgrid(*[[0, s - 1] for s in self.shape], indexing="ij"))
        world = corners.reshape(3, -1).T @ self.affine[:3, :3].T + self.affine[:3, 3]
        depth = world @ np.asarray(frame.n)
        return float(depth.min()), float(depth.max())

    def sample(self, frame: PlaneFrame, depth: float) -> SliceImage:
        """The slice at ``depth`` (n . x, mm) on ``frame``."""
        if self.aligned:
            return self._sample_aligned(frame, depth)
        return self._sample_oblique(frame, depth)

    def _sample_aligned(self, frame: PlaneFrame, depth: float) -> SliceImage:
        axes = frame.axes
        world_axes = np.argmax(np.abs(axes), axis=1)           # world axis of u, v, n
        signs = np.sign(axes[np.arange(3), world_axes])
        ju, jv, jn = (int(self.voxel_of_world_axis[w]) for w in world_axes)
        wn = world_axes[2]
        coord = signs[2] * depth
        k = int(np.rint((coord - self.affine[wn, 3]) / self.affine[wn, jn]))
        snapped = float(signs[2] * (self.affine[wn, jn] * k + self.affine[wn, 3]))
        k_in = 0 <= k < self.shape[jn]
        index = [slice(None)] * 3
        index[jn] = min(max(k, 0), self.shape[jn] - 1)
        plane = self.data[tuple(index)]                          # remaining axes in voxel order
        rest = [j for j in range(3) if j != jn]
        # want array [row (v), col (u)]
        plane = plane if rest == [jv, ju] else plane.T
        # column increases along +u when voxel index increases along +u
        col_forward = signs[0] * self.sign_of_voxel[ju] > 0
        row_forward = signs[1] * self.sign_of_voxel[jv] < 0     # rows go down the screen (-v)
        plane = plane[:, ::1 if col_forward else -1][::1 if row_forward else -1, :]
        origin = self.affine[:3, 3]
        du, dv = float(self.spacing[ju]), float(self.spacing[jv])

        def along(axis_row: int, j: int, idx: int) -> float:
            world = origin + self.affine[:3, j] * idx
            return float(axes[axis_row] @ world)

        u0 = along(0, ju, 0 if col_forward else self.shape[ju] - 1)
        v0 = along(1, jv, 0 if row_forward else self.shape[jv] - 1)
        data = np.ascontiguousarray(plane, dtype=np.float32)
        if not k_in:
            data = np.full_like(data, np.nan)
        return SliceImage(data, u0, v0, du, dv, snapped, inside=bool(k_in))

    def _sample_oblique(self, frame: PlaneFrame, depth: float) -> SliceImage:
        axes = frame.axes
        corners = np.array(np.meshgrid(*[[-0.5, s - 0.5] for s in self.shape], indexing="ij"))
        world = corners.reshape(3, -1).T @ self.affine[:3, :3].T + self.affine[:3, 3]
        uv = world @ axes[:2].T
        step = float(self.spacing.min())
        u_lo, v_lo = uv.min(axis=0) + step / 2
        u_hi, v_hi = uv.max(axis=0) - step / 2
        n_u = max(int(np.floor((u_hi - u_lo) / step)) + 1, 1)
        n_v = max(int(np.floor((v_hi - v_lo) / step)) + 1, 1)
        us = u_lo + step * np.arange(n_u)
        vs = v_hi - step * np.arange(n_v)
        return self._sample_grid(axes, depth, us, vs, step)

    def _sample_grid(self, axes: np.ndarray, depth: float, us: np.ndarray, vs: np.ndarray,
                     step: float) -> SliceImage:
        """Trilinear samples at world points U u + V v + depth n for the grid us x vs."""
        # voxel index = inverse(U u + V v + depth n), affine in (U, V): three broadcast planes
        lin, off = self.inverse[:3, :3], self.inverse[:3, 3]
        base, along_u, along_v = lin @ (depth * axes[2]) + off, lin @ axes[0], lin @ axes[1]
        coords = [(base[c] + along_v[c] * vs[:, None] + along_u[c] * us[None, :]).reshape(-1)
                  for c in range(3)]
        values = ndimage.map_coordinates(self.data, coords, order=1, mode="constant", cval=np.nan,
                                         prefilter=False, output=np.float32)
        data = values.reshape(len(vs), len(us))
        inside = bool(np.any(np.isfinite(data)))
        return SliceImage(data, float(us[0]), float(vs[0]), step, step, float(depth), inside)

    def sample_patch(self, frame: PlaneFrame, centre: np.ndarray, half_size: float,
                     step: float | None = None) -> SliceImage:
        """A square patch of any (also oblique) plane ``frame`` through world point ``centre``,
        ``2 half_size`` mm wide, sampled every ``step`` mm (default: the smallest voxel size),
        trilinear; NaN outside the volume. For views orthogonal to a trajectory."""
        axes = frame.axes
        step = float(self.spacing.min()) if step is None else float(step)
        u_c, v_c, depth = axes @ np.asarray(centre, dtype=np.float64)
        n = max(int(round(2 * half_size / step)), 1) + 1
        offsets = step * (np.arange(n) - (n - 1) / 2)
        return self._sample_grid(axes, depth, u_c + offsets, v_c - offsets, step)


def frame_along(direction: np.ndarray, name: str = "probe") -> PlaneFrame:
    """A slice frame orthogonal to ``direction`` (e.g. a trajectory, entry -> target), shown
    like an axial view: normal n = -direction (towards the entry), screen up = the anterior
    direction made orthogonal to n (superior if the direction is nearly anterior-posterior),
    screen right = n x up (the patient's left for a vertical trajectory, as radiological
    axial views show it)."""
    d = np.asarray(direction, dtype=np.float64)
    n = -d / np.linalg.norm(d)
    up = np.array([0.0, 1.0, 0.0])
    if abs(up @ n) > 0.9:
        up = np.array([0.0, 0.0, 1.0])
    v = up - (up @ n) * n
    v /= np.linalg.norm(v)
    u = np.cross(n, v)
    return PlaneFrame(name, tuple(u), tuple(v), tuple(n))


def window_to_uint8(values: np.ndarray, window: float, level: float) -> np.ndarray:
    """Map intensities to 0..255 grey levels for a display window (width) centred at level.

    NaN (outside the volume) maps to 0.
    """
    width = max(float(window), 1e-6)
    low = float(level) - width / 2
    scaled = (np.nan_to_num(values, nan=low) - low) * (255.0 / width)
    return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)


def auto_window(data: np.ndarray, low_pct: float = 1.0, high_pct: float = 99.5,
                max_samples: int = 200_000) -> tuple[float, float]:
    """(window, level) covering the ``low_pct``..``high_pct`` percentiles of the non-zero voxels."""
    flat = np.asarray(data).reshape(-1)
    if flat.size > max_samples:
        flat = flat[:: flat.size // max_samples]
    flat = flat[np.isfinite(flat)]
    nonzero = flat[flat != 0]
    sample = nonzero if nonzero.size > 100 else flat
    if sample.size == 0:
        return 1.0, 0.5
    low, high = np.percentile(sample, [low_pct, high_pct])
    if high <= low:
        high = low + 1.0
    return float(high - low), float((high + low) / 2)


def contour_normals(points: np.ndarray, plane_normal: np.ndarray) -> np.ndarray:
    """In-plane normals of an ordered contour drawn on a slice, (K, 3), unit length.

    The tangent at each point is the central difference of its neighbours (one-sided at the
    ends of an open contour); the normal is ``tangent x plane_normal``, i.e. perpendicular to
    the contour within the slice. Its sign is chosen to point away from the contour's
    centroid on average (outwards for a contour drawn around a structure). A single point
    has no tangent: its row is NaN.

    Parameters
    ----------
    points : (K, 3) ndarray
        Contour points in drawing order, all in one slice.
    plane_normal : (3,) ndarray
        Normal of the slice plane.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(plane_normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    k = len(points)
    if k < 2:
        return np.full((k, 3), np.nan)
    tangent = np.empty_like(points)
    tangent[1:-1] = points[2:] - points[:-2]
    tangent[0] = points[1] - points[0]
    tangent[-1] = points[-1] - points[-2]
    normal = np.cross(tangent, n)
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.full_like(normal, np.nan), where=length > 1e-12)
    outward = points - points.mean(axis=0)
    valid = np.all(np.isfinite(normal), axis=1)
    if valid.any() and np.sum(np.einsum("ij,ij->i", normal[valid], outward[valid])) < 0:
        normal = -normal
    return normal


def slice_contour_normals(points: np.ndarray, slice_ids: np.ndarray, plane_normals: np.ndarray,
                          surface: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """In-plane normals of contour points drawn on several slices, (P, 3); NaN = unknown.

    Each slice's points (same ``slice_ids``, in drawing order) get :func:`contour_normals`.
    With ``surface`` = (vertices (N, 3), vertex normals (N, 3)) of the current fit, each
    slice's sign is instead the one agreeing with the surface normals at the points' nearest
    vertices (majority vote): right also for an open stroke along one side of a structure,
    where the centroid rule of :func:`contour_normals` is ambiguous.

    Parameters
    ----------
    points : (P, 3) ndarray
        Contour points, world mm, in drawing order.
    slice_ids : (P,) int ndarray
        Which slice each point was drawn on (any labels).
    plane_normals : (P, 3) ndarray
        Normal of each point's slice plane.
    surface : tuple of two (N, 3) ndarrays, optional
        Vertices and unit vertex normals of the surface that orients the normals.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    slice_ids = np.asarray(slice_ids).reshape(-1)
    plane_normals = np.asarray(plane_normals, dtype=np.float64).reshape(-1, 3)
    out = np.full((len(points), 3), np.nan)
    if len(points) == 0:
        return out
    nearest = None
    if surface is not None:
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(np.asarray(surface[0], dtype=np.float64)).query(points)
        surface_normals = np.asarray(surface[1], dtype=np.float64)
    for label in np.unique(slice_ids):
        idx = np.flatnonzero(slice_ids == label)
        normals = contour_normals(points[idx], plane_normals[idx[0]])
        if nearest is not None:
            agree = np.nansum(np.einsum("ij,ij->i", normals, surface_normals[nearest[idx]]))
            if agree < 0:
                normals = -normals
        out[idx] = normals
    return out


def _plane_fit(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares plane of (K, 3) points: unit normal, offset n.x, max |distance|."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=True)
    normal = vt[-1]
    distance = (points - centre) @ normal
    return normal, float(normal @ centre), float(np.abs(distance).max())


def group_coplanar(points: np.ndarray, tolerance_mm: float = 0.5
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split points listed contour by contour into the planes they were drawn on.

    Consecutive points stay in one group while they all lie within ``tolerance_mm`` of their
    least-squares plane (any orientation); a point off that plane starts the next group. A
    group's first point that lies on the previous group's plane as well (contours on
    crossing planes meet on a line) is given to the group whose plane it fits after the
    split. Groups of fewer than three points get the plane of their neighbours when they fit
    it, else the plane through them normal to the smallest spread.

    Parameters
    ----------
    points : (P, 3) ndarray
        Points in file order (world mm).
    tolerance_mm : float
        Largest distance from a group's plane.

    Returns
    -------
    labels : (P,) int ndarray
        Group of each point, 0..G-1 in file order.
    normals : (G, 3) ndarray
        Unit plane normal of each group (sign: largest component positive).
    offsets : (G,) ndarray
        ``normal . x`` of the plane of each group.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    starts = [0]
    i = 0
    while i < n:
        j = i + 1
        while j < n and (j + 1 - i < 4 or _plane_fit(points[i:j + 1])[2] <= tolerance_mm):
            j += 1
        # points i..j-1 are coplanar; with fewer than 4 the plane is not yet pinned down,
        # so the run is cut where a 4-point window stops being planar
        if j < n:
            starts.append(j)
        i = j
    labels = np.zeros(n, dtype=np.int64)
    for g, start in enumerate(starts):
        labels[start:] = g
    # a boundary point fitting the next group's plane better goes there
    for g in range(1, len(starts)):
        first, last = starts[g], starts[g + 1] if g + 1 < len(starts) else n
        prev = np.flatnonzero(labels == g - 1)
        if len(prev) > 3 and last - first >= 3:
            nxt, off, _ = _plane_fit(points[first:last])
            if abs(points[prev[-1]] @ nxt - off) <= tolerance_mm:
                labels[prev[-1]] = g
    groups = np.unique(labels)
    labels = np.searchsorted(groups, labels)
    normals = np.zeros((len(groups), 3))
    offsets = np.zeros(len(groups))
    for g in range(len(groups)):
        normal, offset, _ = _plane_fit(points[labels == g]) if np.sum(labels == g) >= 3 else \
            (np.array([0.0, 0.0, 1.0]), float(points[labels == g][0, 2]), 0.0)
        if normal[np.argmax(np.abs(normal))] < 0:
            normal, offset = -normal, -offset
        normals[g], offsets[g] = normal, offset
    return labels, normals, offsets
