"""The image registration engine: linear (rigid, similarity, affine) registration of two 3D images.

One engine for everything that aligns images in SSM Studio: automatic model placement (patient
image -> the models' template image), ``ssm-studio register`` and the pairwise registrations of
``ssm-studio register-images`` (multi-image registration by transformation synchronisation,
Bernard et al., "Transitively consistent and unbiased multi-image registration using
numerically stable transformation synchronisation", MICCAI workshop on spectral analysis in
medical imaging, 2015; thesis chapter 7).

Method (SimpleITK's registration framework, ``ImageRegistrationMethod``):

- metric: Mattes mutual information (Mattes et al., "PET-CT image registration in the chest
  using free-form deformations", IEEE TMI 2003), so images of different contrast, scanners or a
  bias field register; random sampling of a fixed number of voxels per level (seeded, so a run
  is reproducible);
- multi-resolution: a Gaussian pyramid defined in mm, not in voxels (default 8, 4, 2 mm): each
  level smooths with sigma = half its resolution and resamples both images onto isotropic grids
  of that spacing, so anisotropic or coarse inputs behave like 1 mm ones;
- initialisation: the centres of mass of the intensities are aligned (image moments), which
  brings an image in scanner coordinates far from the template into the capture range;
- transform classes: ``rigid`` (``Euler3DTransform``), ``similarity`` (``Similarity3DTransform``),
  ``affine`` (``AffineTransform``; its coarsest level is solved as a similarity first, which
  keeps the 12 parameters from chasing noise before the pose is found);
- optimiser: regular-step gradient descent with parameter scales from the physical shift
  (a unit step in any parameter moves voxels by about the same distance in mm).

Conventions: the world is RAS mm, as everywhere in SSM Studio. ITK works in LPS: a point
``x_LPS = F x_RAS`` with ``F = diag(-1, -1, 1)``. ITK's registration transform maps *fixed*
physical points to *moving* physical points; :class:`RegistrationResult.transform` is its exact
conversion ``F T_itk^-1 F``: the 4x4 RAS matrix mapping **moving world -> fixed world**, acting
on column vectors (``x_fixed = T @ [x_moving, 1]``). Placing a model built in the fixed
(template) space onto the moving (patient) image therefore uses ``inv(T)``.

Cancellation and progress follow :mod:`core.runtime.progress`: the callback is called at every
optimiser iteration; raising :class:`core.runtime.progress.Cancelled` from it stops the optimiser at
once and the exception propagates.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from core import RESOURCES_DIR
from core.runtime.progress import Cancelled, ProgressCallback, report, sub_progress

TRANSFORMS = ("rigid", "similarity", "affine")
DEFAULT_LEVELS_MM = (8.0, 4.0, 2.0)
_RAS_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])  # its own inverse


def _sitk():
    import SimpleITK as sitk

    return sitk


@dataclass
class RegistrationResult:
    """Outcome of one registration.

    Attributes
    ----------
    transform : (4, 4) float
        RAS world matrix mapping the moving image's world onto the fixed image's world
        (column vectors).
    transform_class : str
        ``rigid``, ``similarity`` or ``affine``.
    metric : float
        Final Mattes mutual information at the finest level (negative; lower is better).
    initial_metric : float
        The same metric after the centre-of-mass initialisation, before optimising.
    iterations : list of int
        Optimiser iterations per level.
    levels_mm : list of float
        The pyramid's resolutions.
    stop_conditions : list of str
        The optimiser's stop reason per level.
    seconds : float
        Wall time.
    """

    transform: np.ndarray
    transform_class: str
    metric: float
    initial_metric: float
    iterations: list = field(default_factory=list)
    levels_mm: list = field(default_factory=list)
    stop_conditions: list = field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (the matrix as nested lists)."""
        return {"transform": np.asarray(self.transform).tolist(),
                "transform_class": self.transform_class,
                "metric": float(self.metric), "initial_metric": float(self.initial_metric),
                "metric_name": "Mattes mutual information (negative, lower is better)",
                "iterations": [int(i) for i in self.iterations],
                "levels_mm": [float(x) for x in self.levels_mm],
                "stop_conditions": list(self.stop_conditions),
                "seconds": float(self.seconds)}


# ----------------------------------------------------------------------------- conversions

def volume_to_sitk(data: np.ndarray, affine: np.ndarray):
    """A float32 SimpleITK image with the geometry of a RAS voxel->world ``affine``.

    ``data`` is indexed [i, j, k] (nibabel order); SimpleITK's index (i, j, k) then holds the
    same voxel, and its origin/spacing/direction are the affine converted to LPS. Oblique and
    flipped grids are kept exactly (a shear in the affine is refused: ITK grids cannot hold it).
    """
    sitk = _sitk()
    affine = np.asarray(affine, dtype=np.float64)
    lps = _RAS_LPS @ affine
    spacing = np.linalg.norm(lps[:3, :3], axis=0)
    if np.any(spacing <= 0):
        raise ValueError("the image affine has a zero voxel size")
    direction = lps[:3, :3] / spacing
    if not np.allclose(direction.T @ direction, np.eye(3), atol=1e-4):
        raise ValueError("the image affine has a shear, which ITK image grids cannot represent")
    u, _, vt = np.linalg.svd(direction)  # exact orthonormal direction for ITK
    image = sitk.GetImageFromArray(np.ascontiguousarray(
        np.asarray(data, dtype=np.float32).transpose(2, 1, 0)))
    image.SetSpacing([float(s) for s in spacing])
    image.SetDirection([float(v) for v in (u @ vt).ravel()])
    image.SetOrigin([float(v) for v in lps[:3, 3]])
    return image


def sitk_affine(image) -> np.ndarray:
    """The RAS voxel->world 4x4 affine of a SimpleITK image (inverse of :func:`volume_to_sitk`)."""
    direction = np.array(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    lps = np.eye(4)
    lps[:3, :3] = direction * np.array(image.GetSpacing())
    lps[:3, 3] = image.GetOrigin()
    return _RAS_LPS @ lps


def sitk_to_array(image) -> np.ndarray:
    """Voxel array of a SimpleITK image indexed [i, j, k] (nibabel order)."""
    return _sitk().GetArrayFromImage(image).transpose(2, 1, 0)


def itk_to_ras(itk_transform) -> np.ndarray:
    """4x4 RAS moving->fixed matrix from an ITK fixed->moving (LPS) linear transform."""
    sitk = _sitk()
    tx = sitk.AffineTransform(3)
    tx.SetMatrix(itk_transform.GetMatrix())
    tx.SetTranslation(itk_transform.GetTranslation())
    tx.SetCenter(itk_transform.GetCenter())
    a = np.array(tx.GetMatrix(), dtype=np.float64).reshape(3, 3)
    c = np.array(tx.GetCenter(), dtype=np.float64)
    t = np.array(tx.GetTranslation(), dtype=np.float64)
    fixed_to_moving = np.eye(4)
    fixed_to_moving[:3, :3] = a
    fixed_to_moving[:3, 3] = c + t - a @ c  # ITK: x' = A (x - c) + c + t
    return _RAS_LPS @ np.linalg.inv(fixed_to_moving) @ _RAS_LPS


def ras_to_itk(transform: np.ndarray):
    """ITK ``AffineTransform`` (fixed->moving, LPS) for a RAS moving->fixed 4x4 matrix."""
    sitk = _sitk()
    fixed_to_moving = _RAS_LPS @ np.linalg.inv(np.asarray(transform, dtype=np.float64)) @ _RAS_LPS
    tx = sitk.AffineTransform(3)
    tx.SetMatrix([float(v) for v in fixed_to_moving[:3, :3].ravel()])
    tx.SetTranslation([float(v) for v in fixed_to_moving[:3, 3]])
    return tx


# ----------------------------------------------------------------------------- pyramid

def _pyramid_level(image, resolution: float):
    """``image`` smoothed to ``resolution`` mm and resampled on an isotropic grid of that spacing."""
    sitk = _sitk()
    spacing = np.array(image.GetSpacing(), dtype=np.float64)
    size = np.array(image.GetSize(), dtype=np.float64)
    if resolution <= spacing.min() * 1.01 and np.allclose(spacing, spacing[0], rtol=0.01):
        return image
    # Gaussian of sigma r/2 on top of what the voxel size already blurs.
    sigma = np.sqrt(np.maximum((resolution / 2.0) ** 2 - (spacing / 2.0) ** 2, 0.0))
    smoothed = image
    if np.any(sigma > 0.05 * spacing):
        smoothed = sitk.SmoothingRecursiveGaussian(image, [float(s) for s in np.maximum(sigma, 1e-3)])
    extent = size * spacing
    new_size = np.maximum(np.ceil(extent / resolution), 1).astype(int)
    direction = np.array(image.GetDirection()).reshape(3, 3)
    # Keep the grid centred on the same physical box.
    first = np.array(image.GetOrigin()) - direction @ (spacing / 2.0)
    origin = first + direction @ (np.full(3, resolution) / 2.0)
    return sitk.Resample(smoothed, [int(s) for s in new_size], sitk.Transform(), sitk.sitkLinear,
                         [float(v) for v in origin], [resolution] * 3,
                         image.GetDirection(), 0.0, sitk.sitkFloat32)


def _pyramid(image, levels: Sequence[float]) -> list:
    """Images for each resolution of ``levels``, each made from the next finer one (cheaper)."""
    order = np.argsort(levels)  # finest first
    out: list = [None] * len(levels)
    current = image
    for idx in order:
        current = _pyramid_level(current, float(levels[idx]))
        out[idx] = current
    return out


def _make_transform(kind: str, previous=None, center=None):
    """A fresh ITK transform of ``kind`` continuing ``previous`` (same map, same centre)."""
    sitk = _sitk()
    if kind == "rigid":
        tx = sitk.Euler3DTransform()
    elif kind == "similarity":
        tx = sitk.Similarity3DTransform()
    else:
        tx = sitk.AffineTransform(3)
    if previous is not None:
        tx.SetCenter(previous.GetCenter())
        tx.SetMatrix(previous.GetMatrix()) if kind == "affine" else _set_rotation(tx, previous)
        tx.SetTranslation(previous.GetTranslation())
    elif center is not None:
        tx.SetCenter(center)
    return tx


def _set_rotation(tx, previous) -> None:
    """Copy previous' linear part into a rigid/similarity transform (projected onto its class)."""
    m = np.array(previous.GetMatrix(), dtype=np.float64).reshape(3, 3)
    u, s, vt = np.linalg.svd(m)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    if hasattr(tx, "SetScale"):
        tx.SetMatrix([float(v) for v in rot.ravel()])
        tx.SetScale(float(np.mean(s)))
    else:
        tx.SetMatrix([float(v) for v in rot.ravel()])


# ----------------------------------------------------------------------------- engine

def register_sitk(fixed, moving, transform: str = "affine", *,
                  levels_mm: Sequence[float] = DEFAULT_LEVELS_MM, n_samples: int = 20000,
                  n_bins: int = 32, max_iterations: int = 200, random_state: int = 0,
                  threads: int | None = None, initial=None, polish: bool = True,
                  progress: ProgressCallback | None = None) -> RegistrationResult:
    """Register two SimpleITK images; see :func:`register` for the parameters.

    ``initial`` is an optional RAS moving->fixed 4x4 starting matrix (default: the centres of
    mass aligned). ``polish`` repeats the finest level once with half the step and new samples.
    """
    sitk = _sitk()
    t0 = time.perf_counter()
    fixed, moving, levels = _checked_inputs(fixed, moving, transform, levels_mm)
    if threads is not None:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(int(threads))
    current = _initial_transform(fixed, moving, transform, initial)
    fixed_pyramid = _pyramid(fixed, levels)
    moving_pyramid = _pyramid(moving, levels)
    iterations: list[int] = []
    stops: list[str] = []
    metric = initial_metric = np.nan
    schedule = _stage_schedule(levels, polish)
    for stage, (li, res, step) in enumerate(schedule):
        kind = transform
        if transform == "affine" and li == 0 and len(levels) > 1 and initial is None:
            kind = "similarity"  # pose first, then the 12 parameters
        current = _make_transform(kind, current)
        f_l, m_l = fixed_pyramid[li], moving_pyramid[li]
        method = _stage_method(current, int(np.prod(f_l.GetSize())), res, step, n_bins=n_bins,
                               n_samples=n_samples, seed=int(random_state) + stage + 1,
                               max_iterations=max_iterations)
        if stage == 0:
            initial_metric = float(method.MetricEvaluate(f_l, m_l))
        _run_stage(method, f_l, m_l, sub_progress(progress, stage / len(schedule),
                                                  (stage + 1) / len(schedule)),
                   f"{res:g} mm", max_iterations)
        iterations.append(int(method.GetOptimizerIteration()))
        stops.append(method.GetOptimizerStopConditionDescription())
        metric = float(method.GetMetricValue())
    report(progress, 1.0, "registered")
    return RegistrationResult(transform=itk_to_ras(current), transform_class=transform,
                              metric=metric, initial_metric=initial_metric,
                              iterations=iterations, levels_mm=levels, stop_conditions=stops,
                              seconds=time.perf_counter() - t0)


def _checked_inputs(fixed, moving, transform: str, levels_mm: Sequence[float]
                    ) -> tuple[Any, Any, list[float]]:
    """Float32 images (neither constant) and the pyramid levels (mm), checked."""
    sitk = _sitk()
    if transform not in TRANSFORMS:
        raise ValueError(f"transform must be one of {', '.join(TRANSFORMS)}; got {transform!r}")
    levels = [float(r) for r in levels_mm]
    if not levels or any(not r > 0 for r in levels):
        raise ValueError(f"levels_mm must be positive resolutions in mm, got {list(levels_mm)}")
    fixed = sitk.Cast(fixed, sitk.sitkFloat32)
    moving = sitk.Cast(moving, sitk.sitkFloat32)
    for name, img in (("fixed", fixed), ("moving", moving)):
        stats = sitk.StatisticsImageFilter()
        stats.Execute(img)
        if not stats.GetVariance() > 0:
            raise ValueError(f"the {name} image is constant: nothing to register")
    return fixed, moving, levels


def _initial_transform(fixed, moving, transform: str, initial):
    """The given RAS start matrix as an ITK transform, else the centres of mass aligned
    (moments: scanner coordinates far from the template's)."""
    sitk = _sitk()
    if initial is not None:
        return _make_transform("affine" if transform == "affine" else transform,
                               ras_to_itk(initial))
    current = sitk.CenteredTransformInitializer(
        fixed, moving, _make_transform("rigid"), sitk.CenteredTransformInitializerFilter.MOMENTS)
    return sitk.Euler3DTransform(current)


def _stage_schedule(levels: list[float], polish: bool) -> list[tuple[int, float, float]]:
    """(level index, resolution mm, first step mm) of every optimisation stage.

    Every level, then the finest once more from where it stopped with a smaller step and a
    fresh sample set: regular-step descent on a sampled metric stops early in a sampling
    artefact's shallow minimum, and the restart leaves it (measured: mean error over the
    brain 1.0-1.3 mm instead of 1.6-3.1 mm for pairs of 4 mm images).
    """
    schedule = [(li, res, res / 2.0) for li, res in enumerate(levels)]
    if polish:
        schedule.append((len(levels) - 1, levels[-1], levels[-1] / 4.0))
    return schedule


def _stage_method(current, n_voxels: int, res: float, step: float, *, n_bins: int,
                  n_samples: int, seed: int, max_iterations: int):
    """The ITK registration method of one stage: Mattes MI on ``n_samples`` seeded random
    samples, linear interpolation, regular-step gradient descent with physical-shift scales,
    optimising ``current`` in place."""
    sitk = _sitk()
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsMattesMutualInformation(numberOfHistogramBins=int(n_bins))
    method.SetMetricSamplingStrategy(method.RANDOM)
    method.SetMetricSamplingPercentage(min(1.0, n_samples / max(n_voxels, 1)), seed)
    method.SetInterpolator(sitk.sitkLinear)
    method.SetOptimizerAsRegularStepGradientDescent(
        learningRate=step, minStep=res / 200.0, numberOfIterations=int(max_iterations),
        relaxationFactor=0.6, gradientMagnitudeTolerance=1e-8)
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetInitialTransform(current, inPlace=True)
    return method


def _run_stage(method, fixed, moving, progress: ProgressCallback | None, label: str,
               max_iterations: int) -> None:
    """Execute one stage, reporting every iteration; an exception from ``progress``
    (``Cancelled``) stops the optimiser at once and is raised here."""
    sitk = _sitk()
    cancelled: list[BaseException] = []

    def on_iteration() -> None:
        frac = min(method.GetOptimizerIteration() / max_iterations, 1.0)
        try:
            report(progress, frac, f"{label}: metric {method.GetMetricValue():.4f}")
        except BaseException as exc:  # Cancelled (or anything): stop the optimiser now
            cancelled.append(exc)
            method.StopRegistration()

    method.AddCommand(sitk.sitkIterationEvent, on_iteration)
    method.Execute(fixed, moving)
    if cancelled:
        raise cancelled[0]


def register(moving_data: np.ndarray, moving_affine: np.ndarray, fixed_data: np.ndarray,
             fixed_affine: np.ndarray, transform: str = "affine", *,
             levels_mm: Sequence[float] = DEFAULT_LEVELS_MM, n_samples: int = 20000,
             n_bins: int = 32, max_iterations: int = 200, random_state: int = 0,
             threads: int | None = None, initial: np.ndarray | None = None,
             polish: bool = True, progress: ProgressCallback | None = None) -> RegistrationResult:
    """Register the moving image onto the fixed image (mutual information, multi-resolution).

    Parameters
    ----------
    moving_data, fixed_data : (I, J, K) arrays
        Voxel values indexed [i, j, k].
    moving_affine, fixed_affine : (4, 4) float
        Voxel -> world RAS mm.
    transform : {"rigid", "similarity", "affine"}
    levels_mm : resolutions of the pyramid, coarse to fine (default 8, 4, 2 mm).
    n_samples : voxels sampled for the metric per level.
    n_bins : histogram bins of the Mattes mutual information.
    max_iterations : optimiser iterations per level.
    random_state : seed of the metric's sampling.
    threads : ITK threads (None: ITK's default, all cores).
    initial : (4, 4) RAS moving->fixed start (None: centres of mass aligned).
    polish : run the finest level a second time (half the step, new samples).
    progress : callable ``progress(fraction, message)``; may raise ``Cancelled``.

    Returns
    -------
    RegistrationResult
        ``transform`` maps moving world -> fixed world (RAS, column vectors).
    """
    return register_sitk(volume_to_sitk(fixed_data, fixed_affine),
                         volume_to_sitk(moving_data, moving_affine), transform,
                         levels_mm=levels_mm, n_samples=n_samples, n_bins=n_bins,
                         max_iterations=max_iterations, random_state=random_state,
                         threads=threads, initial=initial, polish=polish, progress=progress)


def register_volumes(moving, fixed, transform: str = "affine", **kwargs) -> RegistrationResult:
    """:func:`register` for two ``core.io.Volume`` objects (moving onto fixed)."""
    return register(moving.data, moving.affine, fixed.data, fixed.affine, transform, **kwargs)


def resample(data: np.ndarray, affine: np.ndarray, transform: np.ndarray,
             target_shape: Sequence[int], target_affine: np.ndarray, *,
             interpolation: str = "linear", default: float = 0.0) -> np.ndarray:
    """Resample an image through a RAS moving->target ``transform`` onto a target grid.

    The output voxel at target world point y takes the input's value at ``inv(transform) y``.
    Returns a float32 array of ``target_shape`` indexed [i, j, k].
    """
    sitk = _sitk()
    interp = {"linear": sitk.sitkLinear, "nearest": sitk.sitkNearestNeighbor}[interpolation]
    moving = volume_to_sitk(data, affine)
    reference = volume_to_sitk(np.zeros(tuple(int(s) for s in target_shape), np.float32), target_affine)
    out = sitk.Resample(moving, reference, ras_to_itk(transform), interp, float(default),
                        sitk.sitkFloat32)
    return sitk_to_array(out)


def default_template_path() -> Path:
    """The bundled MNI ICBM152 2009a T1 template (the demo models' template space)."""
    return RESOURCES_DIR / "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz"


def threads_default() -> int:
    """Threads for one registration run alone: every core."""
    return os.cpu_count() or 1


__all__ = ["TRANSFORMS", "DEFAULT_LEVELS_MM", "RegistrationResult", "register", "register_sitk",
           "register_volumes", "resample", "volume_to_sitk", "sitk_affine", "sitk_to_array",
           "itk_to_ras", "ras_to_itk", "default_template_path", "Cancelled"]
