"""Benchmark of the model-building methods (PCA, LSF, SPLOCS, Varimax), side by side.

1. Time of every method on the paper's brain-set size (Bernard et al., CVPR 2016): N = 1792
   vertices, K = 17 shapes, M = 96 factors -- synthetic shapes on a torus grid with 12 planted
   local bumps (ground truth), so the support IoU is reported too. Target: LSF < 60 s on 2 cores.
2. On the demo set (``resources/demo/ground_truth.npz``: corresponded caudate shapes with 6
   planted local factors) if present, else on synthetic planted shapes: fit time, support IoU
   against the planted factors, and the paper's four measures (means over shapes, mm) plus the
   variance explained, for all methods; the boxplots are written to ``--plot``.

Run: ``.venv/bin/python benchmarks/bench_models.py [--factors 96] [--jobs 2] [--plot f.png]``.
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

from core.evaluation import evaluate_methods, plot_metrics, summary_rows  # noqa: E402
from core.models import METHODS, make_model  # noqa: E402
from core.models.synthetic import grid_surface, planted_shapes, support_iou  # noqa: E402
from core.pipeline import align  # noqa: E402

DEMO = ROOT / "resources" / "demo" / "ground_truth.npz"


def timed_fits(shapes, faces, planted, n_factors: int, methods=METHODS) -> list[dict]:
    rows = []
    for method in methods:
        params = {"n_factors": n_factors}
        t0 = time.perf_counter()
        c0 = time.process_time()
        model = make_model(method, **params).fit(shapes, faces)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        iou = support_iou(planted, model.factors_) if planted is not None else np.array([np.nan])
        rows.append({"method": method, "wall_s": wall, "cpu_s": cpu, "factors": model.n_factors_,
                     "n_iter": getattr(model, "n_iter_", ""), "iou_mean": float(iou.mean()),
                     "iou_min": float(iou.min())})
    return rows


def print_table(rows: list[dict], columns: list[str]) -> None:
    print("| " + " | ".join(columns) + " |")
    print("|" + "|".join("---" for _ in columns) + "|")
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c, "")
            cells.append(f"{v:.3f}" if isinstance(v, float) else str(v))
        print("| " + " | ".join(cells) + " |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--factors", type=int, default=96, help="M for the timing runs (96)")
    parser.add_argument("--eval-factors", type=int, default=32,
                        help="M for the evaluation table on the demo set (32)")
    parser.add_argument("--jobs", type=int, default=2, help="processes for leave-one-out folds")
    parser.add_argument("--samples", type=int, default=1000, help="specificity samples")
    parser.add_argument("--plot", type=Path, default=None, help="write the demo boxplots here")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="Gaussian noise (mm per coordinate) added to the demo's corresponded "
                             "shapes, standing in for correspondence error (default 0: as given)")
    parser.add_argument("--skip-paper", action="store_true", help="skip the paper-sized timing")
    parser.add_argument("--skip-eval", action="store_true", help="skip the evaluation table")
    args = parser.parse_args()
    print(f"cores: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f}")

    if not args.skip_paper:
        verts, faces = grid_surface(56, 32)  # N = 1792
        data = planted_shapes(verts, faces, n_shapes=17, n_factors=12, noise=0.1, random_state=2)
        print(f"\n## Paper-sized problem: N={verts.shape[0]}, K=17, M={args.factors} "
              "(torus, 12 planted bumps, noise 0.1 mm)\n")
        rows = timed_fits(data.shapes, faces, data.factors, args.factors)
        print_table(rows, ["method", "wall_s", "cpu_s", "factors", "n_iter", "iou_mean", "iou_min"])

    if DEMO.exists():
        z = np.load(DEMO)
        shapes, faces, planted = z["corresponded_shapes"], z["base_faces"], z["factors"]
        label = f"demo set ({DEMO.relative_to(ROOT)})"
        if args.noise > 0:
            shapes = shapes + np.random.default_rng(0).normal(scale=args.noise, size=shapes.shape)
            label += f" + {args.noise} mm noise"
    else:
        verts, faces = grid_surface(50, 40)
        data = planted_shapes(verts, faces, n_shapes=24, n_factors=6, noise=0.05, random_state=3)
        shapes, planted = data.shapes, data.factors
        label = "synthetic planted shapes (demo set not found)"
    aligned = align(shapes, method="sync", transform="similarity").aligned
    print(f"\n## {label}: K={len(shapes)}, N={shapes.shape[1]}, aligned by sync/similarity\n")
    rows = timed_fits(aligned, faces, planted, args.factors)
    print(f"Fits with M={args.factors}:\n")
    print_table(rows, ["method", "wall_s", "cpu_s", "factors", "n_iter", "iou_mean", "iou_min"])
    if not args.skip_eval:
        t0 = time.perf_counter()
        results = evaluate_methods(list(METHODS), aligned, faces, n_factors=args.eval_factors,
                                   n_jobs=args.jobs, n_samples=args.samples)
        print(f"\nEvaluation with M={args.eval_factors} (means over shapes, mm; "
              f"{time.perf_counter() - t0:.0f} s, {args.jobs} processes):\n")
        print_table(summary_rows(results), ["method", "n_factors", "e_avg", "e_max", "g_avg",
                                            "g_max", "s_avg", "s_max", "g0.05_avg", "g0.05_max",
                                            "explained"])
        if args.plot is not None:
            plot_metrics(results, args.plot, title=label)
            print(f"\nboxplots: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
