"""Benchmark: cohort scale -- the Dask executor against the process pool, and sparse synchronisation.

A. Executor throughput (issue 15): ``--shapes`` (default 500) synthetic known-homology shapes
   (``core.datasets.shapes``, "bean", 160-220 vertices, own tessellation and pose
   each) are corresponded to one reference (shape 0, external reference, no grooming, no
   refinement: exactly one per-shape job each) by
   :func:`core.correspondence.establish_correspondence`, whose per-shape jobs go through
   :func:`core.runtime.parallel.run_jobs`: on the process pool (``n_jobs=2``) and as Dask tasks on a
   ``LocalCluster`` of 2 single-threaded worker processes (the same cores). Peers configured as
   documented: the pool has one process per core with one BLAS thread each; the LocalCluster
   ``threads_per_worker=1, processes=True`` (Dask's advice for GIL-holding numeric code). The
   shapes go in chunks of ``--chunk`` (50), the executors alternating chunk by chunk (pool,
   Dask, pool, Dask, ...) so that a change of the machine's load hits both alike; both are
   warmed up first (worker start-up and imports are not throughput). Reported per executor:
   wall time, shapes per second, CPU seconds per shape (the whole process tree: client,
   workers, fork server, from /proc and getrusage), and whether the outputs of both are
   identical. The CPU cost per shape is what the README's 50,000-shape projection uses.

B. Sparse synchronisation (``core.alignment.transforms.align_shapes_sparse``): synthetic corresponded
   shapes (300 vertices: a base shape, 3 random modes, vertex noise, a random similarity pose
   each). 5,000 shapes: wall time and peak memory (in a child process: its max RSS). 200
   shapes: the error of sparse (K = 10 nearest) against dense all-pairs synchronisation
   (``align_shapes(method="sync")``), gauge-free: the mean over 4,000 random ordered pairs of
   the mean vertex displacement (mm) between the recovered relative map T_i^-1 T_j and the
   true one.

C. Client memory of ``ssm-studio correspond`` (issue 15: "memory on the client stays flat in
   the number of shapes"): ``--counts`` (50, 200, 800) synthetic beans (``--vertices``
   150-180 each, own tessellation and pose), written as .vtk files, corresponded by the real
   command (``python -m core.cli correspond FILES --out DIR --jobs 2 --max-iterations 15``:
   fewer CPD iterations than the default, which changes the time, not the memory: grooming, the
   reference-based pass, the outlier and mirror checks, one groupwise refinement pass) in a
   child process. Reported per run: the client's peak RSS (its own ``getrusage`` maximum at
   the end) and, separately, the largest peak RSS of its other processes (workers, fork
   server; their ``VmHWM`` sampled from /proc every 0.1 s), wall time, and whether the
   output files are byte-identical to the peer's. The peer is today's streaming tree against
   the tree at ``--baseline`` (821f4a8: the client reads every input and keeps every input,
   groomed input and result), exported with ``git archive`` and run alternately in the same
   session on the same files.

Run: ``.venv/bin/python benchmarks/bench_cluster.py [--shapes 500] [--chunk 50] [--part ABC]``
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
    from core.runtime.parallel import descendants

    for pid in descendants(os.getpid()):
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += sum(int(x) for x in fields[11:15]) / ticks  # utime stime cutime cstime
    return total


def part_a(n_shapes: int, chunk: int) -> None:
    from core.correspondence import establish_correspondence
    from core.datasets.shapes import known_homology_shapes
    from core.runtime.parallel import use_scheduler

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
    print(f"Dask/pool throughput ratio {ratio:.3f} "
          f"(within 15%: {'yes' if abs(ratio - 1) <= 0.15 else 'no'}); "
          f"load after {os.getloadavg()[0]:.1f}")


def _on(scheduler: str | None):
    """The pool (inside the cluster's use_scheduler) or the enclosing LocalCluster."""
    from core.runtime.parallel import use_scheduler

    return use_scheduler(None) if scheduler is None else contextlib.nullcontext()


def _sync_child(n_shapes: int) -> None:
    """Runs in a child process: time and (via the parent) peak memory of the sparse sync."""
    from core.alignment.transforms import align_shapes_sparse

    shapes, _ = synthetic_shapes(n_shapes, 300, np.random.default_rng(0))
    t0 = time.perf_counter()
    align_shapes_sparse(shapes, "similarity", n_neighbors=10)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux
    print(f"{time.perf_counter() - t0:.2f} {peak_mb:.0f}")


def synthetic_shapes(k: int, n: int, rng: np.random.Generator, noise: float = 0.5):
    from scipy.spatial.transform import Rotation

    from core.alignment.transforms import apply_transform

    base = rng.normal(0, 10, (n, 3)) * [2.0, 1.2, 0.8]
    modes = rng.normal(0, 1, (3, n, 3))
    shapes, poses = [], []
    for _ in range(k):
        s = base + np.einsum("m,mni->ni", rng.normal(0, 1.5, 3), modes) + rng.normal(0, noise, (n, 3))
        pose = np.eye(4)
        scale = rng.uniform(0.8, 1.2)                       # drawn before the rotation's seed
        pose[:3, :3] = scale * Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
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
    from core.alignment.transforms import align_shapes, align_shapes_sparse

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


# Runs the command line in the child and reports the child's own peak RSS (kB) at its end.
_LAUNCHER = ("import resource, sys\n"
             "from core.cli import _main\n"
             "code = _main(sys.argv[1:])\n"
             "print('PEAK_KB', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)\n"
             "sys.exit(code)\n")


def _peak_kb(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _run_correspond(tree: Path, paths: list[Path], out: Path) -> tuple[float, float, float]:
    """(client peak MB, largest other process's peak MB, wall s) of one `correspond` run."""
    import shutil

    from core.runtime.parallel import descendants

    shutil.rmtree(out, ignore_errors=True)
    env = dict(os.environ, PYTHONPATH=str(tree))
    log = out.with_name(out.name + ".log")  # a file, not a pipe: the progress bar fills a pipe
    t0 = time.perf_counter()
    with open(log, "w") as err_file:
        proc = subprocess.Popen([sys.executable, "-c", _LAUNCHER, "correspond",
                                 *map(str, paths), "--out", str(out), "--jobs", "2",
                                 "--max-iterations", "15"],
                                env=env, cwd=str(tree), stdout=subprocess.DEVNULL,
                                stderr=err_file)
        others: dict[int, int] = {}
        try:
            while proc.poll() is None:
                for pid in descendants(proc.pid):
                    others[pid] = max(others.get(pid, 0), _peak_kb(pid))
                time.sleep(0.1)
        finally:
            if proc.poll() is None:
                proc.kill()
    wall = time.perf_counter() - t0
    err = log.read_text(errors="replace")
    peak = [line.split()[1] for line in err.splitlines() if line.startswith("PEAK_KB")]
    if proc.returncode not in (0, 1) or not peak:
        raise RuntimeError(f"correspond failed ({proc.returncode}): {err[-800:]}")
    return int(peak[0]) / 1024, max(others.values(), default=0) / 1024, wall


def _export(commit: str, target: Path) -> Path:
    """The tree at ``commit`` (``git archive``), for the in-memory peer."""
    target.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(target)], input=archive, check=True)
    return target


def _same_outputs(a: Path, b: Path) -> bool:
    names = sorted(p.name for p in a.glob("*.vtk"))
    return names == sorted(p.name for p in b.glob("*.vtk")) and all(
        (a / n).read_bytes() == (b / n).read_bytes() for n in names)


def part_c(counts: list[int], baseline: str, n_points: tuple[int, int]) -> None:
    import tempfile

    from core.datasets.shapes import known_homology_shapes
    from core.io import save_mesh

    work = Path(tempfile.mkdtemp(prefix="bench-stream-"))
    try:
        meshes = known_homology_shapes("bean", max(counts), seed=0, n_points=n_points).meshes
        (work / "in").mkdir()
        paths = []
        for i, mesh in enumerate(meshes):
            paths.append(work / "in" / f"bean_{i:05d}.vtk")
            save_mesh(paths[-1], mesh)
        trees = {"streaming (this tree)": ROOT}
        if baseline:
            trees[f"in memory ({baseline})"] = _export(baseline, work / "baseline")
        print(f"\nC. client memory of `correspond --jobs 2` ({n_points[0]}-{n_points[1]} "
              f"vertices a shape, refine 1), load {os.getloadavg()[0]:.1f}")
        print(f"{'code':<26} {'shapes':>6} {'client peak MB':>15} {'worker peak MB':>15} "
              f"{'wall s':>7} {'identical':>9} {'load':>5}")
        for n in counts:
            outs = {}
            for name, tree in trees.items():
                outs[name] = work / f"out_{len(outs)}_{n}"
                client, worker, wall = _run_correspond(tree, paths[:n], outs[name])
                same = _same_outputs(*outs.values()) if len(outs) == 2 else None
                print(f"{name:<26} {n:6d} {client:15.0f} {worker:15.0f} {wall:7.1f} "
                      f"{'' if same is None else ('yes' if same else 'NO'):>9} "
                      f"{os.getloadavg()[0]:5.1f}", flush=True)
    finally:
        import shutil

        shutil.rmtree(work, ignore_errors=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", type=int, default=500)
    parser.add_argument("--chunk", type=int, default=50)
    parser.add_argument("--large", type=int, default=5000)
    parser.add_argument("--part", default="ABC")
    parser.add_argument("--counts", default="50,200,800", help="part C: numbers of shapes")
    parser.add_argument("--vertices", default="150,180", help="part C: vertex count range")
    parser.add_argument("--baseline", default="821f4a8",
                        help="part C: commit of the in-memory peer ('' for none)")
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
    if "C" in args.part:
        lo, hi = (int(x) for x in args.vertices.split(","))
        part_c([int(x) for x in args.counts.split(",")], args.baseline, (lo, hi))


if __name__ == "__main__":
    main()
