"""Benchmark: SSM Studio's whole correspondence pipeline vs plain rustcpd CPD-then-project, and
how one pair's time scales with the vertex count.

- ``pipeline``: raw known-homology meshes (rings by default) placed in scanner coordinates,
  :func:`core.correspondence.establish_correspondence` (grooming, auto reference, refine 1
  and 0) against plain rustcpd CPD-then-project onto ours' reference, ``--jobs`` processes:
  wall and per-shape task seconds, the assignment's share, the spread of the corresponded
  points' material points (mean, 95th percentile, mm) and failures;
- ``scaling``: one bean pair at ~2,500 and ~10,000 vertices: pair, CPD and assignment time.

Run: ``.venv/bin/python benchmarks/bench_corr_pipeline.py [--only pipeline|scaling] [--shapes 18]
[--jobs 2]`` (also ``bench_correspondence.py --only pipeline|scaling``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from correspondence_common import load_averages, plain_batch_timed


def pipeline_table(kind: str, n_shapes: int, jobs: int, seed: int = 7) -> None:
    """Whole pipeline on raw meshes, reference auto, vs plain rustcpd CPD-then-project."""
    from core.correspondence import DEFAULT_CPD_PARAMS, establish_correspondence
    from core.datasets.shapes import known_homology_shapes

    pop = known_homology_shapes(kind, n_shapes, seed=seed, n_points=(1800, 2300))
    scanner = np.array([-96.0, 131.0, 58.0])  # mm: where a structure sits in scanner coordinates
    for m in pop.meshes:
        m.vertices = m.vertices + scanner
    counts = [m.n_vertices for m in pop.meshes]
    print(f"\n{n_shapes} raw {kind} meshes ({min(counts)}-{max(counts)} vertices, own tessellations, "
          f"planted bumps, centred near {scanner.tolist()} mm), {jobs} worker processes; "
          f"shared machine: times are upper bounds")
    print(f"{'pipeline':<34}{'wall s':>8}{'task s':>8}{'assign s':>10}{'assign %':>9}"
          f"{'spread mean':>13}{'p95 mm':>8}{'fails':>6}")
    rows = {}
    for label, refine in (("ssm-studio (groom, auto, refine 1)", 1), ("ssm-studio, refine 0", 0)):
        t0 = time.perf_counter()
        res = establish_correspondence(pop.meshes, "auto", n_jobs=jobs, refine=refine)
        wall = time.perf_counter() - t0
        spread = pop.spread([m.vertices if m is not None else None for m in res.meshes])
        t = res.timings
        rows[label] = (wall, res)
        print(f"{label:<34}{wall:>8.1f}{t['cpu_total']:>8.1f}{t['assignment_total']:>10.2f}"
              f"{100 * t['assignment_total'] / max(t['cpu_total'], 1e-9):>9.1f}"
              f"{spread.mean():>13.3f}{np.percentile(spread, 95):>8.3f}{len(res.failures):>6}")
    ref_index = rows["ssm-studio, refine 0"][1].reference_index
    reference = pop.meshes[ref_index]
    others = [m for k, m in enumerate(pop.meshes) if k != ref_index]
    out, wall, task_s = plain_batch_timed(reference, others, dict(DEFAULT_CPD_PARAMS), jobs)
    it = iter(out)
    spread = pop.spread([reference.vertices if k == ref_index else next(it) for k in range(n_shapes)])
    print(f"{'rustcpd CPD-then-project':<34}{wall:>8.1f}{task_s:>8.1f}{'-':>10}{'-':>9}"
          f"{spread.mean():>13.3f}{np.percentile(spread, 95):>8.3f}{0:>6}")
    ours_wall, ours = rows["ssm-studio (groom, auto, refine 1)"]
    print(f"load average during the run: {load_averages()}")
    print(f"time ratio ssm-studio / rustcpd CPD-then-project: wall {ours_wall / wall:.2f}, "
          f"sum of per-shape task seconds {ours.timings['cpu_total'] / max(task_s, 1e-9):.2f} "
          f"(ours' grooming, reference choice and GPA are not in the latter); reference "
          f"{ours.reference_name}: {ours.reference_reason}")


def scaling_table(seed: int = 3) -> None:
    """One pair at ~2,500 and ~10,000 vertices: pair time and assignment time."""
    from core.correspondence import correspond_pair
    from core.datasets.shapes import known_homology_shapes

    print("\nscaling, one bean pair with own tessellations (times: shared machine, upper bounds)")
    print(f"{'vertices':>9}{'pair s':>9}{'cpd s':>8}{'assign s':>10}{'assign %':>9}")
    totals = {}
    for n in (2500, 10000):
        pop = known_homology_shapes("bean", 2, seed=seed, n_points=(n, n + 1))
        t0 = time.process_time()
        out = correspond_pair(pop.meshes[0], pop.meshes[1])
        cpu = time.process_time() - t0
        t = out["timings"]
        totals[n] = t["total"]
        print(f"{n:>9}{t['total']:>9.2f}{t['rigid'] + t['nonrigid']:>8.2f}{t['assignment']:>10.3f}"
              f"{100 * t['assignment'] / t['total']:>9.1f}   (cpu {cpu:.2f} s)")
    print(f"10,000 / 2,500 pair time: {totals[10000] / totals[2500]:.2f}x")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", choices=("pipeline", "scaling"), default=None,
                        help="one table (default: both)")
    parser.add_argument("--shapes", type=int, default=18, help="meshes in the pipeline table (18)")
    parser.add_argument("--kind", default="ring", help="shape kind of the pipeline table (ring)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (2)")
    args = parser.parse_args(argv)
    if args.only in (None, "scaling"):
        scaling_table()
    if args.only in (None, "pipeline"):
        pipeline_table(args.kind, args.shapes, args.jobs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
