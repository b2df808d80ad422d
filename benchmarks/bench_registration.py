"""Benchmark: image registration (core.registration.volumes) and multi-image registration (register-images).

Part A, automatic model placement (issue 14 item 3): the bundled 1 mm MNI T1 template moved by
known random affines (+-15 deg, +-20 mm, +-10 % per-axis scale about the brain's centre), with
Gaussian noise (3 % of the maximum) and a multiplicative bias field, on a padded grid in
scanner coordinates 120 mm away. Each copy is registered back onto the template; the demo
caudate (template space) is placed on the copy through the recovered transform and compared
with where the known transform puts it (mean and max vertex error, mm). Peers in the same run:

- ``ssm-studio``: :func:`core.registration.volumes.register` with its defaults (8/4/2 mm pyramid,
  Mattes MI on 20,000 random samples per level, regular-step gradient descent);
- ``sitk-tutorial``: SimpleITK's own documented recipe for affine registration (the SimpleITK
  notebooks' "Registration initialisation / multi-resolution" settings: MOMENTS initialiser,
  Mattes MI 50 bins, 1 % random sampling, gradient descent learning rate 1, 100 iterations,
  shrink factors 4/2/1, smoothing sigmas 2/1/0 voxels, scales from physical shift).

Part B, multi-image registration (issue 15, thesis chapter 7): N copies of the T1 at 4 mm under
known random affines (+-10 deg, +-15 mm, +-8 %), each with its own noise and bias field, in
scanner coordinates up to 60 mm apart; ``core.registration.multi_image.register_images`` with
``method="sync"`` (every pair registered both ways, then transformation synchronisation)
against ``method="reference"`` (every image registered to the first). Error: the mean over
ordered pairs (i, j) of the mean displacement over the brain mask (template grey + white matter
> 0.5) between the recovered map j -> i and the true one -- gauge-free, so no common space is
favoured; consistency: the largest displacement between T_ij T_jk and T_ik over all triples
(the raw pairwise registrations are shown for comparison).

Run: ``.venv/bin/python benchmarks/bench_registration.py [--seeds 4] [--images 6] [--part A|B|AB]``
The machine is shared: times are upper bounds.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.datasets.images import moved_copy, random_affine  # noqa: E402
from core.io import load_mesh, load_volume  # noqa: E402
from core.registration.volumes import itk_to_ras, register, volume_to_sitk  # noqa: E402

TEMPLATE = ROOT / "resources" / "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz"
BRAIN_CENTRE = np.array([0.0, -18.0, 18.0])


def _apply(t, x):
    return x @ t[:3, :3].T + t[:3, 3]


def sitk_tutorial(moving_data, moving_affine, fixed_data, fixed_affine, threads):
    """SimpleITK's documented affine recipe (see module docstring); RAS moving->fixed."""
    import SimpleITK as sitk

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(threads)
    fixed = volume_to_sitk(fixed_data, fixed_affine)
    moving = volume_to_sitk(moving_data, moving_affine)
    init = sitk.CenteredTransformInitializer(fixed, moving, sitk.AffineTransform(3),
                                             sitk.CenteredTransformInitializerFilter.MOMENTS)
    r = sitk.ImageRegistrationMethod()
    r.SetMetricAsMattesMutualInformation(numberOfHistogramBins=50)
    r.SetMetricSamplingStrategy(r.RANDOM)
    r.SetMetricSamplingPercentage(0.01, 1)
    r.SetInterpolator(sitk.sitkLinear)
    r.SetOptimizerAsGradientDescent(learningRate=1.0, numberOfIterations=100,
                                    convergenceMinimumValue=1e-6, convergenceWindowSize=10)
    r.SetOptimizerScalesFromPhysicalShift()
    r.SetShrinkFactorsPerLevel([4, 2, 1])
    r.SetSmoothingSigmasPerLevel([2, 1, 0])
    r.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    r.SetInitialTransform(init, inPlace=True)
    r.Execute(fixed, moving)
    return itk_to_ras(init)


def part_a(n_seeds: int, threads: int) -> None:
    template = load_volume(TEMPLATE)
    caudate = np.asarray(load_mesh(ROOT / "resources" / "demo" / "caudate_base.vtk").vertices, float)
    print(f"\nA. template moved by known affines (1 mm, {template.shape}), {threads} threads")
    print(f"{'seed':>4} {'peer':<14} {'seconds':>8} {'caudate mean':>13} {'caudate max':>12}")
    rows: dict[str, list] = {"ssm-studio": [], "sitk-tutorial": []}
    for seed in range(100, 100 + n_seeds):  # seeds 0-9 were used while tuning; reported: 100+
        rng = np.random.default_rng(seed)
        truth = random_affine(rng, center=BRAIN_CENTRE)
        moved = moved_copy(template.data, template.affine, truth, rng)
        truth_pts = _apply(moved.truth, caudate)
        for peer in rows:
            t0 = time.perf_counter()
            if peer == "ssm-studio":
                t = register(moved.data, moved.affine, template.data, template.affine, "affine",
                             threads=threads).transform
            else:
                t = sitk_tutorial(moved.data, moved.affine, template.data, template.affine, threads)
            sec = time.perf_counter() - t0
            err = np.linalg.norm(_apply(np.linalg.inv(t), caudate) - truth_pts, axis=1)
            rows[peer].append((sec, err.mean(), err.max()))
            print(f"{seed:>4} {peer:<14} {sec:8.1f} {err.mean():13.2f} {err.max():12.2f}")
    print(f"\n{'peer':<14} {'median s':>9} {'max s':>7} {'mean err':>9} {'worst max err':>14}")
    for peer, vals in rows.items():
        v = np.array(vals)
        print(f"{peer:<14} {np.median(v[:, 0]):9.1f} {v[:, 0].max():7.1f} {v[:, 1].mean():9.2f} "
              f"{v[:, 2].max():14.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--images", type=int, default=6)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--part", default="AB")
    args = parser.parse_args()
    print("shared 2-core machine: times are upper bounds")
    if "A" in args.part:
        part_a(args.seeds, args.threads)
    if "B" in args.part:
        part_b(args.images, max(1, args.seeds // 2))


def part_b(n_images: int, n_seeds: int, spacing: float = 4.0) -> None:
    import tempfile

    from core.datasets.images import downsample
    from core.io import save_volume
    from core.registration.multi_image import register_images

    template = load_volume(TEMPLATE)
    gm = load_volume(ROOT / "resources" / "mni_icbm152_gm_tal_nlin_sym_09a.nii.gz")
    wm = load_volume(ROOT / "resources" / "mni_icbm152_wm_tal_nlin_sym_09a.nii.gz")
    brain = (gm.data.astype(float) + wm.data.astype(float)) / 255.0 > 0.5
    mask = np.argwhere(brain)[::100].astype(float) @ template.affine[:3, :3].T + template.affine[:3, 3]
    data, affine = downsample(template.data, template.affine, spacing)
    print(f"\nB. multi-image registration: {n_images} copies of the T1 at {spacing:g} mm under known "
          f"affines (+-10 deg, +-15 mm, +-8 %), noise 3 %, bias field; affine; pyramid "
          f"{2 * spacing:g}/{spacing:g} mm")
    print(f"{'seed':>4} {'method':<10} {'pairs':>6} {'seconds':>8} {'error mm':>9} "
          f"{'consistency mm':>15}")
    summary: dict[str, list] = {"sync": [], "reference": []}
    for seed in range(200, 200 + n_seeds):  # seeds 11-12 were used while tuning
        rng = np.random.default_rng(seed)
        folder = Path(tempfile.mkdtemp(prefix="bench_reg_"))
        paths, truths = [], []
        for k in range(n_images):
            truth = random_affine(rng, rotation_deg=10, translation_mm=15, scale=0.08,
                                  center=BRAIN_CENTRE)
            m = moved_copy(data, affine, truth, rng, scanner_offset_mm=rng.uniform(-60, 60, 3))
            save_volume(folder / f"s{k}.nii.gz", m.data, m.affine)
            paths.append(folder / f"s{k}.nii.gz")
            truths.append(m.truth)
        truths = np.stack(truths)
        for method in summary:
            t0 = time.perf_counter()
            res = register_images(paths, "affine", method=method, n_jobs=2,
                                  registration={"levels_mm": (2 * spacing, spacing)})
            sec = time.perf_counter() - t0
            err = _pairwise_error(res.transforms, truths, mask)
            raw = res.pairwise_matrix()[0]
            cons = _consistency(np.linalg.inv(res.transforms)[:, None] @ res.transforms[None, :], mask)
            summary[method].append((sec, err))
            print(f"{seed:>4} {method:<10} {len(res.pairs):>6} {sec:8.1f} {err:9.3f} {cons:15.2e}")
        print(f"{'':>4} {'raw pairs':<10} {'':>6} {'':>8} {_pairwise_error_raw(raw, truths, mask):9.3f} "
              f"{_consistency(raw, mask):15.2e}")
    print(f"\n{'method':<10} {'mean error mm':>14} {'median s':>9}")
    for method, vals in summary.items():
        v = np.array(vals)
        print(f"{method:<10} {v[:, 1].mean():14.3f} {np.median(v[:, 0]):9.1f}")
    print("error: mean over ordered pairs (i, j) of the mean displacement over the brain mask "
          "between the recovered and the true map j -> i (gauge-free); consistency: max over "
          "triples of the displacement between T_ij T_jk and T_ik")


def _displacement(a: np.ndarray, b: np.ndarray, pts: np.ndarray) -> float:
    d = (a - b)[:3]
    return float(np.linalg.norm(pts @ d[:, :3].T + d[:, 3], axis=1).mean())


def _pairwise_error(transforms, truths, mask) -> float:
    n = len(truths)
    return float(np.mean([_displacement(np.linalg.inv(transforms[i]) @ transforms[j],
                                        truths[i] @ np.linalg.inv(truths[j]), _apply(truths[j], mask))
                          for i in range(n) for j in range(n) if i != j]))


def _pairwise_error_raw(pairwise, truths, mask) -> float:
    n = len(truths)
    return float(np.mean([_displacement(pairwise[i, j], truths[i] @ np.linalg.inv(truths[j]),
                                        _apply(truths[j], mask))
                          for i in range(n) for j in range(n) if i != j]))


def _consistency(pairwise, mask) -> float:
    n = len(pairwise)
    worst = 0.0
    for i in range(n):
        for j in range(n):
            for k in range(n):
                if len({i, j, k}) == 3:
                    worst = max(worst, _displacement(pairwise[i, j] @ pairwise[j, k], pairwise[i, k], mask))
    return worst


if __name__ == "__main__":
    main()
