"""Benchmark of the model-building methods (PCA, LSF, SPLOCS, Varimax), side by side.

1. Time of every method on the paper's brain-set size (Bernard et al., CVPR 2016): N = 1792
   vertices, K = 17 shapes, M = 96 factors -- synthetic shapes on a torus grid with 12 planted
   local bumps (ground truth), so the support IoU is reported too.
2. LSF's x/y/z group norm, l-infinity (the paper's) vs l2 (the default), with PCA and SPLOCS as
   peers, on two kinds of planted data: disjoint local bumps (ellipsoid, 642 vertices, the
   tests' 6 bumps) and overlapping bumps plus global modes. Each method is fitted on 24 shapes;
   support IoU against the planted factors, generalisation and 5% sparse reconstruction on 24
   new shapes of the same distribution (same fixed sparse-fit noise for every method), factors
   and fit time. No parameter was tuned on these draws: every method runs with its defaults
   and the same factor budget.
3. On the demo set (``resources/demo/ground_truth.npz``: corresponded caudate shapes with 6
   planted local factors): fit time, support IoU, and the paper's four measures (means over
   shapes, mm) plus the variance explained, for all methods; boxplots to ``--plot``.
4. Cancel latency of the builder's stages (correspondence, alignment, each model fit,
   evaluation), headless: the stage runs in a thread whose progress callback raises
   ``Cancelled`` once a flag is set, as the GUI's worker does; the latency is the time from
   setting the flag to the stage returning.

Run: ``.venv/bin/python benchmarks/bench_models.py [--factors 96] [--jobs 2] [--plot f.png]
[--skip-paper] [--skip-eval] [--skip-norms] [--skip-cancel]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.build.pipeline import align  # noqa: E402
from core.datasets.factors import ellipsoid_surface, grid_surface, mixed_shapes, planted_shapes, support_iou  # noqa: E402
from core.evaluation import evaluate_methods, evaluate_model, plot_metrics, summary_rows  # noqa: E402
from core.models import METHODS, make_model  # noqa: E402
from core.runtime.progress import Cancelled  # noqa: E402

DEMO = ROOT / "resources" / "demo" / "ground_truth.npz"


def print_table(rows: list[dict], columns: list[str]) -> None:
    print("| " + " | ".join(columns) + " |")
    print("|" + "|".join("---" for _ in columns) + "|")
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c, "")
            cells.append(f"{v:.3f}" if isinstance(v, float) else str(v))
        print("| " + " | ".join(cells) + " |")


def timed_fit(method: str, shapes, faces, planted, params: dict) -> dict:
    t0 = time.perf_counter()
    c0 = time.process_time()
    model = make_model(method, connectivity=faces, **params).fit(shapes)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    iou = support_iou(planted, model.factors_) if planted is not None else np.array([np.nan])
    return {"wall_s": wall, "cpu_s": cpu, "factors": model.n_factors_,
            "n_iter": getattr(model, "n_iter_", ""), "iou_mean": float(iou.mean()),
            "iou_min": float(iou.min()), "model": model}


def timed_fits(shapes, faces, planted, n_factors: int, methods=METHODS) -> list[dict]:
    rows = []
    for method in methods:
        row = timed_fit(method, shapes, faces, planted, {"n_factors": n_factors})
        row.pop("model")
        rows.append({"method": method, **row})
    return rows


# ------------------------------------------------------------------------------------------
# 2. l-infinity vs l2 group norm
# ------------------------------------------------------------------------------------------

PEERS = {"lsf-linf": ("lsf", {"group_norm": "linf"}), "lsf-l2": ("lsf", {"group_norm": "l2"}),
         "splocs": ("splocs", {}), "pca": ("pca", {})}


def heldout_errors(model, test: np.ndarray, noise_var: float, seed: int) -> tuple[float, float]:
    """Generalisation (projection) and 5% sparse reconstruction errors (mm, means over the
    held-out shapes); the sparse fit uses the same fixed sigma^2 for every method."""
    from core.evaluation import reconstruction_errors, sparse_fit

    g, _ = reconstruction_errors(model, test)
    n = test.shape[1]
    rng = np.random.default_rng(seed)
    sparse = []
    for x in test:
        idx = np.sort(rng.choice(n, int(np.ceil(0.05 * n)), replace=False))
        sparse.append(np.linalg.norm(sparse_fit(model, x[idx], idx, noise_var) - x, axis=1).mean())
    return float(g.mean()), float(np.mean(sparse))


def norm_rows(data, n_train: int, n_factors: int, noise_var: float) -> list[dict]:
    train, test = data.shapes[:n_train], data.shapes[n_train:]
    rows = []
    for label, (method, params) in PEERS.items():
        params = {"n_factors": n_factors, **params}
        fit = timed_fit(method, train, data.faces, data.factors, params)
        g, g005 = heldout_errors(fit.pop("model"), test, noise_var, seed=11)
        rows.append({"method": label, "factors": fit["factors"], "iou_mean": fit["iou_mean"],
                     "iou_min": fit["iou_min"], "g_avg": g, "g0.05_avg": g005,
                     "fit_s": fit["wall_s"]})
    return rows


def bench_group_norms(args) -> None:
    base, faces = ellipsoid_surface(3)  # 642 vertices
    noise_var = 0.05 ** 2  # the planted noise: the same sparse-fit sigma^2 for every method
    k = 24
    cases = [("disjoint local bumps (ellipsoid, 642 vertices, 6 bumps, noise 0.05 mm; the "
              "tests' factors)",
              planted_shapes(base, faces, n_shapes=2 * k, n_factors=6, noise=0.05,
                             random_state=1)),
             ("overlapping bumps + global modes (642 vertices, 4 bumps of radius 1.2 x their "
              "spacing, 2 global modes, noise 0.05 mm)",
              mixed_shapes(base, faces, n_shapes=2 * k, n_local=4, n_global=2, overlap=1.2,
                           noise=0.05, random_state=5))]
    for title, data in cases:
        print(f"\n### {title}\n")
        print(f"Fitted on {k} shapes, M = {args.norm_factors} for every method; generalisation "
              f"g and 5% sparse reconstruction g0.05 on {k} new shapes of the same distribution "
              f"(means, mm; sparse fit sigma^2 = {noise_var:g} mm^2 for all).\n")
        print_table(norm_rows(data, k, args.norm_factors, noise_var),
                    ["method", "factors", "iou_mean", "iou_min", "g_avg", "g0.05_avg", "fit_s"])


# ------------------------------------------------------------------------------------------
# 4. Cancel latency
# ------------------------------------------------------------------------------------------


def cancel_latency(run, after: float) -> tuple[float, bool]:
    """Run ``run(progress)`` in a thread, set the cancel flag after ``after`` s; return the
    seconds from the flag to the thread's end and whether it stopped by Cancelled."""
    flag = threading.Event()
    outcome = {}

    def progress(fraction, message):
        if flag.is_set():
            raise Cancelled

    def target():
        try:
            run(progress)
            outcome["cancelled"] = False
        except Cancelled:
            outcome["cancelled"] = True

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    time.sleep(after)
    flag.set()
    t0 = time.perf_counter()
    thread.join()
    return time.perf_counter() - t0, outcome.get("cancelled", False)


def bench_cancel(shapes, faces, args) -> None:
    from core.build.pipeline import correspond
    from core.io import TriMesh

    meshes = [TriMesh(s, faces, f"s{i}") for i, s in enumerate(shapes[:6])]
    every = [TriMesh(s, faces, f"s{i}") for i, s in enumerate(shapes)]
    stages = {
        "correspondence (6 meshes, 2 workers)":
            lambda p: correspond(meshes, reference=0, n_jobs=2, progress=p),
        # the first seconds of a larger batch are the safeguard's remesh trial (silent, and so
        # deaf to Cancel, until 2026-12-08)
        f"correspondence ({len(every)} meshes, reference auto, 2 workers)":
            lambda p: correspond(every, reference="auto", n_jobs=2, progress=p),
        "alignment (sync)": lambda p: align(shapes, progress=p),
        "evaluation (pca, 2 workers)":
            lambda p: evaluate_model("pca", shapes, faces, n_jobs=2, progress=p),
    }
    for method in METHODS:
        params = {"max_iter": 100000, "tol": 0.0} if method in ("lsf", "splocs") else {}
        stages[f"{method} fit"] = (lambda m, pr: lambda p: make_model(
            m, connectivity=faces, **pr).fit(shapes, progress=p))(method, params)
    rows = []
    for name, run in stages.items():
        lat = [cancel_latency(run, after) for after in (0.3, 1.0, 2.0)]
        rows.append({"stage": name, "latency_ms": " / ".join(f"{1000 * t:.0f}" for t, _ in lat),
                     "stopped_by_cancel": " / ".join("yes" if c else "finished" for _, c in lat)})
    print("\n## Cancel latency (cancel after 0.3 / 1.0 / 2.0 s; shared machine, upper bounds)\n")
    print_table(rows, ["stage", "latency_ms", "stopped_by_cancel"])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--factors", type=int, default=96, help="M for the timing runs (96)")
    parser.add_argument("--eval-factors", type=int, default=32,
                        help="M for the evaluation table on the demo set (32)")
    parser.add_argument("--norm-factors", type=int, default=12,
                        help="M for the group-norm comparison (12)")
    parser.add_argument("--jobs", type=int, default=2, help="processes for leave-one-out folds")
    parser.add_argument("--samples", type=int, default=1000, help="specificity samples")
    parser.add_argument("--plot", type=Path, default=None, help="write the demo boxplots here")
    parser.add_argument("--noise", type=float, default=0.0,
                        help="Gaussian noise (mm per coordinate) added to the demo's corresponded "
                             "shapes, standing in for correspondence error (default 0: as given)")
    parser.add_argument("--skip-paper", action="store_true", help="skip the paper-sized timing")
    parser.add_argument("--skip-norms", action="store_true", help="skip linf vs l2")
    parser.add_argument("--skip-eval", action="store_true", help="skip the evaluation table")
    parser.add_argument("--skip-cancel", action="store_true", help="skip the cancel latency")
    args = parser.parse_args()
    print(f"cores: {os.cpu_count()}, load average: {os.getloadavg()[0]:.1f} (shared machine: "
          "times are upper bounds)")

    if not args.skip_paper:
        verts, faces = grid_surface(56, 32)  # N = 1792
        data = planted_shapes(verts, faces, n_shapes=17, n_factors=12, noise=0.1, random_state=2)
        print(f"\n## Paper-sized problem: N={verts.shape[0]}, K=17, M={args.factors} "
              "(torus, 12 planted bumps, noise 0.1 mm)\n")
        rows = timed_fits(data.shapes, faces, data.factors, args.factors)
        print_table(rows, ["method", "wall_s", "cpu_s", "factors", "n_iter", "iou_mean", "iou_min"])

    if not args.skip_norms:
        print("\n## LSF group norm: l-infinity (paper) vs l2")
        bench_group_norms(args)

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
    if not args.skip_eval:
        print(f"\n## {label}: K={len(shapes)}, N={shapes.shape[1]}, aligned by sync/similarity\n")
        rows = timed_fits(aligned, faces, planted, args.eval_factors)
        print(f"Fits with M={args.eval_factors}:\n")
        print_table(rows, ["method", "wall_s", "cpu_s", "factors", "n_iter", "iou_mean", "iou_min"])
        t0 = time.perf_counter()
        results = evaluate_methods(list(METHODS), aligned, faces, n_factors=args.eval_factors,
                                   n_jobs=args.jobs, n_samples=args.samples)
        print(f"\nEvaluation with M={args.eval_factors} (means over shapes, mm; fixed "
              "leave-one-out on the shapes aligned once; specificity from the full coefficient "
              f"covariance; sparse-fit sigma^2 per fold model; {time.perf_counter() - t0:.0f} s, "
              f"{args.jobs} processes):\n")
        print_table(summary_rows(results), ["method", "n_factors", "e_avg", "e_max", "g_avg",
                                            "g_max", "s_avg", "s_max", "g0.05_avg", "g0.05_max",
                                            "explained"])
        if args.plot is not None:
            plot_metrics(results, args.plot, title=label)
            print(f"\nboxplots: {args.plot}")
    if not args.skip_cancel:
        bench_cancel(aligned, faces, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
