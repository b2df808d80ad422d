"""Sparse transformation synchronisation at cohort scale (core.alignment.transforms, issue 15)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.alignment.transforms import (
    align_shapes,
    align_shapes_sparse,
    apply_transform,
    batched_fit_transforms,
    fit_transform,
    shape_neighbours,
    synchronize_sparse,
    synchronize_transforms,
)


def _random_transform(rng, kind):
    t = np.eye(4)
    r = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    if kind == "affine":
        stretch = np.diag(rng.uniform(0.8, 1.2, 3))          # drawn before the second rotation
        r = r @ stretch @ Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    elif kind == "similarity":
        r = r * rng.uniform(0.8, 1.2)
    t[:3, :3] = r
    t[:3, 3] = rng.normal(0, 30, 3)
    return t


def _cohort(k, n, rng, noise=0.5):
    base = rng.normal(0, 10, (n, 3)) * [2.0, 1.2, 0.8]
    modes = rng.normal(0, 1, (3, n, 3))
    poses = np.stack([_random_transform(rng, "similarity") for _ in range(k)])
    shapes = np.stack([apply_transform(p, base + np.einsum("m,mni->ni", rng.normal(0, 1.5, 3), modes)
                                       + rng.normal(0, noise, (n, 3))) for p in poses])
    return shapes, poses


def _relative_error(transforms, poses, shapes):
    errs = []
    for i in range(len(poses)):
        for j in range(len(poses)):
            if i != j:
                d = (np.linalg.inv(transforms[i]) @ transforms[j] - poses[i] @ np.linalg.inv(poses[j]))[:3]
                errs.append(np.linalg.norm(shapes[j] @ d[:, :3].T + d[:, 3], axis=1).mean())
    return float(np.mean(errs))


@pytest.mark.parametrize("kind", ["rigid", "similarity", "affine"])
def test_sparse_sync_exact_on_a_sparse_graph(kind):
    rng = np.random.default_rng(3)
    n = 40
    truth = np.stack([_random_transform(rng, kind) for _ in range(n)])  # item -> common
    ring = [(k, (k + 1) % n) for k in range(n)]
    extra = [(int(a), int(b)) for a, b in rng.integers(0, n, (40, 2)) if a != b]
    pairs = np.array(ring + extra)
    rel = np.linalg.inv(truth[pairs[:, 0]]) @ truth[pairs[:, 1]]  # j -> i
    out = synchronize_sparse(n, pairs, rel, kind)
    implied = np.linalg.inv(out[5]) @ out[23]
    np.testing.assert_allclose(implied, np.linalg.inv(truth[5]) @ truth[23], atol=1e-7)


def test_sparse_sync_on_all_pairs_is_the_dense_method():
    """Every pair measured both ways: the dense spectral problem, solved sparsely."""
    rng = np.random.default_rng(0)
    n = 12
    truth = np.stack([_random_transform(rng, "similarity") for _ in range(n)])
    noisy = np.tile(np.eye(4), (n, n, 1, 1))
    for i in range(n):
        for j in range(n):
            if i != j:
                noise = np.eye(4)
                noise[:3, :3] += rng.normal(0, 0.01, (3, 3))
                noise[:3, 3] = rng.normal(0, 0.5, 3)
                noisy[i, j] = noise @ np.linalg.inv(truth[i]) @ truth[j]
    dense = synchronize_transforms(noisy, "similarity")
    ii, jj = np.nonzero(~np.eye(n, dtype=bool))
    sparse = synchronize_sparse(n, np.column_stack([ii, jj]), noisy[ii, jj], "similarity")
    for i, j in [(0, 1), (4, 9), (11, 3)]:
        np.testing.assert_allclose(np.linalg.inv(sparse[i]) @ sparse[j],
                                   np.linalg.inv(dense[i]) @ dense[j], atol=1e-6)


def test_sparse_alignment_within_5_percent_of_dense():
    rng = np.random.default_rng(1)
    shapes, poses = _cohort(40, 100, rng)
    dense = align_shapes(shapes, "sync", "similarity")
    sparse = align_shapes_sparse(shapes, "similarity", n_neighbors=8)
    e_dense = _relative_error(dense.transforms, poses, shapes)
    e_sparse = _relative_error(sparse.transforms, poses, shapes)
    assert e_sparse <= 1.05 * e_dense, (e_sparse, e_dense)
    np.testing.assert_allclose(sparse.aligned, apply_transform(sparse.transforms, shapes))


def test_neighbour_graph_is_connected_and_sparse():
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(2)
    a, _ = _cohort(30, 50, rng)
    b, _ = _cohort(30, 50, np.random.default_rng(9))  # a second, different population
    shapes = np.concatenate([a, b])
    pairs = shape_neighbours(shapes, 3)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(60, 60))
    assert connected_components(g, directed=False)[0] == 1
    assert len(pairs) <= 60 * 3 + 5 and np.all(pairs[:, 0] < pairs[:, 1])


@pytest.mark.parametrize("kind", ["rigid", "similarity", "euclidean", "affine"])
def test_batched_fits_match_fit_transform(kind):
    rng = np.random.default_rng(4)
    src = rng.normal(0, 10, (5, 30, 3))
    dst = src @ Rotation.random(random_state=1).as_matrix().T * 1.1 + rng.normal(0, 0.3, src.shape)
    batch = batched_fit_transforms(src, dst, kind)
    for p in range(5):
        np.testing.assert_allclose(batch[p], fit_transform(src[p], dst[p], kind), atol=1e-9)


def test_sync_sparse_is_an_alignment_method_of_the_pipeline_and_the_cli(tmp_path):
    """`--align sync-sparse` / `align --method sync-sparse`: the sparse synchronisation from
    the command line; poses recovered as well as the dense method's (known poses)."""
    import json

    from core.build.pipeline import ALIGN_METHODS, align
    from core.cli import main as cli_main
    from core.io import TriMesh, save_mesh

    assert "sync-sparse" in ALIGN_METHODS
    rng = np.random.default_rng(12)
    shapes, poses = _cohort(24, 60, rng)
    sparse = align(shapes, method="sync-sparse")
    dense = align(shapes, method="sync")
    assert sparse.method == "sync-sparse"
    e_sparse = _relative_error(sparse.transforms, poses, shapes)
    e_dense = _relative_error(dense.transforms, poses, shapes)
    assert e_sparse < 1.1 * e_dense  # noise 0.5 mm per coordinate: ~0.5 mm both
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])  # a tetrahedron over 0-3
    paths = []
    for k, s in enumerate(shapes):
        paths.append(tmp_path / f"s{k:02d}.vtk")
        save_mesh(paths[-1], TriMesh(s, faces))
    out = tmp_path / "out"
    assert cli_main(["align", *map(str, paths), "--method", "sync-sparse", "--out", str(out)]) == 0
    report = json.loads((out / "transforms.json").read_text())
    written = np.stack([np.array(s["transform"]) for s in report["shapes"]])
    assert np.allclose(written, sparse.transforms, atol=1e-6)
