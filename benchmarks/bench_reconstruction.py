"""Benchmark of the reconstruction engine against its peers, side by side in one run.

Machine: a shared 2-core machine (other jobs running): the times are upper bounds; compare
columns within one run only.

Cases are split: ``--set tune`` (the cases the defaults were chosen on) and ``--set report``
(the default; never used for choosing parameters). The README quotes ``--set report``.

Section "known" (known correspondences, no pose; the accuracy target of issue 11): a
synthetic family on the demo's 2,000-vertex caudate mesh, x = base + sum of the demo
generator's 6 local factors + 4 smooth global fields (bend, taper, twist, bulge), each
coefficient ~ N(0, 1); a PCA-10 model of 40 training shapes
(``core.evaluation.simulated_user.pca_model``). Left-out shapes of three kinds: "in span" (new
coefficients), "bumps" (in span plus 2 Gaussian bumps along the normal, 4 mm wide, 1 mm high:
not in the model), "other base" (the base shape bent by a quadratic field, 2 mm at the tips,
plus new coefficients: another base shape). Column "span" is the mean per-vertex distance
from the truth to its least-squares projection onto the model's span (mean + factors), i.e.
the part no coefficient can reach. Points: 3 orthogonal contours or 2 parallel axial ones
(``core.evaluation.simulated_user.simulate_user``, 2.5 mm spacing, 0.1 mm in-plane noise). Error: mean
per-vertex distance to the true vertices (mm), the correspondences being known. Methods:
gmm-aniso, gmm-iso, icp (``fit_points(pose="none")``, defaults otherwise) and rustcpd
``register_atlas(optimize_similarity=False, max_iterations=100, tolerance=1e-6)`` with
``lambda_regularization=1`` (the same prior weight as ours: its M-step adds
lambda s2 / eigenvalue to the diagonal, as ours does) and with its default 0.1.

Sections "mixed" / "axial" (with pose): leave-one-out over the demo set's corresponded
ground-truth shapes (``resources/demo/ground_truth.npz``; a synthetic bean family when it is
missing): PCA model of the other shapes, a simulated user draws k contours of the held-out
shape (2 mm spacing, 0.3 mm noise), each method reconstructs the surface with a similarity
pose: gmm-aniso, gmm-aniso without the pose prior (``pose_sd=None``), gmm-iso, icp;
rustcpd ``register_atlas`` (similarity, defaults: 100 iterations, tolerance 1e-3,
lambda 0.1); itk-mci (parallel slices only): ITK's morphological contour interpolation of
the filled contours (0.5 mm voxels), what ITK-SNAP / 3D Slicer users get. Error: symmetric
mean surface distance / Hausdorff distance (mm). The header gives the mean distance of the
held-out shapes from the model span.

Section "families" (issue 27, item 6): the known-correspondence problem without pose on the
independent families of ``benchmarks/recon_families.py`` (PCA-10 of 40 training shapes per
kind, 6 held-out shapes, 3 orthogonal / 2 parallel axial contours, 2 mm spacing, 0.2 mm noise);
the tuning kinds (``--set tune``: bean, planted; global, concave, coarse since 2026-12-07) are
the only ones any default was chosen on, the report kinds (ovoid, tube, twist, ring, mixed,
caudate) are reported. Peers side by side: ours (``fit_points(pose="none")``, defaults) and
rustcpd ``register_atlas`` with ``optimize_similarity=False`` and its documented defaults
otherwise (lambda 0.1, tolerance 1e-3, 100 iterations), and with lambda 1 (our prior weight)
and tolerance 1e-6.
Cells: mean vertex error (mm); the last row the median time per fit.

Latency: a ~2,000-vertex, 50-factor model (the demo topology with extra random smooth bumps
so that PCA has 50 real modes) and 200 contour points; cold fits and warm refits (previous
result as the start, one point dragged by ~0.5 mm, as in the GUI), p50/p99 over ``--reps``.
rustcpd warm refits pass the previous state (``initial_state=``), as its documentation
advises; its limits (100 iterations, tolerance 1e-3, its defaults) are printed.

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

from core.evaluation.simulated_user import pca_model, simulate_user, slice_planes, synthetic_shapes  # noqa: E402
from core.geometry.toolkit import surface_distance  # noqa: E402
from core.reconstruction import fit_points  # noqa: E402

OURS = ("gmm-aniso", "gmm-iso", "icp")
NO_PRIOR = "aniso-no-pose-prior"  # gmm-aniso with pose_sd=None
FIXED_ETA = "aniso-eta10"  # gmm-aniso without the adaptive anisotropy (--fixed-eta)
RUSTCPD_KNOWN = {"rustcpd-l1": 1.0, "rustcpd-l0.1": 0.1}  # lambda_regularization
TUNE_SEEDS, REPORT_SEEDS = range(0, 6), range(100, 112)  # section "known"


def case_split(n_shapes: int, which: str) -> list[int]:
    """Leave-one-out cases: even indices to tune on, odd ones to report."""
    return [c for c in range(n_shapes) if c % 2 == (0 if which == "tune" else 1)]


def span_distance(model, truth: np.ndarray) -> float:
    """Mean per-vertex distance from ``truth`` to its least-squares projection on the span."""
    basis = model.basis
    resid = (truth - model.mean).reshape(-1)
    coef, *_ = np.linalg.lstsq(basis, resid, rcond=None)
    return float(np.linalg.norm((resid - basis @ coef).reshape(-1, 3), axis=1).mean())


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
    methods = (["gmm-aniso", NO_PRIOR, "gmm-iso", "icp"] + ([FIXED_ETA] if with_fixed_eta else [])
               + (["rustcpd"] if with_rustcpd else []) + (["itk-mci"] if with_itk else []))
    table = {m: {k: [] for k in contour_counts} for m in methods}
    times = {m: [] for m in methods}
    spacing = 0.5
    spans = []
    for case in cases:
        model = pca_model(np.delete(shapes, case, axis=0), faces)
        truth = shapes[case]
        spans.append(span_distance(model, truth))
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
                elif method == NO_PRIOR:
                    surf_v = fit_points(model, user.points, user.normals, pose_sd=None).vertices
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
    return table, times, float(np.mean(spans))


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


# ---------------------------------------------------------------------------------------
# Known correspondences, no pose (issue 11's accuracy target)
# ---------------------------------------------------------------------------------------


def known_family(seed: int = 0):
    """Base shape, 10 displacement fields (6 local demo factors + 4 global) and faces."""
    path = ROOT / "resources" / "demo" / "ground_truth.npz"
    if path.exists():
        data = np.load(path)
        base, faces, local = data["base_vertices"], data["base_faces"], data["factors"]
    else:
        shapes, faces = synthetic_shapes(2, subdivisions=4, seed=seed, size=(7.0, 13.0, 26.0))
        base, local = shapes[0], np.zeros((0,) + shapes[0].shape)
    c = base - base.mean(axis=0)
    u = c / np.abs(c).max(axis=0)  # each axis in [-1, 1]
    one = np.ones(len(base))
    fields = np.stack([
        np.stack([u[:, 1] ** 2 - 0.3, 0 * one, 0 * one], axis=1),          # bend along y
        np.stack([c[:, 0] * u[:, 1], c[:, 1] * 0, c[:, 2] * u[:, 1]], axis=1) * 0.08,  # taper
        np.stack([-c[:, 2] * u[:, 1], 0 * one, c[:, 0] * u[:, 1]], axis=1) * 0.06,     # twist
        np.stack([c[:, 0], 0 * one, c[:, 2]], axis=1) * 0.08 * np.exp(-4 * u[:, 1:2] ** 2)])  # bulge
    return base, np.concatenate([local, fields]), faces


def known_shape(base, fields, faces, rng, kind: str) -> np.ndarray:
    from core.geometry.toolkit import vertex_normals

    x = base + np.tensordot(rng.normal(size=len(fields)), fields, axes=1)
    if kind == "bumps":
        normals = vertex_normals(x, faces)
        for centre in x[rng.choice(len(x), 2, replace=False)]:
            bump = np.exp(-((x - centre) ** 2).sum(axis=1) / (2 * 2.0**2))  # 4 mm wide
            x = x + (rng.choice([-1.0, 1.0]) * bump)[:, None] * normals
    elif kind == "other base":
        c = base - base.mean(axis=0)
        t = c[:, 1] / np.abs(c[:, 1]).max()
        x = x + np.stack([2.0 * t**2, 0 * t, -1.0 * t**2], axis=1)  # 2 mm at the tips
    return x


def known_fit(model, user, method: str, rustcpd_options: dict | None) -> np.ndarray:
    """Fitted vertices without pose: ours (``method`` in OURS) or rustcpd ``register_atlas``
    with ``rustcpd_options``."""
    if method in OURS:
        return fit_points(model, user.points, user.normals, method=method, pose="none").vertices
    import rustcpd

    return np.asarray(rustcpd.register_atlas(user.points, model.mean, model.basis,
                                             list(model.coef_var), optimize_similarity=False,
                                             **rustcpd_options).points)


def known_accuracy(which: str, with_rustcpd: bool, quick: bool):
    base, fields, faces = known_family()
    rng = np.random.default_rng(12345)
    train = np.stack([base + np.tensordot(rng.normal(size=len(fields)), fields, axes=1)
                      for _ in range(40)])
    model = pca_model(train, faces, n_factors=10)
    seeds = list(TUNE_SEEDS if which == "tune" else REPORT_SEEDS)[: 2 if quick else None]
    methods = list(OURS) + (list(RUSTCPD_KNOWN) if with_rustcpd else [])
    print(f"\nKnown correspondences, no pose ({which} cases, seeds {seeds[0]}..{seeds[-1]}): "
          f"PCA-{model.n_factors}, {model.n_vertices} vertices; cells: mean vertex error (mm)")
    head = f"{'truth':>10} | {'contours':>12} | {'points':>6} | {'span':>6} | " + " | ".join(
        f"{m:>12}" for m in methods)
    print(head)
    print("-" * len(head))
    times = {m: [] for m in methods}
    for kind in ("in span", "bumps", "other base"):
        for scenario, k, label in (("mixed", 3, "3 orthogonal"), ("axial", 2, "2 parallel")):
            err = {m: [] for m in methods}
            spans, counts = [], []
            for seed in seeds:
                case_rng = np.random.default_rng(seed)
                truth = known_shape(base, fields, faces, case_rng, kind)
                user = simulate_user(truth, faces, k, orientations=scenario, spacing=2.5,
                                     noise=0.1, rng=case_rng)
                spans.append(span_distance(model, truth))
                counts.append(len(user.points))
                for method in methods:
                    t0 = time.perf_counter()
                    v = known_fit(model, user, method, dict(
                        max_iterations=100, tolerance=1e-6,
                        lambda_regularization=RUSTCPD_KNOWN.get(method, 0.0)))
                    times[method].append(time.perf_counter() - t0)
                    err[method].append(float(np.linalg.norm(v - truth, axis=1).mean()))
            print(f"{kind:>10} | {label:>12} | {np.mean(counts):6.0f} | {np.mean(spans):6.3f} | "
                  + " | ".join(f"{np.mean(err[m]):12.4f}" for m in methods))
    print(f"{'time/fit':>10} | {'(median)':>12} | {'':>6} | {'':>6} | "
          + " | ".join(f"{1000 * np.median(times[m]):9.1f} ms" for m in methods))



RUSTCPD_FAMILIES = {"rustcpd (docs)": dict(lambda_regularization=0.1),
                    "rustcpd l1": dict(lambda_regularization=1.0, tolerance=1e-6)}


def family_accuracy(which: str, with_rustcpd: bool, quick: bool, n_held_out: int = 6):
    """Method x kind x contour layout on the independent families (section "families"):
    the mean vertex error (homology: a vertex that slides along the surface counts), then
    the symmetric surface distance to the true surface (the surface alone); with rustcpd,
    gmm-aniso's paired difference from the better rustcpd column per cell (mean and its
    standard error over the held-out shapes: a difference within about 2 SE is a tie)."""
    from core.geometry.toolkit import symmetric_surface_distance

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from recon_families import REPORT, TUNING, family

    kinds = (TUNING if which == "tune" else REPORT)[: 2 if quick else None]
    methods = list(OURS) + (list(RUSTCPD_FAMILIES) if with_rustcpd else [])
    times = {m: [] for m in methods}
    rows = []  # (kind, label, points, {method: vertex errors}, {method: surface distances})
    for kind in kinds:
        # more held-out shapes leave the model and the first 6 as they were (mixed: their 0.05
        # mm vertex noise is drawn after every shape's coefficients, so it differs)
        fam = family(kind, n_held_out=n_held_out)
        model = fam.model
        for scenario, k, label in (("mixed", 3, "3 orthogonal"), ("axial", 2, "2 parallel")):
            err = {m: [] for m in methods}
            surf = {m: [] for m in methods}
            counts = []
            for h, truth in enumerate(fam.held_out[: 2 if quick else None]):
                user = simulate_user(truth, fam.faces, k, orientations=scenario, spacing=2.0,
                                     noise=0.2, rng=np.random.default_rng(h))
                counts.append(len(user.points))
                for method in methods:
                    t0 = time.perf_counter()
                    v = known_fit(model, user, method, RUSTCPD_FAMILIES.get(method))
                    times[method].append(time.perf_counter() - t0)
                    err[method].append(float(np.linalg.norm(v - truth, axis=1).mean()))
                    surf[method].append(symmetric_surface_distance(v, fam.faces, truth, fam.faces))
            rows.append((kind, label, np.mean(counts), err, surf))
    for title, which_cells in (("mean vertex error (mm)", 3), ("symmetric surface distance to the "
                                                             "true surface (mm)", 4)):
        print(f"\nIndependent families, known correspondences, no pose ({which} kinds {kinds}); "
              f"cells: {title} over {n_held_out} held-out shapes")
        print("| kind | contours | points | " + " | ".join(methods) + " |")
        print("|---|---|---|" + "---|" * len(methods))
        for row in rows:
            cells = {m: float(np.mean(row[which_cells][m])) for m in methods}
            best = min(cells.values())
            print(f"| {row[0]} | {row[1]} | {row[2]:.0f} | " + " | ".join(
                f"**{cells[m]:.3f}**" if cells[m] == best else f"{cells[m]:.3f}" for m in methods) + " |")
    print("| time/fit | (median) | | " + " | ".join(f"{1000 * np.median(times[m]):.0f} ms"
                                                  for m in methods) + " |")
    if with_rustcpd:
        _paired_differences(rows)


def _paired_differences(rows) -> None:
    """gmm-aniso minus the better rustcpd column (by the cell's mean) per held-out shape."""
    print("\ngmm-aniso minus the better rustcpd column, mean vertex error (mm): mean +- standard "
          "error of the paired difference, and the shapes where gmm-aniso is closer")
    print("| kind | contours | peer | difference | gmm-aniso closer |")
    print("|---|---|---|---|---|")
    for kind, label, _, err, _ in rows:
        peer = min(RUSTCPD_FAMILIES, key=lambda m: float(np.mean(err[m])))
        d = np.asarray(err["gmm-aniso"]) - np.asarray(err[peer])
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
        print(f"| {kind} | {label} | {peer} | {d.mean():+.4f} +- {se:.4f} | "
              f"{int((d < 0).sum())}/{len(d)} |")


def latency_model(shapes, faces, n_factors=50, seed=0):
    """The demo topology with random smooth bumps added, so PCA has n_factors real modes."""
    rng = np.random.default_rng(seed)
    from core.geometry.toolkit import vertex_normals

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


def latency(shapes, faces, reps: int, with_rustcpd: bool, only: list[str] | None = None):
    model, truth = latency_model(shapes, faces)
    rng = np.random.default_rng(7)
    user = simulate_user(truth, faces, 8, spacing=1.0, rng=rng)
    pick = rng.choice(len(user.points), 200, replace=len(user.points) < 200)
    pts, nrm = user.points[pick], user.normals[pick]
    print(f"\nLatency: model {model.n_vertices} vertices, {model.n_factors} factors, {len(pts)} points,"
          f" {reps} fits each, os.cpu_count()={os.cpu_count()}")
    print("(ours: fit_points defaults; rustcpd: register_atlas defaults, max_iterations=100, "
          "tolerance=1e-3, warm refits with initial_state=previous.state)")
    print(f"{'method':>10} | {'cold p50':>9} | {'cold p99':>9} | {'warm p50':>9} | {'warm p99':>9} "
          "| iters cold/warm")
    methods = list(OURS) + (["rustcpd"] if with_rustcpd else [])
    for method in [m for m in methods if only is None or m in only]:
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
    parser.add_argument("--cases", type=int, default=8,
                        help="leave-one-out cases, spread over the chosen set (default 8)")
    parser.add_argument("--set", choices=("tune", "report"), default="report",
                        help="which cases: those the defaults were tuned on, or the reported ones")
    parser.add_argument("--contours", default=",".join(str(k) for k in range(1, 13)),
                        help="contour counts (default 1..12)")
    parser.add_argument("--reps", type=int, default=100, help="latency fits (default 100)")
    parser.add_argument("--no-itk", action="store_true")
    parser.add_argument("--no-rustcpd", action="store_true")
    parser.add_argument("--fixed-eta", action="store_true",
                        help="also gmm-aniso with a fixed eta = 10 (adaptive_anisotropy=False)")
    parser.add_argument("--skip", default="",
                        help="comma list of sections to skip: known,families,mixed,axial,latency")
    parser.add_argument("--quick", action="store_true", help="smoke run: 2 cases, 3 counts, 5 reps")
    parser.add_argument("--held-out", type=int, default=6,
                        help="section families: held-out shapes per kind (default 6; the model and "
                             "the first 6 stay the same)")
    parser.add_argument("--latency-methods", default=None,
                        help="comma list of methods for the latency section (default all)")
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
    pool = case_split(len(shapes), args.set)
    cases = [pool[int(i)] for i in np.linspace(0, len(pool) - 1, min(args.cases, len(pool))).round()]
    print(f"Shapes: {source}; {shapes.shape[1]} vertices; {args.set} LOO cases {cases}; "
          f"os.cpu_count()={os.cpu_count()}, shared machine: times are upper bounds")
    skip = set(args.skip.split(","))
    if "known" not in skip:
        known_accuracy(args.set, not args.no_rustcpd, args.quick)
    if "families" not in skip:
        family_accuracy(args.set, not args.no_rustcpd, args.quick, args.held_out)
    if "mixed" not in skip:
        table, times, span = accuracy(shapes, faces, cases, counts, "mixed", False,
                                      not args.no_rustcpd, args.fixed_eta)
        print_accuracy(table, times, counts, "Accuracy with pose, mixed axial/coronal/sagittal "
                       f"contours (held-out shapes {span:.3f} mm from the model span, mean)")
    if "axial" not in skip:
        table, times, span = accuracy(shapes, faces, cases, [k for k in counts if k >= 2], "axial",
                                      with_itk, not args.no_rustcpd, args.fixed_eta)
        print_accuracy(table, times, [k for k in counts if k >= 2],
                       "Accuracy with pose, parallel axial contours, and ITK morphological contour "
                       f"interpolation (held-out shapes {span:.3f} mm from the model span, mean)")
    if "latency" not in skip:
        latency(shapes, faces, args.reps, not args.no_rustcpd,
                args.latency_methods.split(",") if args.latency_methods else None)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
