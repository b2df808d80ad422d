"""Benchmark: cohort scale -- the Dask executor against the process pool, and sparse synchronisation.

A. Executor throughput (issue 15): ``--shapes`` (default 500) synthetic known-homology shapes
   (``core.correspondence.synthetic``, "bean", 160-220 vertices, own tessellation and pose
   each) are corresponded to one reference (shape 0, external reference, no grooming, no
   refinement: exactly one per-shape job each) by
   :func:`core.correspondence.establish_correspondence`, whose per-shape jobs go through
   :func:`core.parallel.run_jobs`: on the process pool (``n_jobs=2``) and as Dask tasks on a
   ``LocalCluster`` of 2 single-threaded worker processes (the same cores). Peers configured as
   documented: the pool has one process per core with one BLAS thread each; the LocalCluster
   ``threads_per_worker=1, processes=True`` (Dask's advice for GIL-holding numeric code). The
   shapes go in chunks of ``--chunk`` (50), the executors alternating chunk by chunk (pool,
   Dask, pool, Dask, ...) so that a change of the machine's load hits both alike; both are
   warmed up first (worker start-up and imports are not throughput). Reported per executor:
   wall time, shapes per second, CPU seconds per shape (the whole process tree: client,
   workers, fork server, from /proc and getrusage), and whether the outputs of both are
   identical. The CPU cost per shape is what the README's 50,000-shape projection uses.

B. Sparse synchronisation (``core.alignment.align_shapes_sparse``): synthetic corresponded
   shapes (300 vertices: a base shape, 3 random modes, vertex noise, a random similarity pose
   each). 5,000 shapes: wall time and peak memory (in a child process: its max RSS). 200
   shapes: the error of sparse (K = 10 nearest) against dense all-pairs synchronisation
   (``align_shapes(method="sync")``), gauge-free: the mean over 4,000 random ordered pairs of
   the mean vertex displacement (mm) between the recovered relative map T_i^-1 T_j and the
   true one.

Run: ``.venv/bin/python benchmarks/bench_cluster.py [--shapes 500] [--chunk 50] [--part AB]``
(about 5 minutes on 2 quiet cores). The machine is shared: times are upper bounds; the load
is printed before and after each part.
"""

from __future__ import annotations

import argparse
import contextlib
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


def tree_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process, its reaped children and every live
    descendant with the children it reaped (pool workers are reaped by the fork server)."""
    ticks = os.sysconf("SC_CLK_TCK")
    total = sum(getattr(resource.getrusage(who), f)
                for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
                for f in ("ru_utime", "ru_stime"))
    from core.parallel import descendants

    for pid in descendants(os.getpid()):
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += sum(int(x) for x in fields[11:15]) / ticks  # utime stime cutime cstime
    return total


def part_a(n_shapes: int, chunk: int) -> None:
    from core.correspondence import establish_correspondence
    from core.correspondence.synthetic import known_homology_shapes
    from core.parallel import use_scheduler

    meshes = known_homology_shapes("bean", n_shapes + 1, seed=0, n_points=(160, 220)).meshes
    reference, shapes = meshes[0], meshes[1:]
    chunks = [shapes[k:k + chunk] for k in range(0, len(shapes), chunk)]
    print(f"\nA. correspondence of {n_shapes} synthetic shapes (160-220 vertices) to one "
          f"reference, 2 workers, chunks of {chunk} alternating (load "
          f"{os.getloadavg()[0]:.1f})")
    options = dict(groom=False, refine=0)
    executors = {"process pool": None, "Dask LocalCluster": "local:2"}
    wall = dict.fromkeys(executors, 0.0)
    cpu = dict.fromkeys(executors, 0.0)
    outputs: dict[str, list] = {name: [] for name in executors}
    with use_scheduler("local:2"):  # the cluster stays up; the pool runs inside use_scheduler(None)
        for name, scheduler in executors.items():  # warm-up: start-up and imports
            with _on(scheduler):
                establish_correspondence(shapes[:4], reference, n_jobs=2, **options)
        for part in chunks:
            for name, scheduler in executors.items():
                with _on(scheduler):
                    c0, t0 = tree_cpu_seconds(), time.perf_counter()
                    res = establish_correspondence(part, reference, n_jobs=2, **options)
                    wall[name] += time.perf_counter() - t0
                    cpu[name] += tree_cpu_seconds() - c0
                outputs[name] += [None if m is None else m.vertices for m in res.meshes]
    (pool_out, dask_out) = outputs.values()
    # identical: the same shapes failed (flagged by the batch's checks) and the same vertices
    same = len(pool_out) == len(dask_out) == n_shapes and all(
        (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))
        for a, b in zip(pool_out, dask_out))
    failed = {name: sum(v is None for v in out) for name, out in outputs.items()}
    print(f"{'executor':<20} {'shapes':>6} {'failed':>6} {'wall s':>8} {'shapes/s':>9} "
          f"{'CPU s/shape':>12} {'outputs identical':>18}")
    for name in executors:
        print(f"{name:<20} {n_shapes:6d} {failed[name]:6d} {wall[name]:8.1f} "
              f"{n_shapes / wall[name]:9.3f} {cpu[name] / n_shapes:12.3f} "
              f"{'yes' if same else 'NO':>18}")
    ratio = wall["process pool"] / wall["Dask LocalCluster"]
    print(f"Dask/pool throughput ratio {ratio:.3f} (within 15%: {'yes' if abs(ratio - 1) <= 0.15 else 'no'}); "
          f"load after {os.getloadavg()[0]:.1f}")


def _on(scheduler: str | None):
    """The pool (inside the cluster's use_scheduler) or the enclosing LocalCluster."""
    from core.parallel import use_scheduler

    return use_scheduler(None) if scheduler is None else contextlib.nullcontext()


def _sync_child(n_shapes: int) -> None:
    """Runs in a child process: time and (via the parent) peak memory of the sparse sync."""
    from core.alignment import align_shapes_sparse

    shapes, _ = synthetic_shapes(n_shapes, 300, np.random.default_rng(0))
    t0 = time.perf_counter()
    align_shapes_sparse(shapes, "similarity", n_neighbors=10)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux
    print(f"{time.perf_counter() - t0:.2f} {peak_mb:.0f}")


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

    print(f"\nB. sparse synchronisation (K = 10 nearest), similarity, 300 vertices per shape "
          f"(load {os.getloadavg()[0]:.1f})")
    out = subprocess.run([sys.executable, __file__, "--sync-child", str(n_large)],
                         capture_output=True, text=True, check=True)
    seconds, peak_mb = (float(x) for x in out.stdout.split())
    print(f"{n_large} shapes: {seconds:.1f} s, peak memory of the process {peak_mb:.0f} MB "
          f"(shapes included; targets < 60 s on a quiet machine, < 2048 MB)")
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
    print(f"sparse / dense error: {e_s / e_d:.3f} (within 5%: {'yes' if e_s <= 1.05 * e_d else 'no'}); "
          f"load after {os.getloadavg()[0]:.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=500)
    parser.add_argument("--chunk", type=int, default=50)
    parser.add_argument("--large", type=int, default=5000)
    parser.add_argument("--part", default="AB")
    parser.add_argument("--sync-child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.sync_child is not None:
        _sync_child(args.sync_child)
        return
    print(f"shared 2-core machine (load {os.getloadavg()[0]:.1f}): times are upper bounds")
    if "A" in args.part:
        part_a(args.shapes, args.chunk)
    if "B" in args.part:
        part_b(args.large)


if __name__ == "__main__":
    main()
