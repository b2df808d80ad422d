"""core.evaluation: the four measures and compactness on cases with known answers, the process
pool, cancellation, the boxplot figure, and LSF vs SPLOCS sparse reconstruction on planted
local-support shapes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.evaluation import (MEASURES, compactness, evaluate_methods, evaluate_model,
                             plot_metrics, sparse_fit, specificity, summary_table, to_json,
                             vertex_errors)
from core.models import PCA
from core.models.synthetic import ellipsoid_surface, planted_shapes
from core.progress import Cancelled


@pytest.fixture(scope="module")
def subspace_shapes():
    """Shapes exactly in a 3-dimensional affine subspace (no noise)."""
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(40, 3)) * 10
    basis = rng.normal(size=(3, 40, 3))
    coef = rng.normal(size=(12, 3)) * np.array([3.0, 2.0, 1.0])
    return mean + np.tensordot(coef, basis, axes=1)


def test_vertex_errors_analytic():
    a = np.zeros((2, 4, 3))
    b = a.copy()
    b[0, :, 0] = [1, 2, 3, 4]  # distances 1..4
    b[1, 2] = [3, 4, 0]  # one vertex at distance 5
    avg, mx = vertex_errors(a, b)
    np.testing.assert_allclose(avg, [2.5, 1.25])
    np.testing.assert_allclose(mx, [4.0, 5.0])


def test_pca_on_exact_subspace(subspace_shapes):
    res = evaluate_model("pca", subspace_shapes, None, n_factors=3, n_jobs=1, n_samples=50,
                         noise_var=1e-12)
    assert set(MEASURES) <= set(res)
    # 3 modes span the data: reconstruction and leave-one-out generalisation are exact
    assert res["reconstruction"]["max"].max() < 1e-8
    assert res["generalisation"]["max"].max() < 1e-8
    # 5% of 40 vertices = 2 vertices = 6 equations >= 3 unknowns: exact with tiny sigma^2
    assert res["sparse_reconstruction"]["max"].max() < 1e-6
    np.testing.assert_allclose(res["compactness"][-1], 1.0, atol=1e-12)
    assert np.all(np.diff(res["compactness"]) >= 0)
    assert res["specificity"]["avg"].shape == (50,)
    assert res["reconstruction"]["avg"].shape == (12,)


def test_compactness_equals_pca_explained_variance():
    rng = np.random.default_rng(2)
    X = rng.normal(size=(15, 30, 3)) * np.geomspace(3, 0.1, 30)[None, :, None]
    model = PCA(n_factors=6).fit(X)
    ratio = PCA().fit(X).explained_variance_ratio_
    np.testing.assert_allclose(compactness(model, X), np.cumsum(ratio[:6]), rtol=1e-10)


def test_sparse_fit_recovers_coefficients(subspace_shapes):
    model = PCA(n_factors=3).fit(subspace_shapes)
    truth = model.inverse_transform(np.array([1.5, -2.0, 0.5]) * np.sqrt(model.coef_var_))
    idx = np.array([3, 17, 30])
    rec = sparse_fit(model, truth[idx], idx, noise_var=1e-12)
    np.testing.assert_allclose(rec, truth, atol=1e-6)
    # a strong prior pulls towards the mean
    shrunk = sparse_fit(model, truth[idx], idx, noise_var=1e6)
    assert np.abs(shrunk - model.mean_).max() < 0.1 * np.abs(truth - model.mean_).max()


def test_specificity_closest_training_shape():
    shapes = np.zeros((3, 5, 3))
    shapes[1] += 10.0
    shapes[2] -= 10.0
    model = PCA(n_factors=1).fit(shapes)
    model.coef_var_ = np.array([1e-20])  # samples = the mean = shape 0 exactly
    avg, mx = specificity(model, shapes, 4, random_state=0)
    np.testing.assert_allclose(avg, 0.0, atol=1e-8)
    np.testing.assert_allclose(mx, 0.0, atol=1e-8)


def test_pool_matches_serial_and_cancels():
    base, faces = ellipsoid_surface(2)
    data = planted_shapes(base, faces, n_shapes=6, n_factors=3, random_state=0)
    kwargs = dict(n_factors=3, measures=("generalisation", "sparse_reconstruction"))
    serial = evaluate_model("pca", data.shapes, faces, n_jobs=1, **kwargs)
    pooled = evaluate_model("pca", data.shapes, faces, n_jobs=2, **kwargs)
    for name in kwargs["measures"]:
        np.testing.assert_allclose(pooled[name]["avg"], serial[name]["avg"], rtol=1e-10)
        np.testing.assert_allclose(pooled[name]["max"], serial[name]["max"], rtol=1e-10)

    seen = []

    def cancel(fraction, message):
        seen.append(fraction)
        if fraction > 0:
            raise Cancelled

    with pytest.raises(Cancelled):
        evaluate_model("pca", data.shapes, faces, n_jobs=2, progress=cancel, **kwargs)


def test_bad_arguments():
    shapes = np.random.default_rng(0).normal(size=(5, 10, 3))
    with pytest.raises(ValueError, match="unknown measure"):
        evaluate_model("pca", shapes, None, measures=("speed",))
    with pytest.raises(ValueError, match="unknown parameter"):
        evaluate_model("pca", shapes, None, params={"lambda_": 3})
    with pytest.raises(ValueError, match="at least 3 shapes"):
        evaluate_model("pca", shapes[:2], None)


def test_figure_json_and_table(tmp_path, subspace_shapes):
    res = evaluate_methods(["pca", "varimax"], subspace_shapes, None, n_factors=3, n_jobs=1,
                           n_samples=20)
    fig = plot_metrics(res, tmp_path / "m.png", title="test")
    assert (tmp_path / "m.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(fig.axes) == 10  # 4 measures x (avg, max) + compactness (+ blank)
    text = json.dumps(to_json(res))
    back = json.loads(text)
    assert len(back["methods"]["pca"]["generalisation"]["avg"]) == len(subspace_shapes)
    table = summary_table(res)
    assert "varimax" in table and "g0.05_avg" in table


@pytest.mark.slow
def test_lsf_sparse_reconstruction_beats_splocs_on_planted_shapes():
    """The paper's claim, on shapes made of smooth local bumps with disjoint supports of
    different sizes plus noise: over four draws, LSF's sparse reconstruction error (left-out
    shape from 5% of its vertices) is lower on average and in most draws."""
    base, faces = ellipsoid_surface(3)
    errors = {"lsf": [], "splocs": []}
    for seed in (1, 2, 3, 4):
        data = planted_shapes(base, faces, n_shapes=14, n_factors=6, noise=0.05,
                              radius_spread=0.5, random_state=seed)
        res = evaluate_methods(["lsf", "splocs"], data.shapes, faces, n_factors=12, n_jobs=2,
                               measures=("sparse_reconstruction",))
        for method in errors:
            errors[method].append(res[method]["sparse_reconstruction"]["avg"].mean())
    lsf, splocs = np.array(errors["lsf"]), np.array(errors["splocs"])
    print(f"sparse reconstruction (avg, mm): LSF {np.round(lsf, 4)}, SPLOCS {np.round(splocs, 4)}")
    assert lsf.mean() < splocs.mean()
    assert np.sum(lsf < splocs) >= 3
