"""Mesh operators on (vertices, faces) numpy arrays: normals, edges, graph and Laplacians.

The shared toolbox of the algorithm modules (fairing in correspondence, the graph gradient of
the local-support factorisation, normals for anisotropic fitting). Everything is vectorised;
sparse operators are ``scipy.sparse`` CSR matrices. Shapes: vertices (N, 3) float, faces (F, 3)
int.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


def face_normals(vertices: np.ndarray, faces: np.ndarray, normalize: bool = True) -> np.ndarray:
    """Per-face normals (F, 3); area-weighted (twice the area) when ``normalize`` is False."""
    v = vertices[faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    if normalize:
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return n


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals (N, 3), the area-weighted mean of the adjacent face normals.

    Outward for a closed surface whose faces are consistently oriented counter-clockwise
    seen from outside.
    """
    fn = face_normals(vertices, faces, normalize=False)
    n = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2), each with i < j."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.sort(e, axis=1)
    return np.unique(e, axis=0)


def adjacency(faces: np.ndarray, n_vertices: int, weights: np.ndarray | None = None) -> sp.csr_matrix:
    """Symmetric vertex adjacency (N, N); entry (i, j) is the edge weight (default 1)."""
    e = edges(faces)
    w = np.ones(len(e)) if weights is None else np.asarray(weights, dtype=np.float64)
    a = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([e[:, 0], e[:, 1]]),
                                                np.concatenate([e[:, 1], e[:, 0]]))),
                      shape=(n_vertices, n_vertices))
    return a.tocsr()


def uniform_laplacian(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Umbrella operator L = D^-1 A - I (N, N): (L x)_i = mean of neighbours - x_i."""
    a = adjacency(faces, n_vertices)
    deg = np.asarray(a.sum(axis=1)).ravel()
    inv = sp.diags(1.0 / np.maximum(deg, 1.0))
    return (inv @ a - sp.identity(n_vertices)).tocsr()


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """Cotangent-weight Laplacian (N, N), negative semi-definite, rows summing to zero."""
    v = vertices[faces]
    n = len(vertices)
    weights = []
    rows, cols = [], []
    for k in range(3):
        i, j, o = faces[:, (k + 1) % 3], faces[:, (k + 2) % 3], k
        a = v[:, (k + 1) % 3] - v[:, o]
        b = v[:, (k + 2) % 3] - v[:, o]
        cot = np.einsum("ij,ij->i", a, b) / np.maximum(np.linalg.norm(np.cross(a, b), axis=1), 1e-12)
        weights.append(0.5 * cot)
        rows.append(i)
        cols.append(j)
    w = np.concatenate(weights)
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    w_mat = sp.coo_matrix((np.concatenate([w, w]), (np.concatenate([r, c]), np.concatenate([c, r]))),
                          shape=(n, n)).tocsr()
    return (w_mat - sp.diags(np.asarray(w_mat.sum(axis=1)).ravel())).tocsr()


def n_components(faces: np.ndarray, n_vertices: int) -> int:
    """Number of connected pieces of the mesh graph (isolated unused vertices ignored)."""
    used = np.unique(faces)
    a = adjacency(faces, n_vertices)[used][:, used]
    return int(connected_components(a, directed=False)[0])


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """Edges used by exactly one triangle (B, 2); empty for a closed (watertight) surface."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(e, axis=0, return_counts=True)
    return uniq[counts == 1]


def is_closed(faces: np.ndarray) -> bool:
    """True when every edge is shared by exactly two triangles."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume (mm^3) of a closed, consistently oriented surface (divergence theorem)."""
    v = vertices[faces]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def mean_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean length of the unique edges."""
    e = edges(faces)
    return float(np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1).mean())


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray,
                                c: np.ndarray) -> np.ndarray:
    """Closest point on triangle (a, b, c) to each point p; all (..., 3), broadcast.

    Voronoi-region test of Ericson, Real-Time Collision Detection, section 5.1.5.
    """
    ab, ac, ap = b - a, c - a, p - a
    d1 = np.einsum("...i,...i", ab, ap)
    d2 = np.einsum("...i,...i", ac, ap)
    bp = p - b
    d3 = np.einsum("...i,...i", ab, bp)
    d4 = np.einsum("...i,...i", ac, bp)
    cp = p - c
    d5 = np.einsum("...i,...i", ab, cp)
    d6 = np.einsum("...i,...i", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    denom = np.where(np.abs(denom) < 1e-300, 1e-300, denom)
    v = vb / denom
    wgt = vc / denom
    out = a + ab * v[..., None] + ac * wgt[..., None]  # interior
    # Edges (later assignments win in the order the regions are exclusive).
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    on_bc = (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)
    out = np.where(on_ab[..., None], a + ab * np.nan_to_num(t_ab)[..., None], out)
    out = np.where(on_ac[..., None], a + ac * np.nan_to_num(t_ac)[..., None], out)
    out = np.where(on_bc[..., None], b + (c - b) * np.nan_to_num(t_bc)[..., None], out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    return out


def surface_problems(vertices: np.ndarray, faces: np.ndarray) -> list[str]:
    """Warnings about a readable mesh that may spoil correspondence or modelling.

    Lists vertices in no triangle, an open surface, several separate pieces and degenerate
    (zero-area) triangles; an empty list means none was found.
    """
    problems = []
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    if not used.all():
        problems.append(f"{int((~used).sum())} vertices in no triangle")
    n_boundary = len(boundary_edges(faces))
    if n_boundary:
        problems.append(f"open surface ({n_boundary} boundary edges)")
    pieces = n_components(faces, len(vertices))
    if pieces > 1:
        problems.append(f"{pieces} separate pieces")
    area = np.linalg.norm(face_normals(vertices, faces, normalize=False), axis=1)
    degenerate = int((area <= 1e-12 * max(float(area.max(initial=0.0)), 1e-300)).sum())
    if degenerate:
        problems.append(f"{degenerate} degenerate triangles")
    return problems
