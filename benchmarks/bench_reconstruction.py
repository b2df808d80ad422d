"""Benchmark of the reconstruction engine against its peers, side by side in one run.

Accuracy: leave-one-out over the demo set's corresponded ground-truth shapes
(``resources/demo/ground_truth.npz``; a synthetic bean family when it is missing): PCA model of
the other shapes (``core.simulated_user.pca_model``), a simulated user draws k contours of the
held-out shape (``core.simulated_user.simulate_user``: 2 mm point spacing, 0.3 mm in-plane
noise, normals from the contour tangent), and each method reconstructs the surface:

- gmm-aniso, gmm-iso, icp: ``core.reconstruction.fit_points`` (similarity pose, prior weight 1);
  with ``--fixed-eta`` also ``aniso-eta10``: gmm-aniso with ``adaptive_anisotropy=False`` (the
  fixed eta = 10 it replaced, for comparison);
- rustcpd: ``rustcpd.register_atlas`` (isotropic GMM + similarity, same model: modes (3N, M)
  point-major, eigenvalues = the coefficient variances, its defaults otherwise);
- itk-mci (parallel slices only): each contour's points are filled as a polygon into a label
  image (0.5 mm voxels, the slices on voxel planes) and ITK's morphological contour
  interpolation (``itk-morphologicalcontourinterpolation``, what ITK-SNAP / 3D Slicer users
  get) fills the slices in between; its surface is the mask's marching-cubes surface.

Error: symmetric mean surface distance (mean of the two directed point-to-surface means, mm) and
Hausdorff distance (max of both directed maxima, mm) to the true surface, averaged over cases.
Scenario "mixed": axial/coronal/sagittal cycling; scenario "axial": parallel axial slices.

Latency: a ~2,000-vertex, 50-factor model (the demo topology with extra random smooth bumps
so that PCA has 50 real modes) and 200 contour points; cold fits and warm refits (previous
result as the start, one point dragged by ~0.5 mm, as in the GUI), p50/p99 over ``--reps``.

Run: ``.venv/bin/python benchmarks/bench_reconstruction.py`` (``--quick`` for a smoke run).
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

from core.geometry import surface_distance  # noqa: E402
from core.reconstruction import fit_points  # noqa: E402
from core.simulated_user import pca_model, simulate_user, slice_planes, synthetic_shapes  # noqa: E402

OURS = ("gmm-aniso", "gmm-iso", "icp")
FIXED_ETA = "aniso-eta10"  # gmm-aniso without the adaptive anisotropy (--fixed-eta)


def load_shapes() -> tuple[np.ndarray, np.ndarray, str]:
    path = ROOT / "resources" / "demo" / "ground_truth.npz"
    if path.exists():
        data = np.load(path)
        return data["corresponded_shapes"], data["base_faces"], "demo (left caudate, 24 shapes)"
    shapes, faces = synthetic_shapes(24, subdivisions=4, seed=0, size=(4.0, 8.0, 16.0))
    return shapes, faces, "synthetic beans (demo data missing)"


def errors(surface_v: np.ndarray, surface_f: np.ndarray, true_v: np.ndarray,
           true_f: np.ndarray) -> tuple[float, float]:
    a = surface_distance(surface_v, true_v, true_f)
    b = surface_distance(true_v, surface_v, surface_f)
    return 0.5 * float(a.mean() + b.mean()), float(max(a.max(), b.max()))


def rustcpd_fit(model, points):
    import rustcpd

    result = rustcpd.register_atlas(points, model.mean, model.basis, list(model.coef_var))
    return np.asarray(result.points), result


# ---------------------------------------------------------------------------------------
# ITK morphological contour interpolation of parallel (axial) contours
# ---------------------------------------------------------------------------------------


def axial_planes_on_grid(true_v: np.ndarray, k: int, origin_z: float, step: float):
    planes = slice_planes(true_v, k, "axial")
    snapped = []
    for origin, normal in planes:
        o = origin.copy()
        o[2] = origin_z + np.round((o[2] - origin_z) / step) * step
        snapped.append((o, normal))
    return snapped


def itk_mci_surface(user, grid_origin: np.ndarray, spacing: float, shape: tuple[int, int, int]):
    """Fill each contour polygon in its axial slice, interpolate with ITK MCI, extract surface."""
    import itk
    import pyvista as pv
    from matplotlib.path import Path as PolyPath

    labels = np.zeros(shape, dtype=np.uint8)  # indexed [i, j, k] = x, y, z
    xs = grid_origin[0] + spacing * np.arange(shape[0])
    ys = grid_origin[1] + spacing * np.arange(shape[1])
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    centres = np.column_stack([gx.ravel(), gy.ravel()])
    for loop in np.unique(user.loop):
        pts = user.points[user.loop == loop]
        kz = int(np.round((pts[0, 2] - grid_origin[2]) / spacing))
        if not 0 <= kz < shape[2]:
            continue
        inside = PolyPath(pts[:, :2]).contains_points(centres).reshape(shape[:2])
        labels[:, :, kz] |= inside.astype(np.uint8)
    image = itk.image_from_array(np.ascontiguousarray(labels.transpose(2, 1, 0)))  # itk: [z, y, x]
    filled = itk.array_from_image(itk.morphological_contour_interpolator(image)).transpose(2, 1, 0)
    grid = pv.ImageData(dimensions=shape, spacing=(spacing,) * 3, origin=tuple(grid_origin))
    grid.point_data["mask"] = (filled > 0).astype(np.float32).ravel(order="F")
    surface = grid.contour([0.5], scalars="mask").triangulate()
    if surface.n_points == 0:
        return None, None
    return np.asarray(surface.points, dtype=np.float64), surface.faces.reshape(-1, 4)[:, 1:]


# ---------------------------------------------------------------------------------------


def accuracy(shapes, faces, cases, contour_counts, scenario: str, with_itk: bool, with_rustcpd: bool,
             with_fixed_eta: bool = False):
    methods = (list(OURS) + ([FIXED_ETA] if with_fixed_eta else [])
               + (["rustcpd"] if with_rustcpd else []) + (["itk-mci"] if with_itk else []))
    table = {m: {k: [] for k in contour_counts} for m in methods}
    times = {m: [] for m in methods}
    spacing = 0.5
    for case in cases:
        model = pca_model(np.delete(shapes, case, axis=0), faces)
        truth = shapes[case]
        lo = np.floor(truth.min(axis=0)) - 3.0
        shape = tuple(int(s) for s in np.ceil((truth.max(axis=0) + 3.0 - lo) / spacing) + 1)
        for k in contour_counts:
            rng = np.random.default_rng(1000 * case + k)
            planes = (axial_planes_on_grid(truth, k, lo[2], spacing) if scenario == "axial"
                      else None)
            user = simulate_user(truth, faces, k, orientations=scenario, rng=rng, planes=planes)
            if len(user.points) < 3:
                continue
            for method in methods:
                t0 = time.perf_counter()
                if method in OURS:
                    surf_v = fit_points(model, user.points, user.normals, method=method).vertices
                    surf_f = faces
                elif method == FIXED_ETA:
                    surf_v = fit_points(model, user.points, user.normals, method="gmm-aniso",
                                        adaptive_anisotropy=False).vertices
                    surf_f = faces
                elif method == "rustcpd":
                    surf_v, _ = rustcpd_fit(model, user.points)
                    surf_f = faces
                else:
                    if k < 2:
                        continue
                    surf_v, surf_f = itk_mci_surface(user, lo, spacing, shape)
                    if surf_v is None:
                        continue
                times[method].append(time.perf_counter() - t0)
                table[method][k].append(errors(surf_v, surf_f, truth, faces))
    return table, times


def print_accuracy(table, times, contour_counts, title):
    print(f"\n{title}")
    methods = list(table)
    head = "contours | " + " | ".join(f"{m:>15}" for m in methods)
    print(head)
    print("-" * len(head))
    for k in contour_counts:
        cells = []
        for m in methods:
            vals = table[m][k]
            cells.append(f"{np.mean([v[0] for v in vals]):6.3f} / {np.mean([v[1] for v in vals]):5.2f}"
                         if vals else f"{'-':>15}")
        print(f"{k:8d} | " + " | ".join(f"{c:>15}" for c in cells))
    print("time/fit | " + " | ".join(f"{1000 * np.median(times[m]):12.0f} ms" if times[m]
                                     else f"{'-':>15}" for m in methods))
    print("(cells: mean surface distance / Hausdorff distance, mm, averaged over cases)")


def latency_model(shapes, faces, n_factors=50, seed=0):
    """The demo topology with random smooth bumps added, so PCA has n_factors real modes."""
    rng = np.random.default_rng(seed)
    from core.geometry import vertex_normals

    base = shapes.mean(axis=0)
    normals = vertex_normals(base, faces)
    centres = base[rng.choice(len(base), 70, replace=False)]
    bumps = np.exp(-((base[None] - centres[:, None]) ** 2).sum(axis=2) / (2 * 3.0**2))  # (70, N)
    train = []
    for _ in range(90):
        s = shapes[rng.integers(len(shapes))].copy()
        s += (rng.normal(scale=0.4, size=70) @ bumps)[:, None] * normals
        train.append(s)
    train = np.stack(train)
    model = pca_model(train[1:], faces, n_factors=n_factors)
    return model, train[0]


def latency(shapes, faces, reps: int, with_rustcpd: bool):
    model, truth = latency_model(shapes, faces)
    rng = np.random.default_rng(7)
    user = simulate_user(truth, faces, 8, spacing=1.0, rng=rng)
    pick = rng.choice(len(user.points), 200, replace=len(user.points) < 200)
    pts, nrm = user.points[pick], user.normals[pick]
    print(f"\nLatency: model {model.n_vertices} vertices, {model.n_factors} factors, {len(pts)} points,"
          f" {reps} fits each, os.cpu_count()={os.cpu_count()}")
    print(f"{'method':>10} | {'cold p50':>9} | {'cold p99':>9} | {'warm p50':>9} | {'warm p99':>9} | iters cold/warm")
    methods = list(OURS) + (["rustcpd"] if with_rustcpd else [])
    for method in methods:
        cold, warm, it_c, it_w = [], [], [], []
        prev = None
        for rep in range(reps):
            moved = pts.copy()
            j = rep % len(pts)
            moved[j] += rng.normal(scale=0.3, size=3)
            if method in OURS:
                t0 = time.perf_counter()
                fit = fit_points(model, pts, nrm, method=method)
                cold.append(time.perf_counter() - t0)
                it_c.append(fit.n_iter)
                start = fit if prev is None else prev
                t0 = time.perf_counter()
                prev = fit_points(model, moved, nrm, method=method, init=start)
                warm.append(time.perf_counter() - t0)
                it_w.append(prev.n_iter)
            else:
                import rustcpd

                t0 = time.perf_counter()
                res = rustcpd.register_atlas(pts, model.mean, model.basis, list(model.coef_var))
                cold.append(time.perf_counter() - t0)
                it_c.append(res.iterations)
                start = res if prev is None else prev
                t0 = time.perf_counter()
                prev = rustcpd.register_atlas(moved, model.mean, model.basis, list(model.coef_var),
                                              initial_state=start.state)
                warm.append(time.perf_counter() - t0)
                it_w.append(prev.iterations)
        c, w = 1000 * np.array(cold), 1000 * np.array(warm)
        print(f"{method:>10} | {np.percentile(c, 50):6.1f} ms | {np.percentile(c, 99):6.1f} ms | "
              f"{np.percentile(w, 50):6.1f} ms | {np.percentile(w, 99):6.1f} ms | "
              f"{np.median(it_c):.0f}/{np.median(it_w):.0f}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=8, help="leave-one-out cases (default 8)")
    parser.add_argument("--contours", default=",".join(str(k) for k in range(1, 13)),
                        help="contour counts (default 1..12)")
    parser.add_argument("--reps", type=int, default=100, help="latency fits (default 100)")
    parser.add_argument("--no-itk", action="store_true")
    parser.add_argument("--no-rustcpd", action="store_true")
    parser.add_argument("--fixed-eta", action="store_true",
                        help="also gmm-aniso with a fixed eta = 10 (adaptive_anisotropy=False)")
    parser.add_argument("--skip", default="", help="comma list of sections to skip: mixed,axial,latency")
    parser.add_argument("--quick", action="store_true", help="smoke run: 2 cases, 3 counts, 5 reps")
    args = parser.parse_args(argv)
    counts = [int(c) for c in args.contours.split(",")]
    if args.quick:
        args.cases, counts, args.reps = 2, [1, 3, 6], 5
    with_itk = not args.no_itk
    if with_itk:
        try:
            import itk  # noqa: F401
        except ImportError:
            print("itk-morphologicalcontourinterpolation not installed: ITK column skipped")
            with_itk = False
    shapes, faces, source = load_shapes()
    cases = [int(c) for c in np.linspace(0, len(shapes) - 1, args.cases).round()]
    print(f"Shapes: {source}; {shapes.shape[1]} vertices; LOO cases {cases}")
    skip = set(args.skip.split(","))
    if "mixed" not in skip:
        table, times = accuracy(shapes, faces, cases, counts, "mixed", False, not args.no_rustcpd,
                                args.fixed_eta)
        print_accuracy(table, times, counts, "Accuracy, mixed axial/coronal/sagittal contours")
    if "axial" not in skip:
        table, times = accuracy(shapes, faces, cases, [k for k in counts if k >= 2], "axial",
                                with_itk, not args.no_rustcpd, args.fixed_eta)
        print_accuracy(table, times, [k for k in counts if k >= 2],
                       "Accuracy, parallel axial contours (with ITK morphological contour interpolation)")
    if "latency" not in skip:
        latency(shapes, faces, args.reps, not args.no_rustcpd)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
