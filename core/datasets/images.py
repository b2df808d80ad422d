"""Images with known geometry for testing and benchmarking registration.

A real image (e.g. the bundled MNI T1 template) is moved by a known affine, degraded the way
scanners degrade images (a smooth multiplicative bias field, additive Gaussian noise) and put on
a grid in "scanner" coordinates far from the template's. The truth is then exact: the returned
``truth`` maps template world -> moved image world (RAS, column vectors), so a registration of
the moved image onto the template should return ``inv(truth)``.

The bias field follows the usual low-order model of MR intensity non-uniformity
(exp of a smooth polynomial over the field of view; cf. Sled et al., N3, IEEE TMI 1998).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.registration.volumes import resample, sitk_affine, sitk_to_array, volume_to_sitk


@dataclass
class MovedImage:
    """A degraded copy of an image under a known transform.

    Attributes
    ----------
    data : (I, J, K) float32
    affine : (4, 4) float
        Voxel -> world RAS of the copy.
    truth : (4, 4) float
        Source world -> copy world (column vectors).
    """

    data: np.ndarray
    affine: np.ndarray
    truth: np.ndarray


def random_affine(rng: np.random.Generator, *, rotation_deg: float = 15.0,
                  translation_mm: float = 20.0, scale: float = 0.10,
                  center: np.ndarray | None = None) -> np.ndarray:
    """A random 4x4 affine: Euler angles within +-rotation_deg, translation within
    +-translation_mm per axis, per-axis scale within 1 +- scale; about ``center`` (mm)."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("xyz", rng.uniform(-rotation_deg, rotation_deg, 3), degrees=True)
    linear = rot.as_matrix() @ np.diag(rng.uniform(1.0 - scale, 1.0 + scale, 3))
    c = np.zeros(3) if center is None else np.asarray(center, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = linear
    out[:3, 3] = c - linear @ c + rng.uniform(-translation_mm, translation_mm, 3)
    return out


def downsample(data: np.ndarray, affine: np.ndarray, spacing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-smoothed copy of an image on an isotropic grid of ``spacing_mm`` (same box)."""
    from core.registration.volumes import _pyramid_level

    small = _pyramid_level(volume_to_sitk(data, affine), float(spacing_mm))
    return sitk_to_array(small), sitk_affine(small)


def bias_field(shape: tuple[int, ...], rng: np.random.Generator, strength: float = 0.3) -> np.ndarray:
    """A smooth multiplicative field exp(p(x)), p a random quadratic over the normalised grid."""
    axes = [np.linspace(-1.0, 1.0, n) for n in shape]
    x, y, z = np.meshgrid(*axes, indexing="ij", sparse=True)
    c = rng.normal(0.0, 1.0, 9)
    c /= np.linalg.norm(c)
    poly = (c[0] * x + c[1] * y + c[2] * z + c[3] * x * y + c[4] * y * z + c[5] * x * z
            + c[6] * x ** 2 + c[7] * y ** 2 + c[8] * z ** 2)
    return np.exp(strength * poly).astype(np.float32)


def moved_copy(data: np.ndarray, affine: np.ndarray, truth: np.ndarray, rng: np.random.Generator, *,
               noise: float = 0.03, bias: float = 0.3, pad_mm: float = 20.0,
               scanner_offset_mm=(100.0, -60.0, 40.0)) -> MovedImage:
    """The image moved by ``truth`` (source world -> copy world), with bias and noise.

    The copy's grid has the source's voxel axes, padded by ``pad_mm`` on every side, and is
    then shifted (grid and content together) by ``scanner_offset_mm``, so its world coordinates
    are far from the source's, as a scanner's are. ``noise`` is the Gaussian noise's standard
    deviation as a fraction of the maximum intensity; ``bias`` the strength of the bias field.
    """
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    pad = np.ceil(pad_mm / spacing).astype(int)
    grid = np.asarray(affine, dtype=np.float64).copy()
    grid[:3, 3] = affine[:3, :3] @ (-pad) + affine[:3, 3]
    shape = tuple(int(s) for s in np.array(data.shape) + 2 * pad)
    offset = np.eye(4)
    offset[:3, 3] = scanner_offset_mm
    truth = offset @ np.asarray(truth, dtype=np.float64)
    grid = offset @ grid
    moved = resample(data, affine, truth, shape, grid)
    moved = moved * bias_field(shape, rng, bias)
    moved = moved + rng.normal(0.0, noise * float(np.max(data)), shape).astype(np.float32)
    return MovedImage(moved.astype(np.float32), grid, truth)
