"""core.models: PCA vs numpy's SVD, the estimator contract, LSF's proximal operators and factor
splitting, and recovery of planted local-support factors (LSF, SPLOCS) vs PCA's global ones."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from core.io import load_model, save_model
from core.models import LSF, METHODS, PCA, SPLOCS, Varimax, make_model, model_from_shape_model
from core.models.lsf import _FactorNorm, graph_gradient, prox_sparse_group, split_factors
from core.models.synthetic import ellipsoid_surface, planted_shapes, support_iou
from core.progress import Cancelled
from core import mesh as meshops


@pytest.fixture(scope="module")
def surface():
    return ellipsoid_surface(3)  # 642 vertices


@pytest.fixture(scope="module")
def planted(surface):
    base, faces = surface
    return planted_shapes(base, faces, n_shapes=24, n_factors=6, noise=0.05, random_state=1)


@pytest.fixture(scope="module")
def lsf_fit(planted):
    return LSF(n_factors=12).fit(planted.shapes, planted.faces)


# ------------------------------------------------------------------------------ PCA


def test_pca_matches_numpy_svd():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(10, 50, 3)) * np.linspace(0.1, 3, 50)[None, :, None]
    model = PCA(n_factors=4).fit(X)
    Xc = (X - X.mean(0)).reshape(10, -1)
    _, s, vt = np.linalg.svd(Xc, full_matrices=False)
    np.testing.assert_allclose(model.mean_, X.mean(0), atol=1e-12)
    np.testing.assert_allclose(model.coef_var_, s[:4] ** 2 / 9, rtol=1e-10)
    for m in range(4):  # same directions up to sign
        assert abs(abs(model.factors_[m].ravel() @ vt[m]) - 1) < 1e-10
    # coefficients are the projections; transform/inverse_transform round trip in the subspace
    coef = model.transform(X)
    np.testing.assert_allclose(np.abs(coef), np.abs(Xc @ vt[:4].T), atol=1e-9)
    np.testing.assert_allclose(coef.var(0, ddof=1), model.coef_var_, rtol=1e-9)
    full = PCA().fit(X)
    assert full.n_factors_ == 9
    np.testing.assert_allclose(full.inverse_transform(full.transform(X)), X, atol=1e-9)


def test_pca_variance_retained():
    rng = np.random.default_rng(1)
    X = rng.normal(size=(20, 30, 3)) * np.geomspace(5, 0.01, 30)[None, :, None]
    model = PCA(variance_retained=0.9).fit(X)
    ratio = np.cumsum(PCA().fit(X).explained_variance_ratio_)
    m = model.n_factors_
    assert ratio[m - 1] >= 0.9 - 1e-12 and (m == 1 or ratio[m - 2] < 0.9)


# ------------------------------------------------------------------------------ contract


@pytest.mark.parametrize("method", METHODS)
def test_estimator_contract(method, planted):
    model = make_model(method, n_factors=6)
    assert model.get_params()["n_factors"] == 6
    assert model.fit(planted.shapes[:10], planted.faces) is model
    n = planted.shapes.shape[1]
    m = model.n_factors_
    assert model.mean_.shape == (n, 3) and model.factors_.shape == (m, n, 3)
    assert model.coef_var_.shape == (m,) and np.all(model.coef_var_ > 0)
    coef = model.transform(planted.shapes[:3])
    assert coef.shape == (3, m)
    # Least squares: the residual is orthogonal to every factor (normal equations).
    resid = (planted.shapes[:3] - model.inverse_transform(coef)).reshape(3, -1)
    basis = model.factors_.reshape(m, -1)
    assert np.abs(resid @ basis.T).max() < 1e-8 * np.abs(planted.shapes).max() * n
    samples = model.sample(5, random_state=3)
    assert samples.shape == (5, n, 3)
    np.testing.assert_allclose(model.sample(5, random_state=3), samples)
    # Sorted by explained variance.
    explained = model.coef_var_ * np.sum(model.factors_ ** 2, axis=(1, 2))
    assert np.all(np.diff(explained) <= 1e-9 * explained[0])


def test_errors_are_clear(surface):
    base, faces = surface
    with pytest.raises(ValueError, match="unknown model method"):
        make_model("ica")
    with pytest.raises(ValueError, match="unknown parameter"):
        make_model("lsf", lambda1=3)
    with pytest.raises(ValueError, match=r"\(K, N, 3\)"):
        PCA().fit(np.zeros((5, 10)))
    with pytest.raises(ValueError, match="needs the mesh faces"):
        LSF().fit(np.stack([base, base * 1.1, base * 0.9]))
    with pytest.raises(ValueError, match="lambda_1 must be in"):
        LSF(lambda_1=-1).fit(np.stack([base, base * 1.1, base * 0.9]), faces)
    with pytest.raises(ValueError, match="graph must be one of"):
        LSF(graph="knn").fit(np.stack([base, base * 1.1, base * 0.9]), faces)
    with pytest.raises(ValueError, match="not fitted"):
        PCA().transform(base[None])


def test_save_load_round_trip(tmp_path, planted, lsf_fit):
    shape_model = lsf_fit.to_shape_model(planted.faces, world_transform=np.diag([2.0, 2, 2, 1]),
                                         source_meshes=["a", "b"])
    save_model(tmp_path / "m.npz", shape_model)
    loaded = load_model(tmp_path / "m.npz")
    assert loaded.method == "lsf" and loaded.params["lambda_"] == 64.0
    est = model_from_shape_model(loaded)
    assert isinstance(est, LSF)
    np.testing.assert_allclose(est.transform(planted.shapes), lsf_fit.transform(planted.shapes),
                               atol=1e-10)
    np.testing.assert_allclose(loaded.world_instance(), 2 * lsf_fit.mean_)


# ------------------------------------------------------------------------------ LSF pieces


def test_prox_sparse_group_is_exact():
    """Soft-threshold -> group shrink -> l2 shrink is the prox of the sum (nested groups)."""
    rng = np.random.default_rng(4)
    y = rng.normal(size=(6, 3, 1))
    t1, tg, t2 = np.array([0.3]), np.array([0.4]), np.array([0.5])
    x = prox_sparse_group(y, t1, tg, t2)[:, :, 0].ravel()

    def objective(z):
        zz = z.reshape(6, 3)
        return (0.5 * np.sum((z - y.ravel()) ** 2) + t1[0] * np.abs(z).sum()
                + tg[0] * np.linalg.norm(zz, axis=1).sum() + t2[0] * np.linalg.norm(z))

    best = min((minimize(objective, x0, method="Powell", options={"xtol": 1e-10, "ftol": 1e-14,
                                                                  "maxfev": 200000})
                for x0 in (np.zeros(18), y.ravel(), x + 0.01)), key=lambda r: r.fun)
    assert objective(x) <= best.fun + 1e-9
    # optimality: any perturbation increases the objective
    for _ in range(50):
        assert objective(x + 1e-4 * rng.normal(size=18)) >= objective(x) - 1e-12


def test_factor_norm_prox_with_graph_term(surface):
    """The dual iteration converges to the prox of the full factor norm (Eq. 6)."""
    base, faces = surface
    E = graph_gradient(base, faces)
    rng = np.random.default_rng(5)
    n = len(base)
    y = rng.normal(size=(n, 3, 2)) * 0.3
    t = np.array([0.5, 2.0])
    exact = _FactorNorm(E, 0.02, 0.02, 0.05, 0.5, n_inner=3000).prox(y, t)
    fast = _FactorNorm(E, 0.02, 0.02, 0.05, 0.5, n_inner=3)
    for _ in range(60):  # warm-started repeated calls, as in the outer iterations
        approx = fast.prox(y, t)
    norm = _FactorNorm(E, 0.02, 0.02, 0.05, 0.5, n_inner=1)

    def objective(x):
        return 0.5 * np.sum((x - y) ** 2, axis=(0, 1)) + t * norm.values(x)

    assert np.all(objective(exact) <= objective(y))
    np.testing.assert_allclose(objective(approx), objective(exact), rtol=1e-6)
    # the graph term makes the factor smoother than the graph-free prox
    plain = prox_sparse_group(y, t * 0.02, t * 0.05, t * 0.02)
    assert np.all(np.linalg.norm(norm.grad(exact), axis=(0, 1))
                  < np.linalg.norm(norm.grad(plain), axis=(0, 1)))


def test_graph_gradient_weights(surface):
    base, faces = surface
    E = graph_gradient(base, faces)
    e = meshops.edges(faces)
    assert E.shape == (len(e), len(base))
    d = np.linalg.norm(base[e[:, 0]] - base[e[:, 1]], axis=1)
    w = np.exp(-(d / d.mean()) ** 2)
    z = np.random.default_rng(0).normal(size=len(base))
    np.testing.assert_allclose(np.sum((E @ z) ** 2), np.sum(w * (z[e[:, 0]] - z[e[:, 1]]) ** 2))
    dense = graph_gradient(base, faces, graph="euclidean")
    assert dense.shape[0] > E.shape[0]  # second-ring pairs within the weight threshold


def test_factor_splitting(surface, planted):
    base, faces = surface
    two = planted.factors[0] + planted.factors[1]  # one factor, two disjoint regions
    adj = meshops.adjacency(faces, len(base))
    out = split_factors(np.stack([two, planted.factors[2]]), adj)
    assert len(out) == 3
    iou = support_iou(planted.factors[:3], out)
    assert np.all(iou > 0.99)
    np.testing.assert_allclose(sorted(np.linalg.norm(out.reshape(3, -1), axis=1)),
                               sorted(np.linalg.norm(planted.factors[:3].reshape(3, -1), axis=1)),
                               rtol=0.02)


def test_lsf_cancel(planted):
    calls = []

    def progress(fraction, message):
        calls.append(message)
        if len(calls) >= 3:
            raise Cancelled

    with pytest.raises(Cancelled):
        LSF(n_factors=8).fit(planted.shapes, planted.faces, progress=progress)
    assert len(calls) == 3 and "iteration" in calls[-1]


# ------------------------------------------------------------------------------ planted truth


def test_lsf_recovers_planted_local_supports(planted, lsf_fit):
    iou = support_iou(planted.factors, lsf_fit.factors_)
    print(f"LSF support IoU per planted factor: {np.round(iou, 3)} (mean {iou.mean():.3f})")
    assert iou.mean() >= 0.8 and iou.min() >= 0.6
    assert lsf_fit.n_iter_ >= 1


def test_pca_has_global_support(planted):
    pca = PCA(n_factors=6).fit(planted.shapes)
    iou = support_iou(planted.factors, pca.factors_)
    print(f"PCA support IoU per planted factor: {np.round(iou, 3)} (mean {iou.mean():.3f})")
    assert iou.mean() < 0.5
    # each principal component spreads over several planted regions; LSF factors over one
    assert regions_per_factor(planted, pca.factors_).mean() >= 2.0


def regions_per_factor(planted, factors, share=0.1):
    """How many planted support regions hold at least ``share`` of each factor's energy."""
    energy = np.sum(factors ** 2, axis=2)  # (M, N)
    in_region = planted.supports.astype(float) @ energy.T  # (regions, M)
    return np.sum(in_region >= share * energy.sum(1), axis=0)


def test_lsf_factors_each_cover_one_region(planted, lsf_fit):
    counts = regions_per_factor(planted, lsf_fit.factors_)
    strong = lsf_fit.coef_var_ * np.sum(lsf_fit.factors_ ** 2, axis=(1, 2))
    major = strong >= 0.05 * strong.max()  # the factors carrying the planted deformations
    assert np.all(counts[major] == 1)


def test_splocs_recovers_planted_supports(planted):
    model = SPLOCS(n_factors=6).fit(planted.shapes, planted.faces)
    iou = support_iou(planted.factors, model.factors_)
    assert iou.mean() >= 0.8


def test_varimax_rotates_within_the_pca_subspace(planted):
    pca = PCA(n_factors=6).fit(planted.shapes)
    vm = Varimax(n_factors=6).fit(planted.shapes)
    rec_p = pca.inverse_transform(pca.transform(planted.shapes))
    rec_v = vm.inverse_transform(vm.transform(planted.shapes))
    np.testing.assert_allclose(rec_v, rec_p, atol=1e-8)
    assert vm.converged_
    # rotated factors are more local than the principal components
    assert support_iou(planted.factors, vm.factors_).mean() > \
        support_iou(planted.factors, pca.factors_).mean()
