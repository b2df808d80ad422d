"""Transformation synchronisation vs reference-based alignment (Bernard et al., CVPR 2015, Fig. 4).

K shapes under random transforms of one class; every pairwise transform T_ij (shape j onto
shape i) is perturbed by noise (linear part I + 0.03 G with G standard normal, translation
N(0, 1 mm^2) per axis). The absolute transforms are recovered by
``core.alignment.transforms.synchronize_transforms`` (all pairs at once, no reference) and by chaining
through shape 0 (``reference_transforms``, the reference-based peer), from the same noisy
pairs. Error: RMS point distance of all relative transforms T_i^-1 T_j applied to a
150-point shape (mm), mean over ``--draws`` draws. Exact pairwise transforms give the
recovery error of the method itself.

Run: ``.venv/bin/python benchmarks/bench_alignment.py [--shapes 10] [--draws 20]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.alignment.transforms import (  # noqa: E402
    apply_transform,
    homogeneous,
    reference_transforms,
    synchronize_transforms,
)
from core.geometry.toolkit import random_rotation  # noqa: E402


def random_transform(rng: np.random.Generator, transform: str) -> np.ndarray:
    rot = random_rotation(rng)
    if transform == "similarity":
        rot = rot * rng.uniform(0.6, 1.6)
    if transform == "affine":
        rot = rot @ np.diag(rng.uniform(0.6, 1.6, 3)) @ random_rotation(rng)
    return homogeneous(rot, rng.normal(size=3) * 30.0)


def consistent_pairwise(absolute: np.ndarray) -> np.ndarray:
    """pairwise[i, j] = T_i^-1 T_j: maps shape j onto shape i, for T_k shape k -> common."""
    return np.linalg.inv(absolute)[:, None] @ absolute[None, :]


def relative_error(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray) -> float:
    """RMS point error (mm) of all relative transforms T_i^-1 T_j applied to ``points``."""
    est = consistent_pairwise(estimate)
    tru = consistent_pairwise(truth)
    diff = apply_transform(est, points) - apply_transform(tru, points)
    return float(np.sqrt((diff ** 2).sum(axis=-1).mean()))


def draw(transform: str, k: int, seed: int, noisy: bool, points: np.ndarray) -> tuple[float, float]:
    rng = np.random.default_rng(1000 + seed)
    absolute = np.stack([random_transform(rng, transform) for _ in range(k)])
    pairwise = consistent_pairwise(absolute)
    if noisy:
        for i in range(k):
            for j in range(k):
                if i != j:
                    noise = homogeneous(np.eye(3) + 0.03 * rng.normal(size=(3, 3)),
                                        rng.normal(size=3))
                    pairwise[i, j] = noise @ pairwise[i, j]
    sync = synchronize_transforms(pairwise, transform)
    ref = reference_transforms(pairwise, 0)
    return relative_error(sync, absolute, points), relative_error(ref, absolute, points)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shapes", type=int, default=10, help="K (10)")
    parser.add_argument("--draws", type=int, default=20, help="random draws per class (20)")
    args = parser.parse_args()
    print(f"cores: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f} (shared machine)")
    points = np.random.default_rng(7).normal(size=(150, 3)) * [20.0, 10.0, 6.0]
    print(f"\nK = {args.shapes}, {args.draws} draws per class; RMS error of the relative "
          "transforms on a 150-point shape, mm (mean ± SD over draws)\n")
    print("| transform | synchronised | reference-based | exact pairs: synchronised | time per "
          "synchronisation |")
    print("|---|---|---|---|---|")
    for transform in ("rigid", "similarity", "affine"):
        errs = np.array([draw(transform, args.shapes, s, True, points) for s in range(args.draws)])
        exact = max(draw(transform, args.shapes, s, False, points)[0] for s in range(3))
        pairwise = consistent_pairwise(np.stack([random_transform(np.random.default_rng(0),
                                                                  transform)
                                                 for _ in range(args.shapes)]))
        t0 = time.perf_counter()
        for _ in range(20):
            synchronize_transforms(pairwise, transform)
        per = (time.perf_counter() - t0) / 20
        print(f"| {transform} | {errs[:, 0].mean():.2f} ± {errs[:, 0].std():.2f} mm | "
              f"{errs[:, 1].mean():.2f} ± {errs[:, 1].std():.2f} mm | {exact:.1e} mm | "
              f"{1000 * per:.2f} ms |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
