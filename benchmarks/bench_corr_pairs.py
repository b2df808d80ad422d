"""Benchmark: one pair at a time, SSM Studio vs plain CPD pipelines, on the demo set (or beans).

Peers, on the same inputs in the same run (:mod:`correspondence_common`):

- ``ssm-studio``: :func:`core.correspondence.correspond_pair` (rustcpd rigid + nonrigid CPD,
  log-posterior linear assignment, fairing on the target surface);
- ``rustcpd``: rustcpd rigid + nonrigid CPD with the same parameters, then each deformed
  reference vertex projected to its nearest point on the target surface;
- ``pycpd``: the same plain pipeline on pycpd 2.x (pure numpy; benchmark-only dependency).

Quality against known homologues (the demo set's ground truth when present, else, or with
``--synthetic``, bean shapes of :mod:`core.datasets.shapes`): the distance of every
corresponded vertex to its true homologue (mean and max, mm), the share of degenerate and of
flipped triangles and the area distortion against the reference's triangulation. On the demo
set, pose removal on its true correspondences (sync vs GPA vs to shape 0). Then the whole
batch (``establish_correspondence``, fixed and auto reference) on 2 workers.

Run: ``.venv/bin/python benchmarks/bench_corr_pairs.py [--shapes 6] [--pycpd 2] [--batch 20]
[--synthetic]`` (also ``bench_correspondence.py --only legacy``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from correspondence_common import (
    ROOT,
    area_distortion,
    degenerate_fraction,
    demo_population,
    flipped_fraction,
    ours,
    plain_pycpd,
    plain_rustcpd,
    synthetic_truth,
)


def alignment_on_demo(folder: Path) -> None:
    """Pose removal on the demo set's true correspondences: sync vs GPA vs reference-based.

    The demo shapes are s_k R_k y_k + t_k with known unposed shapes y_k; the error is the RMS
    distance between the aligned shapes and the y_k after one common similarity (the gauge).
    """
    from core.alignment.transforms import (
        align_shapes,
        apply_transform,
        fit_transform,
        pairwise_transforms,
        reference_transforms,
    )

    gt = np.load(folder / "ground_truth.npz")
    posed = gt["corresponded_shapes"]
    unposed = gt["base_vertices"][None] + np.einsum("km,mnc->knc", gt["coefficients"], gt["factors"])

    def error(aligned: np.ndarray) -> float:
        gauge = fit_transform(aligned.reshape(-1, 3), unposed.reshape(-1, 3), "similarity")
        return float(np.sqrt(((apply_transform(gauge, aligned) - unposed) ** 2).sum(-1).mean()))

    print("\nalignment of the demo set's true correspondences (similarity), RMS error vs unposed truth")
    for method in ("sync", "gpa"):
        t0 = time.perf_counter()
        result = align_shapes(posed, method=method, transform="similarity")
        print(f"  {method:<16}{error(result.aligned):8.3f} mm  {time.perf_counter() - t0:6.2f} s")
    ref = reference_transforms(pairwise_transforms(posed, "similarity"), 0)
    print(f"  {'to shape 0':<16}{error(apply_transform(ref, posed)):8.3f} mm")


def pairs_table(meshes: list, truth, n_targets: int, n_pycpd: int) -> None:
    """Shape 0 as the reference onto shapes 1..n_targets (pycpd: the first ``n_pycpd``)."""
    from core.correspondence import DEFAULT_CPD_PARAMS

    params = dict(DEFAULT_CPD_PARAMS)
    ref = 0
    reference = meshes[ref]
    targets = list(range(1, min(len(meshes), n_targets + 1)))
    peers = [("ssm-studio", ours, targets), ("rustcpd alone", plain_rustcpd, targets),
             ("pycpd", plain_pycpd, targets[:n_pycpd])]
    rows = []
    for name, fn, tgts in peers:
        if name == "pycpd":
            try:
                import pycpd  # noqa: F401
            except ImportError:
                print("pycpd not installed (pip install .[bench]); skipped")
                continue
        if not tgts:
            continue
        times, means, maxes, degen, distortion, flipped = [], [], [], [], [], []
        for k in tgts:
            t0 = time.perf_counter()
            out = fn(reference, meshes[k], params)
            times.append(time.perf_counter() - t0)
            err = np.linalg.norm(out - truth(ref, k, reference.vertices), axis=1)
            means.append(err.mean())
            maxes.append(err.max())
            degen.append(degenerate_fraction(out, reference.faces))
            distortion.append(area_distortion(out, reference.vertices, reference.faces))
            flipped.append(flipped_fraction(out, reference.faces, meshes[k]))
        rows.append((name, len(tgts), np.mean(times), np.mean(means), np.max(maxes), 100 * np.mean(degen),
                     np.mean(distortion), 100 * np.mean(flipped)))
    print(f"\nper shape, reference {reference.name} ({reference.n_vertices} vertices), "
          f"same targets, same CPD parameters")
    print(f"{'method':<15}{'shapes':>7}{'s/shape':>9}{'mean err mm':>13}{'max err mm':>12}"
          f"{'degenerate %':>14}{'area distortion':>17}{'flipped %':>11}")
    for r in rows:
        print(f"{r[0]:<15}{r[1]:>7}{r[2]:>9.2f}{r[3]:>13.3f}{r[4]:>12.3f}{r[5]:>14.2f}{r[6]:>17.3f}"
              f"{r[7]:>11.2f}")
    if len(rows) >= 2:
        print(f"time ratio ssm-studio / rustcpd alone: {rows[0][2] / rows[1][2]:.2f}")


def batch_timing(batch: list, truth) -> None:
    """The whole batch on 2 workers, fixed reference (shape 0) and auto (3 candidates): time
    and the error vs truth of the groomed reference's vertices' homologues."""
    from core.correspondence import establish_correspondence

    for label, reference_arg, n_refs in (("fixed reference", 0, 1), ("auto, 3 candidates", "auto", 3)):
        t0 = time.perf_counter()
        result = establish_correspondence(batch, reference_arg, n_references=n_refs, n_jobs=2)
        wall = time.perf_counter() - t0
        r = result.reference_index
        groomed_reference = result.meshes[r].vertices  # grooming may have remeshed it
        errs = [np.linalg.norm(m.vertices - truth(r, k, groomed_reference), axis=1)
                for k, m in enumerate(result.meshes) if m is not None and k != r]
        print(f"\nbatch of {len(batch)} meshes, 2 workers, {label}: {wall:.1f} s wall "
              f"({result.timings['n_registrations']} registrations, "
              f"{result.timings['per_shape_mean']:.2f} s each), reference {result.reference_name}, "
              f"error vs truth mean {np.mean([e.mean() for e in errs]):.3f} mm, "
              f"max {np.max([e.max() for e in errs]):.3f} mm, failures {len(result.failures)}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shapes", type=int, default=6, help="targets per method (default 6)")
    parser.add_argument("--pycpd", type=int, default=2, help="targets for pycpd (slow; default 2)")
    parser.add_argument("--batch", type=int, default=20, help="meshes in the batch timing (default 20)")
    parser.add_argument("--synthetic", action="store_true", help="ignore the demo set")
    args = parser.parse_args(argv)

    demo = ROOT / "resources" / "demo"
    on_demo = not args.synthetic and (demo / "ground_truth.npz").exists()
    if on_demo:
        meshes, truth = demo_population(demo)
        source = f"demo set ({demo.relative_to(ROOT)}, {len(meshes)} caudate meshes)"
    else:
        meshes, truth = synthetic_truth(max(args.batch, args.shapes + 1))
        source = "synthetic bean shapes (core.datasets.shapes)"
    counts = [m.n_vertices for m in meshes]
    print(f"data: {source}; vertices {min(counts)}-{max(counts)}")
    pairs_table(meshes, truth, args.shapes, args.pycpd)
    if on_demo:
        alignment_on_demo(demo)
    if len(meshes[:args.batch]) >= 2:
        batch_timing(meshes[:args.batch], truth)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
