"""Procrustes, GPA and transformation synchronisation against known transforms."""

from __future__ import annotations

import numpy as np
import pytest

from core.alignment.transforms import (
    TRANSFORMS,
    align_shapes,
    apply_transform,
    fit_transform,
    generalized_procrustes,
    homogeneous,
    pairwise_transforms,
    procrustes,
    project_linear,
    reference_transforms,
    synchronize_transforms,
)
from core.geometry.toolkit import random_rotation


def random_transform(rng: np.random.Generator, transform: str, translation: float = 50.0) -> np.ndarray:
    rot = random_rotation(rng)
    if transform == "euclidean" and rng.random() < 0.5:
        rot = rot @ np.diag([1.0, 1.0, -1.0])
    if transform == "similarity":
        rot = rot * rng.uniform(0.6, 1.6)
    if transform == "affine":
        rot = rot @ np.diag(rng.uniform(0.6, 1.6, 3)) @ random_rotation(rng)
    return homogeneous(rot, rng.normal(size=3) * translation)


@pytest.fixture
def base_shape() -> np.ndarray:
    return np.random.default_rng(7).normal(size=(150, 3)) * [20.0, 10.0, 6.0]


# ------------------------------------------------------------------------- Procrustes

@pytest.mark.parametrize("transform", TRANSFORMS)
def test_fit_transform_recovers_exact_transform(base_shape, transform):
    rng = np.random.default_rng(1)
    t_true = random_transform(rng, transform)
    target = apply_transform(t_true, base_shape)
    t_est = fit_transform(base_shape, target, transform)
    np.testing.assert_allclose(t_est, t_true, atol=1e-9)


def test_procrustes_options(base_shape):
    rng = np.random.default_rng(2)
    rot = random_rotation(rng)
    mirror = rot @ np.diag([1.0, -1.0, 1.0])
    target = 1.7 * base_shape @ mirror.T + [5.0, -3.0, 2.0]
    # A reflected target: with reflection allowed the fit is exact ...
    t, aligned, rmsd = procrustes(base_shape, target, scaling=True, reflection=True)
    assert rmsd < 1e-9
    assert np.linalg.det(t[:3, :3]) < 0
    np.testing.assert_allclose(aligned, target, atol=1e-9)
    # ... without, the result is a proper rotation (det +1) and cannot be exact.
    t, _, rmsd = procrustes(base_shape, target, scaling=True, reflection=False)
    assert np.linalg.det(t[:3, :3]) > 0
    assert rmsd > 1.0
    # No scaling: the linear part is orthogonal even though the target is scaled.
    t, _, _ = procrustes(base_shape, target @ mirror, scaling=False)
    np.testing.assert_allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0)


def test_procrustes_weights_ignore_outliers(base_shape):
    rng = np.random.default_rng(3)
    t_true = random_transform(rng, "similarity")
    target = apply_transform(t_true, base_shape)
    target[:10] += 100.0  # gross outliers with zero weight
    weights = np.ones(len(base_shape))
    weights[:10] = 0.0
    t, _, rmsd = procrustes(base_shape, target, weights=weights)
    np.testing.assert_allclose(t, t_true, atol=1e-9)
    assert rmsd < 1e-9


def test_project_linear_classes():
    rng = np.random.default_rng(4)
    m = rng.normal(size=(5, 3, 3))
    rot = project_linear(m, "rigid")
    np.testing.assert_allclose(np.linalg.det(rot), 1.0)
    np.testing.assert_allclose(rot @ np.swapaxes(rot, 1, 2), np.broadcast_to(np.eye(3), (5, 3, 3)),
                               atol=1e-12)
    orth = project_linear(m, "euclidean")
    np.testing.assert_allclose(np.abs(np.linalg.det(orth)), 1.0)
    sim = project_linear(m, "similarity")
    assert np.all(np.linalg.det(sim) > 0)
    np.testing.assert_allclose(project_linear(m, "affine"), m)


# ------------------------------------------------------------------------- synchronisation

def consistent_pairwise(absolute: np.ndarray) -> np.ndarray:
    """pairwise[i, j] = T_i^-1 T_j: maps shape j onto shape i, for T_k shape k -> common."""
    return np.linalg.inv(absolute)[:, None] @ absolute[None, :]


@pytest.mark.parametrize("stable", [True, False])
@pytest.mark.parametrize("transform", TRANSFORMS)
def test_synchronisation_exact_transforms(transform, stable):
    rng = np.random.default_rng(5)
    absolute = np.stack([random_transform(rng, transform, translation=200.0) for _ in range(7)])
    pairwise = consistent_pairwise(absolute)
    sync = synchronize_transforms(pairwise, transform, stable=stable)
    # Transitive consistency reproduces every pairwise transform to numerical precision.
    np.testing.assert_allclose(consistent_pairwise(sync), pairwise, atol=1e-8 * 200)
    if transform == "rigid":
        np.testing.assert_allclose(np.linalg.det(sync[:, :3, :3]), 1.0, atol=1e-12)
    # Recovered up to one common gauge transform G: sync_k = G absolute_k.
    gauge = sync[0] @ np.linalg.inv(absolute[0])
    np.testing.assert_allclose(sync, gauge @ absolute, atol=1e-8 * 200)


def test_synchronisation_with_missing_pairs():
    rng = np.random.default_rng(6)
    absolute = np.stack([random_transform(rng, "rigid") for _ in range(6)])
    pairwise = consistent_pairwise(absolute)
    mask = rng.random((6, 6)) < 0.6
    mask |= np.eye(6, k=1, dtype=bool) | np.eye(6, k=-1, dtype=bool)  # keep it connected
    pairwise[~mask] = np.nan
    sync = synchronize_transforms(pairwise, "rigid", mask=mask)
    np.testing.assert_allclose(consistent_pairwise(sync), consistent_pairwise(absolute), atol=1e-8)


def _relative_error(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray) -> float:
    """RMS point error of all relative transforms T_i^-1 T_j applied to ``points``."""
    est = consistent_pairwise(estimate)
    tru = consistent_pairwise(truth)
    diff = apply_transform(est, points) - apply_transform(tru, points)
    return float(np.sqrt((diff ** 2).sum(axis=-1).mean()))


@pytest.mark.parametrize("transform", ["rigid", "similarity", "affine"])
def test_synchronisation_beats_reference_based_with_noise(transform, base_shape):
    """CVPR 2015, Fig. 4: averaging all pairs is more accurate than chaining via a reference."""
    errors_sync, errors_ref = [], []
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        k = 10
        absolute = np.stack([random_transform(rng, transform, translation=30.0) for _ in range(k)])
        noisy = consistent_pairwise(absolute)
        for i in range(k):
            for j in range(k):
                if i != j:
                    noise = homogeneous(np.eye(3) + 0.03 * rng.normal(size=(3, 3)),
                                        rng.normal(size=3) * 1.0)
                    noisy[i, j] = noise @ noisy[i, j]
        sync = synchronize_transforms(noisy, transform)
        ref = reference_transforms(noisy, 0)
        errors_sync.append(_relative_error(sync, absolute, base_shape))
        errors_ref.append(_relative_error(ref, absolute, base_shape))
    assert np.mean(errors_sync) < 0.7 * np.mean(errors_ref), (errors_sync, errors_ref)


def test_synchronize_rejects_bad_input():
    with pytest.raises(ValueError, match="pairwise must be"):
        synchronize_transforms(np.zeros((3, 2, 4, 4)))
    with pytest.raises(ValueError, match="transform must be one of"):
        synchronize_transforms(np.tile(np.eye(4), (3, 3, 1, 1)), "projective")
    # a mask of the wrong shape is named, not a numpy broadcasting error
    with pytest.raises(ValueError, match=r"mask must be \(3, 3\), got shape \(2, 2\)"):
        synchronize_transforms(np.tile(np.eye(4), (3, 3, 1, 1)), mask=np.ones((2, 2), bool))


# ------------------------------------------------------------------------- GPA and front end

@pytest.mark.parametrize("method", ["sync", "gpa"])
@pytest.mark.parametrize("transform", TRANSFORMS)
def test_align_shapes_removes_exact_poses(base_shape, method, transform):
    rng = np.random.default_rng(8)
    poses = np.stack([random_transform(rng, transform) for _ in range(6)])
    shapes = apply_transform(poses, base_shape[None])
    result = align_shapes(shapes, method=method, transform=transform)
    # Every aligned shape is the same shape; the transforms map the inputs onto them.
    np.testing.assert_allclose(result.aligned, np.broadcast_to(result.aligned[0], result.aligned.shape),
                               atol=1e-7)
    np.testing.assert_allclose(apply_transform(result.transforms, shapes), result.aligned, atol=1e-9)
    assert result.rmsd_.max() < 1e-7
    assert result.converged_
    if transform == "rigid":
        np.testing.assert_allclose(np.linalg.det(result.transforms[:, :3, :3]), 1.0, atol=1e-10)
    if transform in ("rigid", "similarity"):
        # The aligned shape is a similarity copy of the base shape.
        _, _, rmsd = procrustes(base_shape, result.aligned[0], scaling=True)
        assert rmsd < 1e-7
    np.testing.assert_allclose(result.mean.mean(axis=0), 0.0, atol=1e-6)


def test_gpa_with_noise_converges_and_reduces_spread(base_shape):
    rng = np.random.default_rng(9)
    shapes = np.stack([apply_transform(random_transform(rng, "similarity"),
                                       base_shape + rng.normal(size=base_shape.shape) * 0.5)
                       for _ in range(8)])
    result = generalized_procrustes(shapes, "similarity")
    assert result.converged_ and 1 <= result.n_iter_ < 100
    # Residual spread is the noise level (0.5 mm per axis -> ~0.8 mm RMS), not the poses.
    assert result.rmsd_.mean() < 1.2
    sync = align_shapes(shapes, "sync", "similarity")
    assert sync.rmsd_.mean() < 1.2
    # Both find the same relative poses up to noise.
    rel_gpa = consistent_pairwise(result.transforms)
    rel_sync = consistent_pairwise(sync.transforms)
    diff = apply_transform(rel_gpa, base_shape) - apply_transform(rel_sync, base_shape)
    assert np.sqrt((diff ** 2).sum(-1).mean()) < 0.5


def test_pairwise_transforms_convention(base_shape):
    rng = np.random.default_rng(10)
    poses = np.stack([random_transform(rng, "rigid") for _ in range(3)])
    shapes = apply_transform(poses, base_shape[None])
    pairwise = pairwise_transforms(shapes, "rigid")
    np.testing.assert_allclose(apply_transform(pairwise[0, 2], shapes[2]), shapes[0], atol=1e-9)


def test_align_shapes_errors():
    with pytest.raises(ValueError, match="method must be one of"):
        align_shapes(np.zeros((3, 10, 3)), method="icp")
    with pytest.raises(ValueError, match=r"shapes must be \(K, N, 3\)"):
        align_shapes(np.zeros((3, 10)))
    bad = np.random.default_rng(0).normal(size=(3, 10, 3))
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        align_shapes(bad)
