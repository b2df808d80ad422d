"""The one geometry toolkit (core.geometry.toolkit) and the check that no copy of it reappears."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from core.datasets.factors import ellipsoid_surface as icosphere
from core.geometry import mesh as meshops
from core.geometry import toolkit as geometry

ROOT = Path(__file__).resolve().parents[1]


def _sources() -> list[Path]:
    files = [p for folder in ("core", "app", "benchmarks", "tests", "resources", "scripts")
             for p in (ROOT / folder).rglob("*.py")]
    return [p for p in files if p.name != "test_geometry.py" and ".venv" not in p.parts]


# Routines of the toolkit (and of core.geometry.mesh's edge table): a definition of one of these names,
# with or without a leading underscore, anywhere else is a second copy.
TOOLKIT = {"core/geometry/toolkit.py": ["face_normals", "vertex_normals", "vertex_face_table",
                                "closest_points_on_triangles", "barycentric", "SurfaceProjector",
                                "closest_points_on_surface", "surface_coordinates",
                                "surface_distance", "symmetric_surface_distance", "umeyama",
                                "rodrigues", "rotation_vector", "random_rotation", "skew"],
           "core/geometry/mesh.py": ["edge_table", "edges", "boundary_edges", "is_closed"]}
ALIASES = ["vertex_normals_fast", "rotation_log", "random_rotation", "procrustes_svd",
           "closest_point_on_triangle", "cotangent_laplacian"]

# Fingerprints of the algorithms themselves, whatever the function is called.
FINGERPRINTS = {
    "Rodrigues' formula": re.compile(r"\(1(\.0)? - np\.cos\("),
    "Ericson's closest point on a triangle": re.compile(r"d3 \* d6 - d5 \* d4"),
    "a VTK closest-point locator": re.compile(r"FindClosestPoint\("),
    "per-face edge listing": re.compile(r"faces?\[:, \[0, 1\]\]"),
}


# A benchmark's peer, run side by side with the toolkit's answer, is not a copy in use.
BENCHMARK_PEERS = {"benchmarks/bench_closest_points.py": {"a VTK closest-point locator"}}


def test_no_second_definition_of_a_geometry_routine():
    owners = {name: owner for owner, names in TOOLKIT.items() for name in names}
    offenders = []
    for path in _sources():
        rel = path.relative_to(ROOT).as_posix()
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
                bare = node.name.lstrip("_")
                if (bare in owners and owners[bare] != rel) or \
                        (bare in ALIASES and rel not in TOOLKIT):
                    offenders.append(f"{rel}:{node.lineno} defines {node.name}")
    assert not offenders, "use core.geometry.toolkit / core.geometry.mesh instead: " + "; ".join(offenders)


def test_no_copy_of_a_geometry_algorithm_under_another_name():
    offenders = []
    for path in _sources():
        rel = path.relative_to(ROOT).as_posix()
        if rel in TOOLKIT:
            continue
        text = path.read_text(encoding="utf-8")
        for what, pattern in FINGERPRINTS.items():
            if what in BENCHMARK_PEERS.get(rel, ()):
                continue
            for match in pattern.finditer(text):
                offenders.append(f"{rel}:{text.count(chr(10), 0, match.start()) + 1} ({what})")
    assert not offenders, "semantic copies of core.geometry.toolkit: " + "; ".join(offenders)


def test_vertex_normals_of_a_sphere_are_radial_and_the_subset_path_agrees():
    v, f = icosphere(3, (1.0, 1.0, 1.0))
    n = geometry.vertex_normals(v, f)
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.einsum("ij,ij->i", n, v / np.linalg.norm(v, axis=1, keepdims=True)).min() > 0.999
    at = np.array([0, 5, 17, 300, len(v) - 1])
    table = geometry.vertex_face_table(f, len(v), fill=len(f))
    assert np.allclose(geometry.vertex_normals(v, f, at=at, table=table), n[at], atol=1e-12)


def test_fast_and_exact_projection_agree_with_brute_force_near_the_surface():
    rng = np.random.default_rng(3)
    v, f = icosphere(2, (20.0, 12.0, 8.0))
    queries = v[rng.integers(0, len(v), 200)] + rng.normal(scale=0.8, size=(200, 3))
    tri = v[f]
    brute = geometry.closest_points_on_triangles(queries[:, None], tri[None, :, 0], tri[None, :, 1],
                                                 tri[None, :, 2])
    d_brute = np.linalg.norm(brute - queries[:, None], axis=2).min(axis=1)
    closest, d_exact = geometry.closest_points_on_surface(queries, v, f)
    assert np.allclose(d_exact, d_brute, atol=1e-9)
    assert np.allclose(np.linalg.norm(closest - queries, axis=1), d_exact)
    assert np.allclose(geometry.surface_distance(queries, v, f), d_brute, atol=1e-9)
    tri_idx, bary, points = geometry.surface_coordinates(queries, v, f)
    assert np.allclose(points, closest, atol=1e-9)
    assert np.allclose(bary.sum(axis=1), 1.0) and bary.min() >= 0
    # the fairing loop's projector (first pass over the nearest centroids only): points on
    # the surface, within a small fraction of an edge of the exact distance
    first, d_first = geometry.SurfaceProjector(v, f, exact=False, candidates="centroids")(queries)
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean()
    assert np.all(d_first >= d_brute - 1e-9) and np.abs(d_first - d_brute).max() < 0.05 * edge
    assert np.allclose(np.linalg.norm(first - queries, axis=1), d_first)
    with pytest.raises(ValueError, match="candidates"):
        geometry.SurfaceProjector(v, f, exact=False, candidates="faces")


def test_exact_projection_is_exact_far_from_the_surface_and_refuses_bad_surfaces():
    # The exact projector (libigl's AABB tree): queries far off and inside, against brute
    # force over every triangle; bad surfaces are refused before compiled code reads them.
    rng = np.random.default_rng(4)
    v, f = icosphere(2, (20.0, 12.0, 8.0))
    queries = np.vstack([rng.normal(scale=60.0, size=(100, 3)), rng.normal(scale=3.0, size=(50, 3))])
    tri = v[f]
    brute = geometry.closest_points_on_triangles(queries[:, None], tri[None, :, 0], tri[None, :, 1],
                                                 tri[None, :, 2])
    d_brute = np.linalg.norm(brute - queries[:, None], axis=2).min(axis=1)
    closest, dist, index = geometry.SurfaceProjector(v, f).project(queries)
    assert np.allclose(dist, d_brute, atol=1e-9)
    on_triangle = geometry.closest_points_on_triangles(closest, *(tri[index, j] for j in range(3)))
    assert np.allclose(on_triangle, closest, atol=1e-9)  # the triangle index is the point's
    bad_index = f.copy()
    bad_index[5, 1] = len(v)
    not_finite = v.copy()
    not_finite[3, 0] = np.nan
    for vertices, faces, what in ((v, bad_index, "does not exist"), (not_finite, f, "not finite"),
                                  (v, f[:, :2], "triangle surface"), (v, f[:0], "triangle surface")):
        with pytest.raises(ValueError, match=what):
            geometry.SurfaceProjector(vertices, faces)
    with pytest.raises(ValueError, match="not finite"):
        geometry.SurfaceProjector(v, f).project(np.array([[0.0, np.inf, 0.0]]))


@pytest.mark.parametrize("scaling,reflection", [(True, False), (False, False), (False, True)])
def test_weighted_umeyama_recovers_a_known_transform_despite_outliers(scaling, reflection):
    rng = np.random.default_rng(1)
    src = rng.normal(size=(60, 3)) * [10.0, 5.0, 2.0]
    rot = geometry.random_rotation(rng)
    if reflection:
        rot = rot @ np.diag([1.0, 1.0, -1.0])
    scale = 1.7 if scaling else 1.0
    dst = scale * src @ rot.T + [3.0, -2.0, 8.0]
    weights = np.ones(len(src))
    dst[:5] += rng.normal(scale=50.0, size=(5, 3))  # outliers with zero weight
    weights[:5] = 0.0
    s, r, t = geometry.umeyama(src, dst, weights, scaling=scaling, reflection=reflection)
    assert s == pytest.approx(scale, rel=1e-9)
    assert np.allclose(r, rot, atol=1e-9)
    assert np.allclose(t, [3.0, -2.0, 8.0], atol=1e-8)


def test_rodrigues_and_rotation_vector_are_inverse():
    rng = np.random.default_rng(2)
    for _ in range(20):
        omega = rng.normal(size=3)
        omega *= rng.uniform(0.0, 3.0) / np.linalg.norm(omega)
        rot = geometry.rodrigues(omega)
        assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-12) and np.linalg.det(rot) > 0
        assert np.allclose(geometry.rotation_vector(rot), omega, atol=1e-9)
        assert np.allclose(rot @ np.cross(omega, [1.0, 0, 0]),  # axis is fixed
                           np.cross(omega, rot @ [1.0, 0, 0]), atol=1e-9)


def test_edge_table_counts_give_the_euler_characteristic():
    v, f = icosphere(2, (1.0, 1.0, 1.0))
    e, counts, face_edges = meshops.edge_table(f)
    assert len(v) - len(e) + len(f) == 2 and np.all(counts == 2)
    assert np.array_equal(np.sort(f[:, [0, 1]], axis=1), e[face_edges[:, 0]])
    assert meshops.is_closed(f) and meshops.is_consistently_oriented(f)
    assert not meshops.is_consistently_oriented(np.vstack([f[:1, ::-1], f[1:]]))
    assert len(meshops.boundary_edges(f[1:])) == 3
