"""Mesh topology and operators on (vertices, faces) numpy arrays: edges, graph, Laplacian, checks.

The shared toolbox of the algorithm modules (fairing in correspondence, the graph gradient of
the local-support factorisation, mesh checks). Normals, closest points and other metric
geometry are in :mod:`core.geometry.toolkit`. Everything is vectorised;
sparse operators are ``scipy.sparse`` CSR matrices. Shapes: vertices (N, 3) float, faces (F, 3)
int.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from core.geometry.toolkit import SurfaceProjector, face_normals, vertex_normals


def _directed_edges(faces: np.ndarray) -> np.ndarray:
    """The three directed edges (0->1, 1->2, 2->0) of every face, (3F, 2), face-major per corner."""
    faces = np.asarray(faces)
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def edge_table(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The one edge count of the code base.

    Returns the unique undirected edges (E, 2) with i < j, the number of triangles using each
    (E,), and for every face the indices of its edges 01, 12, 20 (F, 3).
    """
    e = np.sort(_directed_edges(faces), axis=1).astype(np.int64)
    if len(e) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.int64)
    # One int64 key per edge: a 1-D unique is many times faster than unique(axis=0).
    n = int(e.max()) + 1
    keys, inverse, counts = np.unique(e[:, 0] * n + e[:, 1], return_inverse=True,
                                      return_counts=True)
    uniq = np.column_stack([keys // n, keys % n])
    return uniq, counts, inverse.reshape(-1).reshape(3, -1).T


def edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2), each with i < j."""
    return edge_table(faces)[0]


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


def n_components(faces: np.ndarray, n_vertices: int) -> int:
    """Number of connected pieces of the mesh graph (isolated unused vertices ignored)."""
    used = np.unique(faces)
    a = adjacency(faces, n_vertices)[used][:, used]
    return int(connected_components(a, directed=False)[0])


def euler_characteristic(n_vertices: int, faces: np.ndarray) -> int:
    """V - E + F of the mesh (2 - 2 genus for one closed surface)."""
    return int(n_vertices) - len(edges(faces)) + len(faces)


def boundary_edges(faces: np.ndarray) -> np.ndarray:
    """Edges used by exactly one triangle (B, 2); empty for a closed (watertight) surface."""
    uniq, counts, _ = edge_table(faces)
    return uniq[counts == 1]


def is_closed(faces: np.ndarray) -> bool:
    """True when every edge is shared by exactly two triangles."""
    return bool(np.all(edge_table(faces)[1] == 2))


def is_consistently_oriented(faces: np.ndarray) -> bool:
    """True when no directed edge is used twice (neighbouring faces traverse it oppositely)."""
    directed = _directed_edges(faces)
    return len(np.unique(directed, axis=0)) == len(directed)


def vertex_fans(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Fan label of every face corner (F, 3): corners of one vertex joined across the
    manifold edges (two triangles) through it; a manifold vertex has all its corners in one fan.

    The labels are global (0 .. n_fans - 1); a vertex whose corners have several labels is a
    non-manifold vertex (two surfaces touching at a point, or a fin's edge).
    """
    faces = np.asarray(faces, dtype=np.int64)
    n_f = len(faces)
    _, counts, face_edges = edge_table(faces)
    # Per face and edge slot (01, 12, 20): the corner slots of the edge's two ends.
    ends = np.array([[0, 1], [1, 2], [2, 0]])
    fe = face_edges.reshape(-1)
    face_of = np.repeat(np.arange(n_f), 3)
    slot = np.tile(np.arange(3), n_f)
    manifold = counts[fe] == 2
    order = np.argsort(fe[manifold], kind="stable")
    pair_face = face_of[manifold][order].reshape(-1, 2)
    pair_slot = slot[manifold][order].reshape(-1, 2)
    row_parts, col_parts = [], []
    for end in (0, 1):  # join the corners of each end vertex in the two faces
        ca = pair_face[:, 0] * 3 + ends[pair_slot[:, 0], end]
        va = faces[pair_face[:, 0], ends[pair_slot[:, 0], end]]
        # the same vertex's corner in the other face: whichever end of its slot it is
        other = ends[pair_slot[:, 1]]
        in_b = np.where(faces[pair_face[:, 1], other[:, 0]] == va, other[:, 0], other[:, 1])
        row_parts.append(ca)
        col_parts.append(pair_face[:, 1] * 3 + in_b)
    rows, cols = np.concatenate(row_parts), np.concatenate(col_parts)
    graph = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n_f, 3 * n_f))
    return connected_components(graph, directed=False)[1].reshape(n_f, 3)


def topology(faces: np.ndarray, n_vertices: int) -> dict:
    """Counts of a mesh's topology defects and its Euler characteristic and pieces:
    ``open_edges`` (one triangle), ``non_manifold_edges`` (three or more),
    ``non_manifold_vertices`` (several fans), ``misoriented_edges`` (a directed edge used
    twice), ``pieces``, ``euler``, and ``genus`` (of one closed manifold piece, else None)."""
    faces = np.asarray(faces, dtype=np.int64)
    _, counts, _ = edge_table(faces)
    fans = vertex_fans(faces, n_vertices)
    n_fans = len(np.unique(fans))
    used = len(np.unique(faces))
    directed = _directed_edges(faces)
    misoriented = len(directed) - len(np.unique(directed, axis=0))
    euler = euler_characteristic(used, faces)
    out: dict[str, int | None] = {
        "open_edges": int((counts == 1).sum()), "non_manifold_edges": int((counts > 2).sum()),
        "non_manifold_vertices": int(n_fans - used), "misoriented_edges": int(misoriented),
        "pieces": n_components(faces, n_vertices), "euler": int(euler)}
    clean = not (out["open_edges"] or out["non_manifold_edges"] or out["non_manifold_vertices"]
                 or out["misoriented_edges"]) and out["pieces"] == 1
    out["genus"] = (2 - euler) // 2 if clean else None
    return out


def is_closed_manifold(faces: np.ndarray, n_vertices: int) -> bool:
    """One closed, 2-manifold (every edge on two triangles, every vertex one fan), consistently
    oriented surface."""
    return topology(faces, n_vertices)["genus"] is not None


def volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume (mm^3) of a closed, consistently oriented surface (divergence theorem)."""
    v = vertices[faces]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def mean_edge_length(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Mean length of the unique edges."""
    e = edges(faces)
    return float(np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1).mean())


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


def fair_mesh(vertices: np.ndarray, faces: np.ndarray, target: SurfaceProjector, *,
              rest_vertices: np.ndarray | None = None, iterations: int = 10,
              step: float = 0.5) -> np.ndarray:
    """Parametrisation-invariant fairing of a mesh lying on a target surface.

    Each iteration: ``delta = L V - L V_rest`` (uniform Laplacian, sparse), keep only its
    tangential part (remove the component along the vertex normals), move ``V += step * delta``
    and project the vertices back onto the target surface. With ``rest_vertices`` None the rest
    Laplacian coordinates are zero (plain tangential smoothing to a uniform distribution);
    with a reference shape as rest shape, the reference's vertex distribution is
    restored (the pipeline passes the rigidly posed reference). Shape is kept by the
    projection; only the parametrisation changes.

    Parameters
    ----------
    vertices : (N, 3) float
    faces : (F, 3) int
    target : SurfaceProjector
    rest_vertices : (N, 3) float, optional

    Returns
    -------
    (N, 3) float
        Faired vertices, on the target surface.
    """
    lap: sp.csr_matrix = uniform_laplacian(faces, len(vertices))
    rest = np.zeros_like(vertices) if rest_vertices is None else lap @ rest_vertices
    v = np.array(vertices, dtype=np.float64)
    for _ in range(int(iterations)):
        normals = vertex_normals(v, faces)
        delta = lap @ v - rest
        delta -= np.einsum("ij,ij->i", delta, normals)[:, None] * normals
        v, _ = target(v + step * delta)
    return v
