"""Is the fit's uncertainty honest? Coverage of the true surface by the posterior's 2 SD band.

Leave-one-out on the demo caudates (ground-truth corresponded shapes, so the true position of
every fitted vertex is known): a PCA model of the other 23 shapes is fitted (gmm-aniso, the
default) to a simulated user's contours on the left-out shape; ``core.reconstruction.uncertainty`` gives each
vertex's posterior SD along its normal; the true error there is the normal component of
(true vertex - fitted vertex). Reported per contour count: the share of vertices whose true
error is within 2 SD (95 % expected for a calibrated posterior), the mean SD and the mean
true error (mm), and the 2 SD radius of the target (centroid-anchored) ellipsoid.

Cases 0-3 are kept for tuning: ``--tune`` prints, from them only, the factor by which the
Laplace SDs must be widened so that 95 % of their vertices fall within 2 SD
(``core.reconstruction.uncertainty.SD_CALIBRATION`` holds the value in use); the table reports cases 4-23.

    python benchmarks/bench_uncertainty.py [--cases N] [--tune]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.geometry.toolkit import vertex_normals  # noqa: E402
from core.planning.frames import anchored_point_weights, volume_centroid  # noqa: E402
from core.reconstruction import fit_points  # noqa: E402
from core.evaluation.simulated_user import pca_model, simulate_user  # noqa: E402
from core.reconstruction.uncertainty import SD_CALIBRATION, ellipsoid, fit_posterior  # noqa: E402

TUNING_CASES = (0, 1, 2, 3)


def load_shapes():
    data = np.load(ROOT / "resources" / "demo" / "ground_truth.npz")
    return data["corresponded_shapes"], data["base_faces"]


def run(cases, counts=(1, 2, 3, 6, 10)):
    shapes, faces = load_shapes()
    rows = {k: {"cover": [], "sd": [], "err": [], "target_mm": [], "target_err": [], "z": []}
            for k in counts}
    for case in cases:
        model = pca_model(np.delete(shapes, case, axis=0), faces)
        truth = shapes[case]
        idx, w = anchored_point_weights(model.mean, volume_centroid(model.mean, faces))
        for k in counts:
            rng = np.random.default_rng(1000 * case + k)
            user = simulate_user(truth, faces, k, orientations="mixed", rng=rng)
            if len(user.points) < 3:
                continue
            fit = fit_points(model, user.points, user.normals, method="gmm-aniso")
            post = fit_posterior(model, user.points, fit.coef, fit.pose, pose_mode=fit.pose_mode)
            sd = post.vertex_sd()
            normals = vertex_normals(fit.vertices, faces)
            err = np.abs(np.einsum("ij,ij->i", truth - fit.vertices, normals))
            rows[k]["cover"].append(np.mean(err <= 2 * sd))
            rows[k]["z"].append(err / np.maximum(sd, 1e-12) * SD_CALIBRATION)  # uncalibrated
            rows[k]["sd"].append(sd.mean())
            rows[k]["err"].append(err.mean())
            e = ellipsoid(w @ fit.vertices[idx], post.point_covariance(idx, w))
            rows[k]["target_mm"].append(e.radius_mm)
            rows[k]["target_err"].append(np.linalg.norm(w @ truth[idx] - e.centre))
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=20, help="reported cases (from case 4 on)")
    parser.add_argument("--tune", action="store_true",
                        help="print the SD calibration factor from the tuning cases 0-3 only")
    args = parser.parse_args(argv)
    if args.tune:
        rows = run(TUNING_CASES)
        z = np.concatenate([np.concatenate(r["z"]) for r in rows.values() if r["z"]])
        print(f"tuning cases {TUNING_CASES}: 95th percentile of |error| / SD = "
              f"{np.percentile(z, 95):.3f}; SD_CALIBRATION = {np.percentile(z, 95) / 2:.3f} "
              f"(in use: {SD_CALIBRATION})")
        return 0
    shapes, _ = load_shapes()
    cases = [c for c in range(len(shapes)) if c not in TUNING_CASES][:args.cases]
    t0 = time.perf_counter()
    rows = run(cases)
    print(f"Posterior coverage, demo caudates, leave-one-out PCA, gmm-aniso, "
          f"{len(cases)} reported cases ({time.perf_counter() - t0:.0f} s; machine shared)")
    print("| contours | within 2 SD | mean SD (mm) | mean true error (mm) | target 2 SD radius (mm) "
          "| target error (mm) |")
    print("|---|---|---|---|---|---|")
    for k, r in rows.items():
        if not r["cover"]:
            continue
        print(f"| {k} | {100 * np.mean(r['cover']):.1f} % | {np.mean(r['sd']):.3f} | "
              f"{np.mean(r['err']):.3f} | {np.mean(r['target_mm']):.2f} | "
              f"{np.mean(r['target_err']):.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
