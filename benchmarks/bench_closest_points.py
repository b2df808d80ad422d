"""Benchmark: exact closest points on a triangle surface, and what they cost correspondence.

Side by side in one run:

- ``numpy (round 2)``: the vectorised search the toolkit used until 2026-12-06 (Ericson's
  Voronoi-region test on the triangles of the k = 8 nearest centroids, certified by a
  bounding-radius test, the uncertified queries redone with twice as many candidates),
  re-implemented here from the toolkit's own ``closest_points_on_triangles`` as the peer;
- ``VTK``: ``vtkStaticCellLocator.FindClosestPoint``, VTK's documented exact query, one call
  a point (VTK has no batched call for it);
- ``libigl AABB`` (today's ``SurfaceProjector``): tree built once, all queries in one call.

Per surface size: the build + query time of each (median of repeats) and the largest
distance difference from libigl's answer. Then one population of the tuning family "global"
(6 shapes, 700-900 vertices, the safeguard's test population) corresponded with the
product's defaults twice in this process, once with the round-2 search patched in.

Run: ``OPENBLAS_NUM_THREADS=1 PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_closest_points.py``
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial import cKDTree

from core.datasets.shapes import known_homology_shapes
from core.geometry import toolkit


class NumpyRound2:
    """The round-2 exact search, built once per surface like the projector it was."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.n_faces = len(faces)
        self.triangles = vertices[faces]
        centroids = self.triangles.mean(axis=1)
        self.radius = float(np.linalg.norm(self.triangles - centroids[:, None], axis=2).max())
        self.tree = cKDTree(centroids)

    def _query(self, points: np.ndarray, k: int):
        """The k nearest centroids' triangles, and whether the answer is certified exact."""
        cdist, cand = self.tree.query(points, k=k)
        cdist, cand = cdist.reshape(len(points), -1), cand.reshape(len(points), -1)
        c, d, t = toolkit._closest_among(points, self.triangles, cand)
        return c, d, t, (k >= self.n_faces) | (d + self.radius <= cdist[:, -1])

    def project(self, points: np.ndarray, k: int = 8):
        """Closest points (P, 3), distances (P,), triangles (P,)."""
        k = min(k, self.n_faces)
        closest, dist, tri, ok = self._query(points, k)
        todo = np.flatnonzero(~ok)
        while len(todo) and k < self.n_faces:
            k = min(2 * k, self.n_faces)
            c, d, t, e = self._query(points[todo], k)
            closest[todo], dist[todo], tri[todo] = c, d, t
            todo = todo[~e]
        return closest, dist, tri


def numpy_round2(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    return NumpyRound2(vertices, faces).project(points)


def vtk_locator(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    import pyvista as pv
    import vtk

    surface = pv.PolyData(vertices, np.hstack([np.full((len(faces), 1), 3), faces]).ravel())
    locator = vtk.vtkStaticCellLocator()
    locator.SetDataSet(surface)
    locator.BuildLocator()
    closest = np.empty_like(points)
    dist2 = np.empty(len(points))
    c, cell, sub, d2 = [0.0, 0.0, 0.0], vtk.mutable(0), vtk.mutable(0), vtk.mutable(0.0)
    for i, p in enumerate(points):
        locator.FindClosestPoint(p, c, cell, sub, d2)
        closest[i] = c
        dist2[i] = float(d2)
    return closest, np.sqrt(dist2), None


def libigl(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray):
    return toolkit.SurfaceProjector(vertices, faces).project(points)


def _median_time(fn, repeats: int) -> tuple[float, tuple]:
    times, out = [], fn()  # a first call outside the timing: imports, caches
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def queries_table(sizes: list[int], repeats: int) -> None:
    print("| surface (vertices / triangles), queries | numpy (round 2) | VTK locator | libigl AABB |"
          " max distance difference from libigl (numpy / VTK) |")
    print("|---|---|---|---|---|")
    for n in sizes:
        mesh = known_homology_shapes("bean", 1, seed=1, n_points=(n, n + n // 10)).meshes[0]
        v, f = mesh.vertices, np.asarray(mesh.faces)
        # queries as correspondence makes them: points near the surface (a deformed copy)
        # and a few far off (the LOO criterion's model instances early in a pass)
        rng = np.random.default_rng(0)
        pts = v + rng.normal(scale=0.5, size=v.shape)
        pts[: len(pts) // 20] += rng.normal(scale=10.0, size=(len(pts) // 20, 3))
        t_np, (_, d_np, _) = _median_time(lambda: numpy_round2(v, f, pts), repeats)
        t_vtk, (_, d_vtk, _) = _median_time(lambda: vtk_locator(v, f, pts), max(1, repeats // 3))
        t_igl, (_, d_igl, _) = _median_time(lambda: libigl(v, f, pts), repeats)
        print(f"| {len(v)} / {len(f)}, {len(pts)} | {1e3 * t_np:.1f} ms | {1e3 * t_vtk:.1f} ms | "
              f"**{1e3 * t_igl:.1f} ms** | {np.abs(d_np - d_igl).max():.1e} / "
              f"{np.abs(d_vtk - d_igl).max():.1e} mm |")


def correspondence_table() -> None:
    from core.correspondence import establish_correspondence
    from core.datasets.families import population

    pop = population("global", 6, 100, size=(700, 900))
    original = toolkit.SurfaceProjector.project

    def round2_project(self, points):
        if not self.exact:
            return original(self, points)
        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if len(points) == 0:
            return np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        if not hasattr(self, "_round2"):  # built once per projector, as round 2 did
            self._round2 = NumpyRound2(self.vertices, np.asarray(self.faces))
        return self._round2.project(points)

    print("\n| global population 100 (6 shapes), defaults, one process | time | true spread mean (mm) |")
    print("|---|---|---|")
    for label, project in (("numpy (round 2)", round2_project), ("libigl AABB", original)):
        toolkit.SurfaceProjector.project = project
        try:
            t0 = time.perf_counter()
            result = establish_correspondence(pop.meshes, n_jobs=1)
            elapsed = time.perf_counter() - t0
        finally:
            toolkit.SurfaceProjector.project = original
        spread = float(pop.spread([m.vertices for m in result.meshes]).mean())
        print(f"| {label} | {elapsed:.1f} s | {spread:.4f} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[800, 3000, 12000])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--skip-correspondence", action="store_true")
    args = parser.parse_args()
    queries_table(args.sizes, args.repeats)
    if not args.skip_correspondence:
        correspondence_table()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
