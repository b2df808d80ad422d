"""Benchmark: cohort scale -- the Dask executor against the process pool, and sparse synchronisation.

A. Executor throughput (issue 15): ``--shapes`` (default 500) synthetic closed meshes
   (ellipsoid-like surfaces of 300-420 vertices, random axes, pose and tessellation) are
   corresponded to one reference by :func:`core.correspondence.establish_correspondence`
   through the same :func:`core.parallel.run_jobs` call, once on the process pool
   (``n_jobs=2``) and once as Dask tasks on a ``LocalCluster`` of 2 single-threaded worker
   processes (the same cores). Peers configured as documented: the pool spawns one process per
   core with one BLAS thread each; the LocalCluster has ``threads_per_worker=1``,
   ``processes=True`` (Dask's advice for GIL-holding numeric code). Reported: wall time,
   shapes per second, the ratio, whether the outputs are identical, and the measured cost per
   shape (CPU seconds), from which the README projects a 50,000-shape cohort.

B. Sparse synchronisation (``core.alignment.align_shapes_sparse``): synthetic corresponded
   shapes (300 vertices: a base shape, 3 random modes, vertex noise, a random similarity pose
   each). 5,000 shapes: wall time and peak memory (in a child process: its max RSS). 200
   shapes: the error of sparse (K = 10 nearest) against dense all-pairs synchronisation
   (``align_shapes(method="sync")``), gauge-free: the mean over 4,000 random ordered pairs of
   the mean vertex displacement (mm) between the recovered relative map T_i^-1 T_j and the
   true one.

Run: ``.venv/bin/python benchmarks/bench_cluster.py [--shapes 500] [--part AB]``
The machine is shared (2 cores): times are upper bounds.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.io import TriMesh  # noqa: E402


def synthetic_meshes(n: int, seed: int = 0) -> list[TriMesh]:
    from scipy.spatial import ConvexHull
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        m = int(rng.integers(300, 420))
        u = rng.normal(size=(m, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        faces = ConvexHull(u).simplices
        v = u[faces]
        flip = np.einsum("ij,ij->i", np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), v.mean(1)) < 0
        faces[flip] = faces[flip][:, ::-1]
        bump = 1.0 + 0.15 * np.sin(3 * u[:, 0] + rng.uniform(0, 6)) * u[:, 1]
        pts = u * bump[:, None] * np.array([12.0, 8.0, 6.0]) * rng.uniform(0.9, 1.1, 3)
        pts = pts @ Rotation.from_rotvec(rng.normal(0, 0.15, 3)).as_matrix().T + rng.normal(0, 2, 3)
        out.append(TriMesh(pts, faces, f"shape{k:04d}"))
    return out


def part_a(n_shapes: int) -> None:
    from core.correspondence import establish_correspondence
    from core.parallel import use_scheduler

    meshes = synthetic_meshes(n_shapes)
    print(f"\nA. correspondence of {n_shapes} synthetic shapes to one reference, 2 workers")
    rows = {}
    for name, scheduler in (("process pool", None), ("Dask LocalCluster", "local:2")):
        with use_scheduler(scheduler):
            # warm-up on 4 shapes (5 meshes): worker start-up and imports are not throughput
            establish_correspondence(meshes[:5], 0, n_jobs=2)
            t0 = time.perf_counter()
            res = establish_correspondence(meshes, 0, n_jobs=2)
            wall = time.perf_counter() - t0
        rows[name] = (wall, res)
    print(f"{'executor':<20} {'wall s':>8} {'shapes/s':>9} {'CPU s/shape':>12}")
    for name, (wall, res) in rows.items():
        cpu = res.timings["cpu_total"] / max(res.timings["n_registrations"], 1)
        print(f"{name:<20} {wall:8.1f} {(n_shapes - 1) / wall:9.2f} {cpu:12.3f}")
    (w_pool, r_pool), (w_dask, r_dask) = rows.values()
    same = all(np.array_equal(a.vertices, b.vertices) for a, b in zip(r_pool.meshes, r_dask.meshes)
               if a is not None and b is not None)
    print(f"Dask/pool throughput ratio: {w_pool / w_dask:.3f} (1.0 = equal); outputs identical: {same}")


def _sync_child(n_shapes: int) -> None:
    """Runs in a child process: time and (via the parent) peak memory of the sparse sync."""
    from core.alignment import align_shapes_sparse

    shapes, _ = synthetic_shapes(n_shapes, 300, np.random.default_rng(0))
    t0 = time.perf_counter()
    align_shapes_sparse(shapes, "similarity", n_neighbors=10)
    print(f"{time.perf_counter() - t0:.2f}")


def synthetic_shapes(k: int, n: int, rng: np.random.Generator, noise: float = 0.5):
    from scipy.spatial.transform import Rotation

    from core.alignment import apply_transform

    base = rng.normal(0, 10, (n, 3)) * [2.0, 1.2, 0.8]
    modes = rng.normal(0, 1, (3, n, 3))
    shapes, poses = [], []
    for _ in range(k):
        s = base + np.einsum("m,mni->ni", rng.normal(0, 1.5, 3), modes) + rng.normal(0, noise, (n, 3))
        pose = np.eye(4)
        pose[:3, :3] = rng.uniform(0.8, 1.2) * Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
        pose[:3, 3] = rng.normal(0, 50, 3)
        shapes.append(apply_transform(pose, s))
        poses.append(pose)
    return np.stack(shapes), np.stack(poses)


def relative_error(transforms, poses, shapes, n_pairs=4000, seed=1) -> float:
    rng = np.random.default_rng(seed)
    ii = rng.integers(0, len(poses), n_pairs)
    jj = rng.integers(0, len(poses), n_pairs)
    errs = []
    for i, j in zip(ii, jj):
        if i == j:
            continue
        d = (np.linalg.inv(transforms[i]) @ transforms[j] - poses[i] @ np.linalg.inv(poses[j]))[:3]
        errs.append(np.linalg.norm(shapes[j] @ d[:, :3].T + d[:, 3], axis=1).mean())
    return float(np.mean(errs))


def part_b(n_large: int) -> None:
    from core.alignment import align_shapes, align_shapes_sparse

    print(f"\nB. sparse synchronisation (K = 10 nearest), similarity, 300 vertices per shape")
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    out = subprocess.run([sys.executable, __file__, "--sync-child", str(n_large)],
                         capture_output=True, text=True, check=True)
    peak_mb = max(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, before) / 1024
    print(f"{n_large} shapes: {float(out.stdout.strip()):.1f} s, peak memory of the process "
          f"{peak_mb:.0f} MB (shapes included)")
    shapes, poses = synthetic_shapes(200, 300, np.random.default_rng(2))
    t0 = time.perf_counter()
    sparse = align_shapes_sparse(shapes, "similarity", n_neighbors=10)
    t_sparse = time.perf_counter() - t0
    t0 = time.perf_counter()
    dense = align_shapes(shapes, "sync", "similarity")
    t_dense = time.perf_counter() - t0
    e_s = relative_error(sparse.transforms, poses, shapes)
    e_d = relative_error(dense.transforms, poses, shapes)
    print(f"{'200 shapes':<26} {'seconds':>8} {'error mm':>9}")
    print(f"{'dense all pairs':<26} {t_dense:8.1f} {e_d:9.4f}")
    print(f"{'sparse K=10':<26} {t_sparse:8.1f} {e_s:9.4f}")
    print(f"sparse / dense error: {e_s / e_d:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=500)
    parser.add_argument("--large", type=int, default=5000)
    parser.add_argument("--part", default="AB")
    parser.add_argument("--sync-child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.sync_child is not None:
        _sync_child(args.sync_child)
        return
    print(f"shared 2-core machine (load {os.getloadavg()[0]:.1f}): times are upper bounds")
    if "A" in args.part:
        part_a(args.shapes)
    if "B" in args.part:
        part_b(args.large)


if __name__ == "__main__":
    main()
