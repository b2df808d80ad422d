"""Grooming of raw training meshes before correspondence.

Real meshes cut from segmentations are messy: duplicated vertices (STL), a stray island of
a few voxels, a small hole, flipped triangles, and very different resolutions (a 14-vertex
tiny structure next to a 5,000-vertex large one). Each step here fixes one of those and says
what it did, so that the per-shape report can show it:

1. weld duplicated vertices, drop unused vertices and degenerate or repeated triangles;
2. split non-manifold edges and vertices (:func:`split_non_manifold`: every fan of triangles
   around a vertex gets its own vertex, so sheets glued along an edge or touching at a point
   come apart and a fin comes off as a piece of its own);
3. keep the largest connected piece (by area), reporting the dropped pieces; a mesh whose
   dropped part is a large share of its area (``max_dropped_share``) is refused;
4. fill holes small against the mesh: boundary loops up to ``max_hole_perimeter`` (0.3) of
   the bounding box diagonal around, or up to ``max_hole_edges`` edges (by default
   max(6, sqrt(N) / 2) for N vertices), with a triangle or a fan around the loop's centroid;
5. make the orientation consistent (flip faces to agree with their neighbours, breadth-first
   over the manifold edges) and outward (positive enclosed volume); refuse, saying why, what
   is still not one closed, oriented 2-manifold (:func:`core.geometry.mesh.topology`);
6. remove small handles (:func:`remove_small_handles`: thinner than about one mean edge
   length, found by voxelising the surface and repairing the mask as ``mesh-labels`` does);
7. remesh to a target vertex count with an even density (:func:`remesh`: linear subdivision
   while too coarse, quadric decimation to the target, Garland & Heckbert, SIGGRAPH 1997, in
   VTK, then tangential relaxation projected onto the input surface, the same fairing as
   the correspondence step with a uniform rest state).

The target density is common to all shapes, reference included, so the model's resolution
does not depend on which subject is the reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, connected_components

from core.geometry import mesh as meshops
from core.geometry.toolkit import SurfaceProjector, face_normals
from core.types import TriMesh

REMESH_ATTEMPTS = 5  # decimations tried by :func:`remesh` before it gives up on a clean result

DEFAULT_GROOMING: dict[str, Any] = {
    "largest_piece": True,
    "fill_holes": True,
    "fix_orientation": True,
    "remesh": True,
    "vertices": 2000,           # target vertex count of every groomed mesh
    "max_dropped_share": 0.25,  # refuse when more of the area than this is not in the largest piece
    "repair_non_manifold": True,
    "remove_small_handles": True,  # handles thinner than about one mean edge length
    "max_hole_edges": None,     # loops up to this many edges are filled (None: max(6, sqrt(N) / 2))
    "max_hole_perimeter": 0.3,  # ... and loops up to this share of the bounding box diagonal
    "keep_tessellation_above": None,  # an input with at least this share of ``vertices``
    # keeps its own tessellation (None: every input is remeshed). The correspondence batch
    # sets 0.5 and remeshes only the reference (issue 27: the targets' remesh took away the
    # density cue CPD matched; inputs.remesh_reference).
}


class GroomingError(ValueError):
    """A mesh grooming cannot make usable (the message says why)."""


@dataclass
class GroomReport:
    """What grooming did to one mesh (JSON-ready through :meth:`to_dict`)."""

    input_vertices: int = 0
    output_vertices: int = 0
    welded_vertices: int = 0
    removed_degenerate_faces: int = 0
    dropped_pieces: int = 0
    dropped_vertices: int = 0
    dropped_area_share: float = 0.0
    non_manifold_edges: int = 0
    non_manifold_vertices: int = 0
    removed_non_manifold_faces: int = 0
    split_vertices: int = 0
    filled_holes: int = 0
    open_boundary_edges: int = 0
    genus: int | None = None
    removed_handles: int = 0
    flipped_faces: int = 0
    turned_outward: bool = False
    remeshed: bool = False
    notes: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, list) else v) for k, v in self.__dict__.items()}


def describe(report: dict) -> str:
    """What grooming did to one mesh, in one short line ("" when it changed nothing), from a
    :meth:`GroomReport.to_dict` (as stored in ``correspondence.json``)."""
    done = []
    if report.get("dropped_pieces"):
        share = 100 * report.get("dropped_area_share", 0.0)
        done.append(f"dropped {report['dropped_pieces']} piece{'s' if report['dropped_pieces'] > 1 else ''}"
                    f" ({f'{share:.0f}%' if share >= 0.5 else '<1%'} of the area)")
    if report.get("filled_holes"):
        done.append(f"filled {report['filled_holes']} hole{'s' if report['filled_holes'] > 1 else ''}")
    if report.get("split_vertices"):
        done.append(f"split {report.get('non_manifold_edges', 0)} non-manifold edges and "
                    f"{report.get('non_manifold_vertices', 0)} vertices")
    if report.get("removed_non_manifold_faces"):
        done.append(f"removed {report['removed_non_manifold_faces']} triangles on non-manifold edges")
    if report.get("removed_handles"):
        done.append(f"removed {report['removed_handles']} small handle"
                    f"{'s' if report['removed_handles'] > 1 else ''}")
    if report.get("welded_vertices"):
        done.append(f"welded {report['welded_vertices']} vertices")
    if report.get("removed_degenerate_faces"):
        done.append(f"removed {report['removed_degenerate_faces']} degenerate or duplicate triangles")
    if report.get("flipped_faces"):
        done.append(f"reoriented {report['flipped_faces']} triangles")
    if report.get("turned_outward"):
        done.append("turned outward")
    if report.get("remeshed"):
        done.append(f"remeshed {report.get('input_vertices')} -> {report.get('output_vertices')} vertices")
    return "; ".join(done)


def weld(vertices: np.ndarray, faces: np.ndarray, tol: float | None = None
         ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Merge coincident vertices, drop degenerate faces and unused vertices.

    Returns (vertices, faces, n welded, n degenerate faces removed).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    extent = float(np.ptp(v, axis=0).max()) if len(v) else 1.0
    tol = 1e-7 * max(extent, 1e-300) if tol is None else tol
    keys = np.round(v / tol).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep the vertices in their input order
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    welded = len(v) - len(first)
    f = rank[inverse.reshape(-1)][f]
    v = v[first[order]]
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    ok &= np.linalg.norm(face_normals(v, f, normalize=False), axis=1) > 0
    # Duplicate triangles (same three vertices) count once.
    _, uniq = np.unique(np.sort(f[ok], axis=1), axis=0, return_index=True)
    kept = f[ok][np.sort(uniq)]
    removed = len(f) - len(kept)
    v, kept = compact(v, kept)
    return v, kept, welded, removed


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices used by no face; renumber the faces."""
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(vertices)[used], remap[faces]


def largest_piece(vertices: np.ndarray, faces: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, int, int, float]:
    """The connected piece of largest area: (vertices, faces, pieces dropped, vertices
    dropped, dropped share of the area)."""
    n = len(vertices)
    n_pieces, labels = connected_components(meshops.adjacency(faces, n), directed=False)
    face_label = labels[faces[:, 0]]
    area = 0.5 * np.linalg.norm(face_normals(vertices, faces, normalize=False), axis=1)
    per_piece = np.bincount(face_label, weights=area, minlength=n_pieces)
    used_pieces = np.unique(face_label)
    if len(used_pieces) <= 1:
        return vertices, faces, 0, 0, 0.0
    keep = int(np.argmax(per_piece))
    kept_faces = faces[face_label == keep]
    share = 1.0 - float(per_piece[keep] / max(per_piece.sum(), 1e-300))
    v, f = compact(vertices, kept_faces)
    return v, f, len(used_pieces) - 1, len(np.unique(faces)) - len(v), share


def split_non_manifold(vertices: np.ndarray, faces: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Split a mesh into a 2-manifold with boundary: every fan of triangles around a vertex
    (joined across edges of exactly two triangles, :func:`core.geometry.mesh.vertex_fans`) gets its
    own copy of the vertex, so that sheets glued along a non-manifold edge (marching cubes
    at voxels touching along an edge: four triangles on it) or touching at a point come
    apart, and a fin comes off as a piece of its own. Triangles on an edge that still has
    three or more after that (rare) are removed, leaving holes for :func:`fill_holes`.
    Returns (vertices, faces, triangles removed, vertices added)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n_faces, n_used = len(f), len(np.unique(f))
    for _ in range(5):
        fans = meshops.vertex_fans(f, len(v))
        _, first = np.unique(fans.ravel(), return_index=True)
        v, f = v[f.ravel()[first]], fans
        _, counts, face_edges = meshops.edge_table(f)
        bad = (counts[face_edges] > 2).any(axis=1)
        if not bad.any():
            break
        f = f[~bad]
        v, f = compact(v, f)
    return v, f, n_faces - len(f), int(len(v) - n_used)


def hole_limit(vertices: np.ndarray, faces: np.ndarray, max_edges: int | None,
               max_perimeter: float) -> tuple[int, float]:
    """The largest hole :func:`fill_holes` closes: (edges, perimeter mm). Edges: ``max_edges``,
    else max(6, sqrt(N) / 2); perimeter: ``max_perimeter`` times the bounding box diagonal."""
    edges = max_edges or max(6, int(round(0.5 * np.sqrt(len(vertices)))))
    diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0))) if len(vertices) else 0.0
    return int(edges), float(max_perimeter) * diagonal


def _perimeter(vertices: np.ndarray, loop: np.ndarray) -> float:
    return float(np.linalg.norm(vertices[loop] - vertices[np.roll(loop, -1)], axis=1).sum())


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed boundary loops (vertex index arrays, in the faces' direction).

    Loops through a vertex with several boundary edges out of it (non-manifold) are skipped.
    """
    _, counts, face_edges = meshops.edge_table(faces)
    directed = meshops._directed_edges(faces)
    on_boundary = counts[face_edges.T.reshape(-1)] == 1
    dir_edges = directed[on_boundary]
    if len(dir_edges) == 0:
        return []
    starts, n_out = np.unique(dir_edges[:, 0], return_counts=True)
    bad = set(starts[n_out > 1].tolist())
    nxt = {a: c for a, c in dir_edges.tolist() if a not in bad}
    loops, seen = [], set()
    for start in list(nxt):  # a loop over the few boundary vertices, not over the mesh
        if start in seen:
            continue
        loop, cur = [], start
        while cur in nxt and cur not in seen:
            seen.add(cur)
            loop.append(cur)
            cur = nxt[cur]
        if cur == start and len(loop) >= 3:
            loops.append(np.array(loop))
    return loops


def fill_holes(vertices: np.ndarray, faces: np.ndarray, max_edges: int,
               max_perimeter: float = 0.0) -> tuple[np.ndarray, np.ndarray, int]:
    """Close boundary loops of at most ``max_edges`` edges or ``max_perimeter`` mm: a triangle
    loop by one triangle, a longer one by a fan around its centroid."""
    loops = [loop for loop in boundary_loops(faces)
             if len(loop) <= max_edges or _perimeter(vertices, loop) <= max_perimeter]
    if not loops:
        return vertices, faces, 0
    new_v, new_f = [vertices], [faces]
    n = len(vertices)
    for loop in loops:
        # The loop runs along the faces' own direction; the fill traverses each edge backwards.
        if len(loop) == 3:
            new_f.append(loop[::-1][None])
            continue
        new_v.append(vertices[loop].mean(axis=0)[None])
        new_f.append(np.column_stack([np.roll(loop, -1), loop, np.full(len(loop), n)]))
        n += 1
    return np.vstack(new_v), np.vstack(new_f), len(loops)


def orient(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, int, bool]:
    """Consistent, outward orientation: (faces, faces flipped, whole mesh turned)."""
    faces = np.array(faces)
    e, counts, face_edges = meshops.edge_table(faces)
    manifold = counts == 2
    # The two faces of each manifold edge, and whether they traverse it the same way.
    fe = face_edges.reshape(-1)
    face_of = np.repeat(np.arange(len(faces)), 3)
    corner = np.tile(np.arange(3), len(faces))
    order = np.argsort(fe, kind="stable")
    fe_s, f_s, c_s = fe[order], face_of[order], corner[order]
    starts = np.searchsorted(fe_s, np.flatnonzero(manifold))
    fa, fb = f_s[starts], f_s[starts + 1]
    ca, cb = c_s[starts], c_s[starts + 1]
    first_a = faces[fa, ca]
    first_b = faces[fb, cb]
    same_direction = first_a == first_b  # both go i -> j: one of them must flip
    n_f = len(faces)
    graph = sp.coo_matrix((np.where(same_direction, 2, 1), (fa, fb)), shape=(n_f, n_f)).tocsr()
    graph = (graph + graph.T).tocsr()
    n_comp, comp = connected_components(graph, directed=False)
    flip = np.zeros(n_f, bool)
    for c in range(n_comp):  # one breadth-first tree per connected piece (usually one)
        root = int(np.flatnonzero(comp == c)[0])
        nodes, pred = breadth_first_order(graph, root, directed=False, return_predecessors=True)
        child = nodes[1:]
        # Parity of "same direction" edges on the tree path to the root, by pointer jumping.
        parity = np.zeros(n_f, bool)
        rel = graph[pred[child], child]
        rel = rel.toarray().ravel() if sp.issparse(rel) else np.asarray(rel).ravel()
        parity[child] = rel == 2
        up = np.full(n_f, -1, dtype=np.int64)
        up[child] = pred[child]
        while True:
            live = np.flatnonzero(up >= 0)
            if len(live) == 0:
                break
            anc = up[live]
            parity[live] = parity[live] ^ parity[anc]
            up[live] = up[anc]
        flip[nodes] = parity[nodes]
    n_flipped = int(flip.sum())
    if n_flipped > n_f // 2:
        flip = ~flip
        n_flipped = n_f - n_flipped
    faces[flip] = faces[flip][:, ::-1]
    turned = False
    if meshops.volume(vertices, faces) < 0:
        faces = faces[:, ::-1].copy()
        turned = True
    return faces, n_flipped, turned


def remesh(vertices: np.ndarray, faces: np.ndarray, n_vertices: int, *,
           relax_iterations: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """Closed surface with about ``n_vertices`` vertices of even density, on the input surface.

    Linear subdivision (the shape is unchanged) until there are at least twice as many
    faces as the target needs, quadric decimation with volume preservation to the target,
    then tangential relaxation towards a uniform vertex distribution, each step projected
    back onto the (subdivided) input surface (:func:`core.geometry.mesh.fair_mesh` with no rest
    shape).

    Quadric decimation now and then folds a thin part into a non-manifold edge (a clean,
    closed 1,281-vertex tube came out with one edge on three triangles at a target of 1,200
    and closed at 1,100 and 1,250); a result that is not closed or has another Euler
    characteristic than the input is decimated again to a target 2 % or 4 % off, up to
    :data:`REMESH_ATTEMPTS` times (each also with its folds split and their holes closed,
    :func:`_refold`, which mostly gives the input's topology back); then by
    topology-preserving decimation (vtkDecimatePro; Schroeder, Zarge & Lorensen, SIGGRAPH
    1992), and if that too does not give one closed 2-manifold of the input's Euler
    characteristic, the input is returned as it is. Vertices
    then only move (relaxation), so a closed manifold input gives a closed manifold output.
    """
    import pyvista as pv

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    euler = meshops.euler_characteristic(len(v), f)  # 2 - 2 genus for a closed surface
    target_faces = max(2 * int(n_vertices) - 2 * euler, 8)
    poly = pv.PolyData(v, np.column_stack([np.full(len(f), 3), f]).ravel())
    while poly.n_cells < 2 * target_faces:
        poly = poly.subdivide(1, subfilter="linear")
    dense_v = np.asarray(poly.points, dtype=np.float64)
    dense_f = np.asarray(poly.faces).reshape(-1, 4)[:, 1:]
    for attempt in range(REMESH_ATTEMPTS):
        # targets 0, +2, -2, +4, -4 % off (an even face count each): a fold stays for nearby
        # targets (the tube above: still folded at 4 and 40 faces fewer, closed at 40 more)
        step = 2 * int(round(0.01 * target_faces * ((attempt + 1) // 2)))
        shift = step if attempt % 2 else -step
        reduction = 1.0 - (target_faces + shift) / poly.n_cells
        out = poly.decimate(reduction, volume_preservation=True) if reduction > 0 else poly
        rv, rf = _arrays(out.triangulate())
        if _same_topology(rv, rf, euler):
            break
        rv, rf = _refold(rv, rf)
        if _same_topology(rv, rf, euler):
            break
    else:
        # Topology-preserving decimation (vtkDecimatePro without splitting: no collapse that
        # changes the topology), when every quadric attempt folded the surface.
        rv, rf = _arrays(poly.decimate_pro(1.0 - target_faces / poly.n_cells,
                                           preserve_topology=True, splitting=False,
                                           boundary_vertex_deletion=False).triangulate())
        if not _same_topology(rv, rf, euler):
            return v, f  # the input as it is: a valid surface at its own resolution
    projector = SurfaceProjector(dense_v, dense_f, exact=False, candidates="centroids")
    rv = meshops.fair_mesh(rv, rf, projector, iterations=relax_iterations, step=0.5)
    return rv, rf


def _arrays(poly) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a triangulated pyvista PolyData, unused vertices dropped."""
    rv = np.asarray(poly.points, dtype=np.float64)
    rf = np.asarray(poly.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
    return compact(rv, rf)


def _refold(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A decimation's few folds undone: the non-manifold edges and vertices split
    (:func:`split_non_manifold`), stray bits dropped, the small holes left closed, oriented
    (the caller checks that the topology is the input's)."""
    v, f, _, _ = split_non_manifold(vertices, faces)
    v, f, _, _, _ = largest_piece(v, f)
    v, f, _ = fill_holes(v, f, 12)
    f, _, _ = orient(v, f)
    return v, f


def _same_topology(vertices: np.ndarray, faces: np.ndarray, euler: int) -> bool:
    """One closed, 2-manifold, consistently oriented surface of Euler characteristic ``euler``."""
    check = meshops.topology(faces, len(vertices))
    return check["genus"] is not None and check["euler"] == euler


def needs_remesh(vertices: np.ndarray, faces: np.ndarray, n_vertices: int) -> bool:
    """False when the mesh already has the common density: vertex count within 10% of the
    target and an even spacing (edge-length coefficient of variation below 0.5)."""
    if not 0.9 <= len(vertices) / max(n_vertices, 1) <= 1.1:
        return True
    e = meshops.edges(faces)
    length = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    return bool(length.std() > 0.5 * length.mean())


def remove_small_handles(vertices: np.ndarray, faces: np.ndarray, genus: int
                         ) -> tuple[np.ndarray, np.ndarray, int]:
    """The surface without its handles thinner than about one mean edge length h:
    (vertices, faces, handles removed). The closed surface is voxelised at h
    (``vtkPolyDataToImageStencil`` through pyvista) and the mask repaired as a label's is
    (:func:`core.correspondence.mesh_labels.repair_mask`: one-voxel bridges cut, tunnels filled while there
    are more handles than a 1-voxel opening and closing leave); when that removes handles,
    the repaired mask's smoothed Surface Nets surface replaces the mesh (then remeshed by the
    caller), else the mesh is returned as it is."""
    import pyvista as pv

    from core.correspondence.mesh_labels import mask_surface, repair_mask

    h = meshops.mean_edge_length(vertices, faces)
    poly = pv.PolyData(vertices, np.column_stack([np.full(len(faces), 3), faces]).ravel())
    image = poly.voxelize_binary_mask(spacing=h)
    mask = np.asarray(image.point_data["mask"]).reshape(image.dimensions, order="F") > 0
    if mask.sum() < 27:
        return vertices, faces, 0
    solid, info = repair_mask(mask)
    if info["genus"] is None or info["genus"] >= genus:
        return vertices, faces, 0
    affine = np.eye(4)
    affine[:3, :3] = np.diag(image.spacing)
    affine[:3, 3] = image.origin
    v, f = mask_surface(solid, affine)
    if meshops.topology(f, len(v))["genus"] != info["genus"]:
        return vertices, faces, 0
    return v, f, int(genus - info["genus"])


def _not_closed_reason(vertices: np.ndarray, faces: np.ndarray, check: dict, max_edges: int,
                      max_perimeter: float) -> str:
    """Why a groomed mesh is still not one closed, oriented 2-manifold (one line)."""
    if check["open_edges"]:
        loops = boundary_loops(faces)
        longest = max((_perimeter(vertices, loop) for loop in loops), default=0.0)
        return (f"not a closed surface: {check['open_edges']} boundary edges remain in "
                f"{len(loops)} hole(s), the largest {longest:.1f} mm around (holes up to "
                f"{max_perimeter:.1f} mm or {max_edges} edges are filled)")
    if check["non_manifold_edges"] or check["non_manifold_vertices"]:
        return (f"not a closed surface: {check['non_manifold_edges']} non-manifold edges and "
                f"{check['non_manifold_vertices']} non-manifold vertices remain")
    if check["misoriented_edges"]:
        return "the surface is not orientable (no consistent inside and outside)"
    return f"not one closed surface: {check['pieces']} pieces"


def groom_mesh(mesh: TriMesh, options: dict | None = None) -> tuple[TriMesh, GroomReport]:
    """All grooming steps (module docstring) on one mesh; raises :class:`GroomingError`.

    ``options`` override :data:`DEFAULT_GROOMING`; a step set to False is skipped.
    """
    opt = dict(DEFAULT_GROOMING)
    opt.update(options or {})
    unknown = set(opt) - set(DEFAULT_GROOMING)
    if unknown:
        raise ValueError(f"unknown grooming option(s): {', '.join(sorted(unknown))}")
    report = GroomReport(input_vertices=int(len(mesh.vertices)))
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1:] != (3,) or f.ndim != 2 or f.shape[1:] != (3,) or len(f) == 0:
        raise GroomingError("not a triangle mesh (no faces, or vertices not (N, 3))")
    if f.min() < 0 or f.max() >= len(v):
        raise GroomingError("faces index vertices that do not exist")
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad[np.unique(f)].any():
        raise GroomingError(f"{int(bad.sum())} vertices have NaN or infinite coordinates")
    v, f, report.welded_vertices, report.removed_degenerate_faces = weld(v, f)
    if len(f) < 4:
        raise GroomingError(f"only {len(f)} non-degenerate triangles; a closed surface needs at least 4")
    check = meshops.topology(f, len(v))
    report.non_manifold_edges = check["non_manifold_edges"]
    report.non_manifold_vertices = check["non_manifold_vertices"]
    if opt["repair_non_manifold"] and (report.non_manifold_edges or report.non_manifold_vertices):
        v, f, report.removed_non_manifold_faces, report.split_vertices = split_non_manifold(v, f)
        if len(f) < 4:
            raise GroomingError("nothing is left once the triangles on non-manifold edges are removed")
    if opt["largest_piece"]:
        v, f, report.dropped_pieces, report.dropped_vertices, report.dropped_area_share = \
            largest_piece(v, f)
        if report.dropped_area_share > opt["max_dropped_share"]:
            raise GroomingError(
                f"the largest connected piece has only {100 * (1 - report.dropped_area_share):.0f}% "
                f"of the surface ({report.dropped_pieces + 1} pieces); keeping it would drop too much")
    max_edges, max_perimeter = hole_limit(v, f, opt["max_hole_edges"], opt["max_hole_perimeter"])
    if opt["fill_holes"]:
        v, f, report.filled_holes = fill_holes(v, f, max_edges, max_perimeter)
    report.open_boundary_edges = int(len(meshops.boundary_edges(f)))
    if opt["fix_orientation"]:
        f, report.flipped_faces, report.turned_outward = orient(v, f)
    check = meshops.topology(f, len(v))
    if check["genus"] is None:
        raise GroomingError(_not_closed_reason(v, f, check, max_edges, max_perimeter))
    report.genus = int(check["genus"])
    if opt["remove_small_handles"] and report.genus > 0:
        v, f, report.removed_handles = remove_small_handles(v, f, report.genus)
        report.genus -= report.removed_handles
    if abs(meshops.volume(v, f)) <= 1e-9 * max(float(np.ptp(v, axis=0).max()), 1e-300) ** 3:
        raise GroomingError("the surface encloses no volume (flat or collapsed)")
    keep = opt["keep_tessellation_above"]
    if keep is not None and len(v) >= float(keep) * int(opt["vertices"]):
        pass  # kept as it is: a correspondence target needs no common count
    elif opt["remesh"] and needs_remesh(v, f, int(opt["vertices"])):
        v, f = remesh(v, f, int(opt["vertices"]))
        report.remeshed = True
        if meshops.topology(f, len(v))["genus"] != report.genus:
            raise GroomingError("remeshing did not give one closed 2-manifold surface")
    report.output_vertices = int(len(v))
    return TriMesh(v, f, mesh.name), report
