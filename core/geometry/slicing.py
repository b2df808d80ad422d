"""Cross-sections of a triangle mesh with a plane: segments and ordered contour polylines.

Used by the slice views (the model's outline in an axial/coronal/sagittal/oblique slice) and
by the simulated user of the evaluation (``core.evaluation.simulated_user``), which samples points
along the contours of a true surface in a few slice planes.

Method: signed distances d_v = (v - origin) . n of every vertex; a vertex with d_v >= 0
counts as "above" (so vertices lying exactly on the plane are handled without special
cases). A triangle whose vertices are not all on one side is cut along its two sign-changing
edges, at p = v_a + t (v_b - v_a), t = d_a / (d_a - d_b). Each segment is oriented along
n x n_face, so for a closed, outward-oriented surface every contour runs counter-clockwise
seen from the tip of ``normal``. Segments are linked into polylines through the mesh edge
they cut (an exact, topological linking: no distance threshold).

Shapes: vertices (N, 3) float, faces (F, 3) int, segments (S, 2, 3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.geometry.toolkit import face_normals


@dataclass
class Section:
    """Raw result of a plane/mesh intersection.

    Attributes
    ----------
    segments : (S, 2, 3) float ndarray
        Oriented segments (start, end).
    faces : (S,) int ndarray
        The triangle each segment lies in.
    keys : (S, 2) int ndarray
        Topological id of each end point: the cut mesh edge (or the vertex, for a vertex
        lying on the plane). Equal keys mean the same point.
    """

    segments: np.ndarray
    faces: np.ndarray
    keys: np.ndarray


def _unit(normal: np.ndarray) -> np.ndarray:
    normal = np.asarray(normal, dtype=np.float64).reshape(3)
    length = np.linalg.norm(normal)
    if not np.isfinite(length) or length < 1e-12:
        raise ValueError("the plane normal must be a finite, non-zero 3-vector")
    return normal / length


def section(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray,
            normal: np.ndarray) -> Section:
    """Intersect the mesh with the plane through ``origin`` with normal ``normal``.

    Returns the oriented segments with the faces they lie in and their end-point keys
    (see :class:`Section`). Degenerate zero-length pieces (a triangle touching the plane
    at one vertex) are dropped; a triangle edge lying in the plane is reported once.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    n = _unit(normal)
    n_vertices = len(vertices)
    dist = (vertices - np.asarray(origin, dtype=np.float64).reshape(3)) @ n
    above = dist >= 0.0
    side = above[faces]  # (F, 3)
    n_above = side.sum(axis=1)
    cut = (n_above == 1) | (n_above == 2)
    cut_faces = np.flatnonzero(cut)
    empty = Section(np.zeros((0, 2, 3)), np.zeros(0, np.int64), np.zeros((0, 2), np.int64))
    if cut_faces.size == 0:
        return empty
    tri = faces[cut_faces]  # (C, 3)
    s = side[cut_faces]
    # The lone vertex (the one on the minority side) is at position k; the two cut edges
    # are (lone, k+1) and (lone, k+2).
    lone_is_above = s.sum(axis=1) == 1
    lone = np.where(lone_is_above, np.argmax(s, axis=1), np.argmin(s, axis=1))
    rows = np.arange(len(tri))
    a = tri[rows, lone]
    b = tri[rows, (lone + 1) % 3]
    c = tri[rows, (lone + 2) % 3]

    def cut_point(i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        di, dj = dist[i], dist[j]
        t = di / (di - dj)  # di and dj have different "above" flags, so di != dj
        p = vertices[i] + t[:, None] * (vertices[j] - vertices[i])
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        key = n_vertices + lo * n_vertices + hi
        # A vertex exactly on the plane: the point is that vertex, keyed by it.
        key = np.where(di == 0.0, i, np.where(dj == 0.0, j, key))
        return p, key

    p0, k0 = cut_point(a, b)
    p1, k1 = cut_point(a, c)
    keep = k0 != k1
    p0, p1, k0, k1, cut_faces = p0[keep], p1[keep], k0[keep], k1[keep], cut_faces[keep]
    # Orient along n x n_face (counter-clockwise around n for an outward closed surface).
    direction = np.cross(n, face_normals(vertices, faces[cut_faces], normalize=False))
    flip = np.einsum("ij,ij->i", p1 - p0, direction) < 0.0
    start = np.where(flip[:, None], p1, p0)
    end = np.where(flip[:, None], p0, p1)
    k_start = np.where(flip, k1, k0)
    k_end = np.where(flip, k0, k1)
    return Section(np.stack([start, end], axis=1), cut_faces, np.stack([k_start, k_end], axis=1))


def intersect_plane(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray,
                    normal: np.ndarray) -> np.ndarray:
    """Segments (S, 2, 3) where the plane (``origin``, ``normal``) cuts the triangle mesh.

    Each segment lies in one triangle; segments are oriented counter-clockwise around
    ``normal`` for a closed, outward-oriented surface. Empty (0, 2, 3) if the plane misses.
    """
    return section(vertices, faces, origin, normal).segments


@dataclass
class Polyline:
    """One connected piece of a cross-section.

    Attributes
    ----------
    points : (L, 3) float ndarray
        Ordered points; for a closed loop the first point is not repeated at the end.
    closed : bool
        True for a closed loop (the usual case for a closed surface).
    """

    points: np.ndarray
    closed: bool

    @property
    def length(self) -> float:
        """Total length in mm (including the closing edge of a loop)."""
        pts = np.vstack([self.points, self.points[:1]]) if self.closed else self.points
        return float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())


def _chains(keys: np.ndarray) -> list[tuple[list[int], bool]]:
    """Order segments (given by their end keys) into chains; returns (segment ids, closed)."""
    next_of: dict[int, int] = {}
    for idx, key in enumerate(keys[:, 0].tolist()):
        next_of.setdefault(key, idx)
    ends = keys[:, 1].tolist()
    starts = keys[:, 0].tolist()
    has_incoming = set(ends)
    used = np.zeros(len(keys), dtype=bool)
    chains: list[tuple[list[int], bool]] = []
    # Open chains first (start keys nobody ends at), then the loops.
    order = [i for i, k in enumerate(starts) if k not in has_incoming] + list(range(len(keys)))
    for first in order:
        if used[first]:
            continue
        chain = [first]
        used[first] = True
        closed = False
        current = first
        while True:
            nxt = next_of.get(ends[current])
            if nxt is None:
                break
            if nxt == first:
                closed = True
                break
            if used[nxt]:
                break
            used[nxt] = True
            chain.append(nxt)
            current = nxt
        chains.append((chain, closed))
    return chains


def polylines(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray,
              normal: np.ndarray) -> list[Polyline]:
    """The plane's cross-section of the mesh as ordered polylines, longest first.

    A closed, manifold surface gives closed loops (one per connected piece of the cut).
    """
    sec = section(vertices, faces, origin, normal)
    if len(sec.segments) == 0:
        return []
    lines = []
    for chain, closed in _chains(sec.keys):
        pts = sec.segments[chain, 0]
        if not closed:
            pts = np.vstack([pts, sec.segments[chain[-1], 1][None]])
        lines.append(Polyline(points=pts, closed=closed))
    lines.sort(key=lambda line: -line.length)
    return lines


def sample_polyline(line: Polyline, spacing: float | None = None,
                    count: int | None = None, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Points at equal arc-length steps along a polyline, with the unit tangent there.

    Give either ``spacing`` (mm) or ``count``. ``offset`` (fraction of one step, 0..1) shifts
    the first sample. Returns (points (P, 3), tangents (P, 3)).
    """
    pts = np.vstack([line.points, line.points[:1]]) if line.closed else line.points
    seg = np.diff(pts, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    total = seg_len.sum()
    if total <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    if count is None:
        if spacing is None or spacing <= 0:
            raise ValueError("give a positive spacing or a count")
        count = max(1, int(np.floor(total / spacing)) + (0 if line.closed else 1))
    step = total / count if line.closed else total / max(count - 1, 1)
    s = (np.arange(count) + offset) * step
    s = np.mod(s, total) if line.closed else np.clip(s, 0.0, total)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = (s - cum[idx]) / np.maximum(seg_len[idx], 1e-300)
    points = pts[idx] + t[:, None] * seg[idx]
    tangents = seg[idx] / np.maximum(seg_len[idx], 1e-300)[:, None]
    return points, tangents
