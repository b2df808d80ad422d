"""core.models: PCA vs numpy's SVD, the estimator contract, LSF's proximal operators and factor
splitting, and recovery of planted local-support factors (LSF, SPLOCS) vs PCA's global ones."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from core.datasets.factors import ellipsoid_surface, planted_shapes, support_iou
from core.geometry import mesh as meshops
from core.io import load_model, save_model
from core.models import LSF, METHODS, PCA, SPLOCS, Varimax, clone, make_model, model_from_shape_model
from core.models.base import edge_adjacency
from core.models.lsf import FactorNorm, graph_gradient, project_l1_ball, prox_sparse_group, split_factors
from core.runtime.progress import Cancelled


@pytest.fixture(scope="module")
def surface():
    return ellipsoid_surface(3)  # 642 vertices


@pytest.fixture(scope="module")
def planted(surface):
    base, faces = surface
    return planted_shapes(base, faces, n_shapes=24, n_factors=6, noise=0.05, random_state=1)


@pytest.fixture(scope="module")
def lsf_fit(planted):
    return LSF(n_factors=12, connectivity=planted.faces).fit(planted.shapes)


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
    model = make_model(method, n_factors=6, connectivity=planted.faces)
    assert model.get_params()["n_factors"] == 6
    assert model.fit(planted.shapes[:10]) is model
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
    three = np.stack([base, base * 1.1, base * 0.9])
    with pytest.raises(ValueError, match="needs the mesh graph"):
        LSF().fit(three)
    with pytest.raises(ValueError, match="'lambda_1' parameter of LSF must be a float in"):
        LSF(lambda_1=-1, connectivity=faces).fit(three)
    with pytest.raises(ValueError, match="'graph' parameter of LSF must be a str among"):
        LSF(graph="knn", connectivity=faces).fit(three)
    with pytest.raises(ValueError, match="'group_norm' parameter"):
        LSF(group_norm="l1", connectivity=faces).fit(three)
    with pytest.raises(ValueError, match="takes only the shapes"):
        LSF().fit(three, faces)  # the old fit(X, faces) call says where the mesh goes now
    with pytest.raises(ValueError, match="not fitted"):
        PCA().transform(base[None])


def test_connectivity_parameter_clone_and_adjacency(planted):
    """The mesh graph is a constructor parameter (as scikit-learn's connectivity): clone keeps
    it, set_params changes it, and a sparse vertex adjacency gives the same LSF as triangles."""
    est = LSF(n_factors=6, max_iter=60, connectivity=planted.faces)
    twin = clone(est)
    assert twin is not est and not hasattr(twin, "model_")
    assert twin.get_params().keys() == est.get_params().keys()
    np.testing.assert_array_equal(twin.connectivity, planted.faces)
    assert twin.connectivity is not planted.faces
    a = est.fit(planted.shapes)
    n = planted.shapes.shape[1]
    adj = edge_adjacency(meshops.edges(planted.faces), n)
    b = clone(est).set_params(connectivity=adj).fit(planted.shapes)
    np.testing.assert_allclose(b.factors_, a.factors_, atol=1e-10)
    assert a.model_.faces.shape == planted.faces.shape and len(b.model_.faces) == 0
    with pytest.raises(ValueError, match="needs mesh triangles"):
        b.to_shape_model()
    assert b.to_shape_model(planted.faces).n_factors == b.n_factors_
    assert "connectivity" not in a.to_shape_model().params  # data, not a setting
    assert "connectivity" not in LSF.setting_names()
    assert LSF.parameter_rule("graph") == ("options", ("mesh", "euclidean"))
    assert LSF.parameter_rule("n_factors") == ("int", 1, None, False)


@pytest.mark.parametrize("method", METHODS)
def test_explained_variance_ratio_follows_the_factors(method, planted):
    """explained_variance_ratio_ is coef_var * ||factor||^2 over the total variance, in the
    factors' order (for PCA: the eigenvalue ratios), and goes into the model file's info."""
    model = make_model(method, n_factors=6, connectivity=planted.faces).fit(planted.shapes)
    X = planted.shapes
    total = np.sum(X.var(axis=0, ddof=1))
    expected = model.coef_var_ * np.sum(model.factors_ ** 2, axis=(1, 2)) / total
    np.testing.assert_allclose(model.explained_variance_ratio_, expected, rtol=1e-12)
    assert np.all(np.diff(model.explained_variance_ratio_) <= 1e-12)
    info = model.to_shape_model(planted.faces).info
    np.testing.assert_allclose(info["explained_variance_ratio"], expected, rtol=1e-12)
    if method == "pca":
        _, s, _ = np.linalg.svd((X - X.mean(0)).reshape(len(X), -1), full_matrices=False)
        np.testing.assert_allclose(model.explained_variance_ratio_, (s ** 2 / np.sum(s ** 2))[:6],
                                   rtol=1e-9)


def test_lsf_drops_factors_that_explain_nothing(planted):
    """Asked for twice the planted number of factors, LSF keeps only factors explaining at
    least min_explained of the variance; with min_explained=0 the weak ones stay."""
    kw = dict(n_factors=12, max_iter=80, connectivity=planted.faces)
    every = LSF(min_explained=0.0, **kw).fit(planted.shapes)
    assert every.explained_variance_ratio_.min() < 0.01
    pruned = LSF(min_explained=0.01, **kw).fit(planted.shapes)
    assert pruned.explained_variance_ratio_.min() >= 0.01
    assert pruned.n_dropped_ > 0 and every.n_factors_ > pruned.n_factors_
    # the planted regions are still all represented after the pruning
    assert support_iou(planted.factors, pruned.factors_).min() >= 0.6


def test_old_lsf_files_keep_their_group_norm():
    """The demo model file predates group_norm: it was built with the l1/l2 norm and without
    dropping factors, and its estimator says so (today's defaults would misdescribe it)."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "resources" / "demo" / "model.npz"
    model = load_model(path)
    if model.method != "lsf" or "group_norm" in model.params:
        pytest.skip("the demo model is not a pre-group_norm LSF file")
    est = model_from_shape_model(model)
    assert est.group_norm == "l2" and est.min_explained == 0.0
    assert est.n_factors_ == model.n_factors
    np.testing.assert_allclose(est.inverse_transform(est.transform(model.mean)), model.mean,
                               atol=1e-9)


def test_lsf_default_factor_count_is_sensible():
    """Issue 17: 24 shapes used to give 128 factors, many explaining 0.0% of the variance.
    With the defaults every factor explains at least 0.5%, the count stays far below that,
    and the shares reported are the model's own (in step with the factors)."""
    base, faces = ellipsoid_surface(2)
    data = planted_shapes(base, faces, n_shapes=24, n_factors=5, noise=0.05, random_state=3)
    model = LSF(connectivity=faces).fit(data.shapes)
    assert model.n_factors_ <= 40
    assert model.explained_variance_ratio_.min() >= 0.005
    assert support_iou(data.factors, model.factors_).min() >= 0.6
    saved = model.to_shape_model()
    np.testing.assert_allclose(saved.info["explained_variance_ratio"],
                               model.explained_variance_ratio_)


def test_save_load_round_trip(tmp_path, planted, lsf_fit):
    shape_model = lsf_fit.to_shape_model(world_transform=np.diag([2.0, 2, 2, 1]),
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
    x = prox_sparse_group(y, t1, tg, t2, "l2")[:, :, 0].ravel()

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


def test_project_l1_ball_matches_direct_projection():
    """The sort-based projection of every triple equals a constrained least-squares solve."""
    from scipy.optimize import minimize as _min

    rng = np.random.default_rng(7)
    V = rng.normal(size=(5, 3, 2)) * 2
    r = np.array([0.7, 3.0])
    P = project_l1_ball(V, r)
    for i in range(5):
        for m in range(2):
            v = V[i, :, m]
            assert np.abs(P[i, :, m]).sum() <= r[m] + 1e-12
            if np.abs(v).sum() <= r[m]:
                np.testing.assert_allclose(P[i, :, m], v)
                continue
            # direct: min ||u - v||^2 s.t. ||u||_1 <= r, as a smooth problem in (u+, u-) >= 0
            res = _min(lambda w: np.sum((w[:3] - w[3:] - v) ** 2), np.zeros(6),
                       jac=lambda w: np.r_[2 * (w[:3] - w[3:] - v), -2 * (w[:3] - w[3:] - v)],
                       bounds=[(0, None)] * 6, method="SLSQP",
                       constraints=[{"type": "ineq", "fun": lambda w: r[m] - w.sum()}],
                       options={"ftol": 1e-14, "maxiter": 500})
            np.testing.assert_allclose(P[i, :, m], res.x[:3] - res.x[3:], atol=1e-6)


@pytest.mark.parametrize("seed", [4, 11])
def test_prox_sparse_group_linf_is_exact(seed):
    """With the paper's l-infinity group norm the composition soft-threshold -> group prox
    (residual of the l1-ball projection) -> l2 shrinkage is still the exact prox: no direct
    minimisation from several starts finds a lower objective."""
    rng = np.random.default_rng(seed)
    y = rng.normal(size=(6, 3, 1))
    t1, tg, t2 = np.array([0.2]), np.array([0.6]), np.array([0.4])
    x = prox_sparse_group(y, t1, tg, t2, "linf")[:, :, 0].ravel()

    def objective(z):
        zz = z.reshape(6, 3)
        return (0.5 * np.sum((z - y.ravel()) ** 2) + t1[0] * np.abs(z).sum()
                + tg[0] * np.abs(zz).max(axis=1).sum() + t2[0] * np.linalg.norm(z))

    best = min((minimize(objective, x0, method="Powell", options={"xtol": 1e-10, "ftol": 1e-14,
                                                                  "maxfev": 200000})
                for x0 in (np.zeros(18), y.ravel(), x + 0.01)), key=lambda r: r.fun)
    assert objective(x) <= best.fun + 1e-9
    for _ in range(50):
        assert objective(x + 1e-4 * rng.normal(size=18)) >= objective(x) - 1e-12
    # l-infinity groups zero whole triples less eagerly than l2 but cap their largest entry:
    # the two norms give different proxes on the same input
    assert not np.allclose(x, prox_sparse_group(y, t1, tg, t2, "l2")[:, :, 0].ravel())


@pytest.mark.parametrize("group_norm", ["linf", "l2"])
def test_factor_norm_prox_with_graph_term(surface, group_norm):
    """The dual iteration converges to the prox of the full factor norm (Eq. 6)."""
    base, faces = surface
    E = graph_gradient(base, meshops.edges(faces))
    rng = np.random.default_rng(5)
    n = len(base)
    y = rng.normal(size=(n, 3, 2)) * 0.3
    t = np.array([0.5, 2.0])
    exact = FactorNorm(E, 0.02, 0.02, 0.05, 0.5, n_inner=3000, group_norm=group_norm).prox(y, t)
    fast = FactorNorm(E, 0.02, 0.02, 0.05, 0.5, n_inner=3, group_norm=group_norm)
    for _ in range(60):  # warm-started repeated calls, as in the outer iterations
        approx = fast.prox(y, t)
    norm = FactorNorm(E, 0.02, 0.02, 0.05, 0.5, n_inner=1, group_norm=group_norm)

    def objective(x):
        return 0.5 * np.sum((x - y) ** 2, axis=(0, 1)) + t * norm.values(x)

    assert np.all(objective(exact) <= objective(y))
    np.testing.assert_allclose(objective(approx), objective(exact), rtol=1e-6)
    # the graph term makes the factor smoother than the graph-free prox
    plain = prox_sparse_group(y, t * 0.02, t * 0.05, t * 0.02, group_norm)
    assert np.all(np.linalg.norm(norm.grad(exact), axis=(0, 1))
                  < np.linalg.norm(norm.grad(plain), axis=(0, 1)))


def test_graph_gradient_weights(surface):
    base, faces = surface
    e = meshops.edges(faces)
    E = graph_gradient(base, e)
    assert E.shape == (len(e), len(base))
    d = np.linalg.norm(base[e[:, 0]] - base[e[:, 1]], axis=1)
    w = np.exp(-(d / d.mean()) ** 2)
    z = np.random.default_rng(0).normal(size=len(base))
    np.testing.assert_allclose(np.sum((E @ z) ** 2), np.sum(w * (z[e[:, 0]] - z[e[:, 1]]) ** 2))
    dense = graph_gradient(base, e, graph="euclidean")
    assert dense.shape[0] > E.shape[0]  # second-ring pairs within the weight threshold


def test_factor_splitting(surface, planted):
    base, faces = surface
    two = planted.factors[0] + planted.factors[1]  # one factor, two disjoint regions
    adj = edge_adjacency(meshops.edges(faces), len(base))
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
        LSF(n_factors=8, connectivity=planted.faces).fit(planted.shapes, progress=progress)
    assert len(calls) == 3 and "iteration" in calls[-1]


# ------------------------------------------------------------------------------ planted truth


def test_lsf_recovers_planted_local_supports(planted, lsf_fit):
    iou = support_iou(planted.factors, lsf_fit.factors_)
    assert iou.mean() >= 0.8 and iou.min() >= 0.6
    assert lsf_fit.n_iter_ >= 1


def test_pca_has_global_support(planted):
    pca = PCA(n_factors=6).fit(planted.shapes)
    iou = support_iou(planted.factors, pca.factors_)
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
    model = SPLOCS(n_factors=6, connectivity=planted.faces).fit(planted.shapes)
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


def _noisy_ovoids(seed: int, noise: float = 0.2):
    """12 ovoids of the ``ovoid`` family on one 1,500-vertex lattice (known correspondences),
    4 bumps (sigma 2 mm) planted at the same material points, plus ``noise`` mm of per-vertex
    correspondence noise; and the planted bumps as factors on the lattice."""
    from core.datasets.families import OVOID_CENTRES, ovoid_base, ovoid_shape, sphere_lattice

    m, faces = sphere_lattice(1500)
    rng = np.random.default_rng([seed, 7])
    shapes = np.stack([ovoid_shape(m, faces, rng, OVOID_CENTRES) for _ in range(12)])
    shapes = shapes + noise * np.random.default_rng([seed, 8]).standard_normal(shapes.shape)
    d2 = ((ovoid_base(m)[None] - ovoid_base(OVOID_CENTRES)[:, None]) ** 2).sum(axis=2)
    planted = np.zeros((len(OVOID_CENTRES), len(m), 3))
    planted[:, :, 0] = np.exp(-d2 / (2 * 2.0 ** 2))
    return shapes, faces, planted


def test_lsf_default_is_local_on_noisy_corresponded_ovoids():
    """Issue 27 item 5: the default LSF finds the 4 bumps planted on ovoids with 0.2 mm of
    correspondence noise (mean best support IoU over 3 populations, 8 factors). With the
    l-infinity group norm at the same weight (the default before) it was 0.15 (0.10, 0.21,
    0.14), with l2 0.26 (0.15, 0.40, 0.22); PCA's 8 components give about 0.06."""
    ious, ious_pca = [], []
    for seed in range(3):
        shapes, faces, planted = _noisy_ovoids(seed)
        ious.append(support_iou(planted, LSF(n_factors=8, connectivity=faces).fit(shapes).factors_).mean())
        ious_pca.append(support_iou(planted, PCA(n_factors=8).fit(shapes).factors_).mean())
    assert np.mean(ious) >= 0.22
    assert np.mean(ious) >= 3 * np.mean(ious_pca)
