"""The fit's posterior: calibrated on a linear-Gaussian problem, shrinking with more contours."""

from __future__ import annotations

import json

import numpy as np
import pytest
from analytic import sphere
from scipy import stats

from core.io import load_model, load_points
from core.models.shape_model import ShapeModel
from core.reconstruction import fit_points
from core.reconstruction.uncertainty import SD_CALIBRATION, ellipsoid, fit_posterior, suggest_slice


def _smooth_model(n_factors: int = 4) -> ShapeModel:
    v, f = sphere(10.0, [0, 0, 0], 3)
    u = v / 10.0
    # low-order radial deformations: x, y, z and x*y along the normal
    basis = np.stack([u[:, 0], u[:, 1], u[:, 2], u[:, 0] * u[:, 1]])[:n_factors]
    factors = basis[:, :, None] * u[None]
    return ShapeModel(v, factors, np.array([4.0, 2.25, 1.0, 0.25])[:n_factors], f)


def test_posterior_is_calibrated_on_the_linear_gaussian_model():
    """Point-to-plane measurements of a linear model with exact correspondences: the true
    coefficients' Mahalanobis distance under the posterior follows chi2(M), i.e. the
    covariance (with the estimated noise) is neither too wide nor too narrow."""
    model = _smooth_model()
    rng = np.random.default_rng(0)
    sigma = 0.1
    normals = model.mean / 10.0
    d2, noise = [], []
    for _ in range(200):
        a = rng.normal(size=4) * np.sqrt(model.coef_var)
        idx = rng.choice(model.n_vertices, 40, replace=False)
        # the true surface moves along the normals only, so the fitted vertex normals are the
        # sphere's and the points lie along them
        pts = model.instance(a)[idx] + rng.normal(scale=sigma, size=(40, 1)) * normals[idx]
        g = np.einsum("pa,pam->pm", normals[idx], model.factors.transpose(1, 2, 0)[idx])
        r = np.einsum("pa,pa->p", normals[idx], pts - model.mean[idx])
        h = g.T @ g / sigma ** 2 + np.diag(1 / model.coef_var)
        a_map = np.linalg.solve(h, g.T @ r / sigma ** 2)
        post = fit_posterior(model, pts, a_map, np.eye(4), pose_mode="none", min_noise_mm=1e-3)
        err = a - a_map
        d2.append(err @ np.linalg.solve(post.coef_cov, err))
        noise.append(np.sqrt(post.noise_var))
    assert np.median(noise) == pytest.approx(sigma, rel=0.1)
    # 95 % of chi2(4) draws fall below its 0.95 quantile: binomial(200, 0.95) range
    inside = np.mean(np.array(d2) < stats.chi2.ppf(0.95, 4))
    assert 0.90 <= inside <= 0.99, inside


def test_no_points_gives_the_prior():
    model = _smooth_model()
    post = fit_posterior(model, np.zeros((0, 3)), np.zeros(4), np.eye(4), pose_mode="none")
    np.testing.assert_allclose(post.coef_cov, np.diag(model.coef_var), rtol=1e-9)
    # vertex SD under the prior: factor 0 moves vertex (10, 0, 0) by u_x * n = 1 along its
    # normal per unit coefficient (SD 2) and the other factors not at all
    i = int(np.argmax(model.mean[:, 0]))
    assert post.vertex_sd()[i] == pytest.approx(2.0 * SD_CALIBRATION, rel=1e-3)
    with_pose = fit_posterior(model, np.zeros((0, 3)), np.zeros(4), np.eye(4))
    assert with_pose.cov.shape == (11, 11)
    # the pose prior adds 1 mm translation SD in every direction
    assert with_pose.vertex_sd()[i] > post.vertex_sd()[i]


def test_target_ellipsoid_and_slice_suggestion():
    model = _smooth_model()
    post = fit_posterior(model, np.zeros((0, 3)), np.zeros(4), np.eye(4), pose_mode="none")
    i = int(np.argmax(model.mean[:, 0]))
    e = ellipsoid(model.mean[i], post.point_covariance([i], [1.0]))
    # vertex (10, 0, 0) moves along x by factors 0 (SD 2) and 3 (u_x u_y = 0 there): 2 SD = 4 mm
    assert e.radius_mm == pytest.approx(4.0 * SD_CALIBRATION, rel=1e-3)
    np.testing.assert_allclose(np.abs(e.axes[0]), [1, 0, 0], atol=1e-6)
    sd = post.vertex_sd()
    s = suggest_slice(model.mean, sd, spacing=1.0)
    # factor 0 (the largest prior variance) moves the x-poles most: a sagittal plane wins
    assert s.view == "sagittal"
    again = suggest_slice(model.mean, sd, spacing=1.0, drawn=[(s.view, s.depth)])
    assert again.view != s.view or abs(again.depth - s.depth) >= 2.0


@pytest.mark.parametrize("method", ["gmm-aniso", "icp"])
def test_spread_shrinks_as_contours_are_added(resources_dir, method):
    demo = resources_dir / "demo"
    model = load_model(demo / "model.npz")
    pts = load_points(demo / "contour_points.csv")
    planes = json.loads((demo / "ground_truth.json").read_text())["synthetic"]["heldout"][
        "contour_planes"]
    ends = np.cumsum([p["n_points"] for p in planes])  # sagittal, coronal, axial contours
    spreads = []
    for end in ends:
        fit = fit_points(model, pts.points[:end], pts.normals[:end], method=method)
        post = fit_posterior(model, pts.points[:end], fit.coef, fit.pose, pose_mode=fit.pose_mode)
        spreads.append(post.vertex_sd().mean())
    assert spreads[0] > spreads[1] > spreads[2] > 0, spreads


def test_pose_aware_posterior_covers_turned_shapes_and_says_the_pose_is_uncertain():
    """Held-out shapes turned by 20 degrees and shifted 5 mm per axis, placed at the points'
    centre (Place here), 3 orthogonal contours: with the fit's deviation from its placement
    and its residual correlation (``fit=``) the true surface lies within 2 SD at more
    vertices than with the fixed 3-degree pose prior, and at >= 83 % on average. Left at the
    stored placement 12 mm away, the posterior says the pose, not the shape, is uncertain."""
    from core.evaluation.simulated_user import pca_model, simulate_user, synthetic_shapes
    from core.geometry.toolkit import rodrigues, vertex_normals

    shapes, faces = synthetic_shapes(25, subdivisions=3, seed=5, size=(3.0, 6.0, 14.0))
    model = pca_model(shapes[4:], faces)
    aware, fixed = [], []
    for h in range(4):
        rng = np.random.default_rng(h)
        axis = rng.normal(size=3)
        rot = rodrigues(np.deg2rad(20.0) * axis / np.linalg.norm(axis))
        centre = shapes[h].mean(axis=0)
        truth = (shapes[h] - centre) @ rot.T + centre + rng.normal(scale=5.0, size=3)
        user = simulate_user(truth, faces, 3, orientations="mixed", rng=rng)
        fit = fit_points(model, user.points, user.normals, placement="points")
        assert fit.placement_source == "points"
        normals = vertex_normals(fit.vertices, faces)
        err = np.abs(np.einsum("ij,ij->i", truth - fit.vertices, normals))
        for out, kw in ((aware, {"fit": fit}), (fixed, {})):
            post = fit_posterior(model, user.points, fit.coef, fit.pose, pose_mode=fit.pose_mode, **kw)
            out.append(np.mean(err <= 2 * post.vertex_sd()))
    assert np.mean(aware) >= 0.83, aware
    assert np.mean(aware) > np.mean(fixed) + 0.03, (aware, fixed)

    truth = shapes[0] + np.array([8.0, -6.0, 6.0])
    user = simulate_user(truth, faces, 3, rng=np.random.default_rng(2))
    fit = fit_points(model, user.points, user.normals)
    post = fit_posterior(model, user.points, fit.coef, fit.pose, fit=fit)
    assert post.pose_dominates  # the fit's warning: the placement is what is uncertain
    assert "the pose is uncertain" in post.message() and "--placement" in post.message()
    # and the fit gets there all the same: 0.38 mm from the truth (5.9 mm while EM could stop
    # where its E-step's neighbour count shrank, issue 27). Measured with the shape prior's
    # weight 1: from 12 mm away the fit reaches the truth in only 3 of 12 such cases with
    # either weight (1 or today's 1.4), and this case is one of them at 1 but not at 1.4
    # (4.8 mm), so the guard keeps the weight it was measured with.
    guard = fit_points(model, user.points, user.normals, prior_weight=1.0)
    assert np.linalg.norm(guard.vertices - truth, axis=1).mean() < 1.0
    placed = fit_points(model, user.points, user.normals, placement="points")
    again = fit_posterior(model, user.points, placed.coef, placed.pose, fit=placed)
    assert again.vertex_sd().mean() < 0.8 * post.vertex_sd().mean()  # measured 0.63


def test_coverage_on_turned_unseen_shapes_per_contour_layout():
    """Issue 27 item 7, a small fixed known-truth case of the benchmark's kind: held-out
    shapes turned by up to 25 degrees and shifted N(0, 10 mm) per axis, placed at the points
    (Place here), 1 axial / 2 parallel / 3 orthogonal contours (2 mm spacing, 0.2 mm noise).
    The true surface lies within 2 SD at >= 88 % of vertices on average per layout (the
    report kinds give 92-97 % per layout, benchmarks/RESULTS.md), and the mode offset (the
    fit's 3 degree pose prior held it off the posterior's mode) adds coverage."""
    from core.evaluation.simulated_user import pca_model, simulate_user, synthetic_shapes
    from core.geometry.toolkit import random_rotation, vertex_normals

    shapes, faces = synthetic_shapes(26, subdivisions=3, seed=11, size=(3.0, 6.0, 14.0))
    model = pca_model(shapes[6:], faces, n_factors=10)
    rng = np.random.default_rng(27)
    truths = []
    for shape in shapes[:6]:
        centre = shape.mean(axis=0)
        truths.append((shape - centre) @ random_rotation(rng, 25.0).T + centre
                      + rng.normal(scale=10.0, size=3))
    for orientation, k in (("axial", 1), ("axial", 2), ("mixed", 3)):
        cover, bare_cover = [], []
        for h, truth in enumerate(truths):
            user = simulate_user(truth, faces, k, orientations=orientation, spacing=2.0, noise=0.2,
                                 rng=np.random.default_rng(100 * h + k))
            fit = fit_points(model, user.points, user.normals, placement="points")
            post = fit_posterior(model, user.points, fit.coef, fit.pose, pose_mode=fit.pose_mode,
                                 fit=fit)
            assert post.offset is not None and post.offset.shape == (post.cov.shape[0],)
            err = np.abs(np.einsum("ij,ij->i", truth - fit.vertices, vertex_normals(fit.vertices, faces)))
            sd = post.vertex_sd()
            cover.append(np.mean(err <= 2 * sd))
            u = np.einsum("na,nap->np", post.normals, post.jacobians)
            bare = SD_CALIBRATION * np.sqrt(((u @ post.cov) * u).sum(axis=1))
            bare_cover.append(np.mean(err <= 2 * bare))
        assert np.mean(cover) >= 0.88, (orientation, k, cover)
        # measured: +2.9 / +0.9 points (2 parallel / 3 orthogonal; +1.9 / +1.7 before the
        # over-relaxed EM brought the fit nearer the mode)
        if k >= 2:
            assert np.mean(cover) >= np.mean(bare_cover) + 0.005, (k, cover, bare_cover)


def test_residual_basis_and_out_of_span_term():
    """The Nystrom factor reproduces the Gaussian kernel between nearby vertices and keeps
    each vertex's unit variance; the residual term (``residual_var_factor``) widens the band
    most far from the points (it is conditioned on them) and counts as shape uncertainty."""
    from core.reconstruction.uncertainty import residual_basis

    model = _smooth_model()
    length = 4.0
    psi = residual_basis(model.mean, length, rank=200)
    assert residual_basis(model.mean, length, rank=200) is psi  # cached per model
    np.testing.assert_allclose((psi ** 2).sum(axis=1), 1.0, rtol=1e-9)
    d = np.linalg.norm(model.mean[:, None] - model.mean[None], axis=2)
    near = (d > 0) & (d < 3.0)
    exact = np.exp(-d[near] ** 2 / (2 * length ** 2))
    assert np.abs((psi @ psi.T)[near] - exact).max() < 0.05
    rng = np.random.default_rng(3)
    a = rng.normal(size=4) * np.sqrt(model.coef_var)
    top = model.mean[:, 2] > 8.0  # a cap of points around the +z pole
    pts = model.instance(a)[top] + rng.normal(scale=0.1, size=(top.sum(), 1)) * model.mean[top] / 10
    plain = fit_posterior(model, pts, a, np.eye(4), pose_mode="none")
    with_gp = fit_posterior(model, pts, a, np.eye(4), pose_mode="none", residual_var_factor=4.0)
    assert with_gp.n_residual > 0 and plain.n_residual == 0
    added = with_gp.vertex_sd() ** 2 - plain.vertex_sd() ** 2
    assert np.all(added > -1e-9)
    far = model.mean[:, 2] < -8.0
    assert added[far].mean() > 3 * added[top].mean()
    shape_plain, _ = plain.variance_shares()
    shape_gp, pose_gp = with_gp.variance_shares()
    assert shape_gp > shape_plain and pose_gp == 0.0


def test_one_contour_has_a_mirror_mode_counted_as_pose(monkeypatch):
    """All points in one plane (or in parallel slices of one view): the section of a shape
    whose centre lies h above the cut looks like the one h below, so the posterior adds the
    mirror mode's shift (-2 h along the plane's normal, weight MIRROR_WEIGHT) to the SD, as
    pose; a crossing contour removes it."""
    from core.reconstruction.uncertainty import MIRROR_WEIGHT

    model = _smooth_model()
    v = model.mean
    ring = np.abs(v[:, 2] - 4.0) < 1.0  # vertices near the plane z = 4, the shape's centre at 0
    pts = v[ring].copy()
    pts[:, 2] = 4.0
    post = fit_posterior(model, pts, np.zeros(4), np.eye(4), pose_mode="none")
    np.testing.assert_allclose(np.abs(post.mirror), [0, 0, np.sqrt(MIRROR_WEIGHT) * 8.0], atol=0.3)
    pole = int(np.argmax(v[:, 2]))  # normal along z: the mirror moves it by 8 mm
    with monkeypatch.context() as m:
        m.setattr("core.reconstruction.uncertainty.MIRROR_WEIGHT", 0.0)
        plain = fit_posterior(model, pts, np.zeros(4), np.eye(4), pose_mode="none")
    assert plain.mirror is None
    added = (post.vertex_sd()[pole] ** 2 - plain.vertex_sd()[pole] ** 2) / SD_CALIBRATION ** 2
    assert added == pytest.approx(MIRROR_WEIGHT * 64.0, rel=0.08)
    _, pose_var = post.variance_shares()
    assert pose_var > 0 and post.pose_dominates and "either side" in post.message()
    assert "either side" not in fit_posterior(model, np.zeros((0, 3)), np.zeros(4), np.eye(4)).message()
    # two parallel axial slices at z = 3 and 5: mirrored about z = 4, the same shift
    two = [v[np.abs(v[:, 2] - z) < 1.0] * [1, 1, 0] + [0, 0, z] for z in (3.0, 5.0)]
    parallel = fit_posterior(model, np.concatenate(two), np.zeros(4), np.eye(4), pose_mode="none")
    np.testing.assert_allclose(parallel.mirror, post.mirror, atol=0.3)
    crossing = np.concatenate([pts, v[np.abs(v[:, 0]) < 0.8]])
    assert fit_posterior(model, crossing, np.zeros(4), np.eye(4), pose_mode="none").mirror is None


def test_the_band_widens_where_the_residuals_run_along_the_contours():
    """Issue 27 item 7: a held-out shape with a bump the model cannot make (outside its span)
    leaves residuals that run along the contours, and its band widens by 1 +
    CORRELATION_WIDENING x the fit's shrunk residual correlation; the same shapes without the
    bump (inside the span) leave white residuals and keep their band. The widening covers
    more of the bumped truth."""
    import dataclasses

    from core.evaluation.simulated_user import pca_model, simulate_user, synthetic_shapes
    from core.geometry.toolkit import vertex_normals
    from core.reconstruction.uncertainty import CORRELATION_WIDENING

    assert CORRELATION_WIDENING > 0
    shapes, faces = synthetic_shapes(26, subdivisions=3, seed=11, size=(3.0, 6.0, 14.0))
    model = pca_model(shapes[6:], faces, n_factors=10)
    inside, outside, gain = [], [], []
    for h, truth in enumerate(shapes[:6]):
        normals = vertex_normals(truth, faces)
        d = np.linalg.norm(truth - (truth.mean(axis=0) + [0.0, 0.0, 8.0]), axis=1)
        bumped = truth + 1.5 * np.exp(-d ** 2 / 18.0)[:, None] * normals  # 1.5 mm, 3 mm wide
        for shape, out in ((truth, inside), (bumped, outside)):
            user = simulate_user(shape, faces, 3, orientations="mixed", spacing=2.0, noise=0.2,
                                 rng=np.random.default_rng(h))
            fit = fit_points(model, user.points, user.normals, placement="points")
            post = fit_posterior(model, user.points, fit.coef, fit.pose, pose_mode=fit.pose_mode,
                                 fit=fit)
            shrunk = (fit.prior_inflation - 1.0) / (fit.prior_inflation + 1.0)
            assert post.widening == pytest.approx(1.0 + CORRELATION_WIDENING * shrunk)
            out.append(post.widening)
            if shape is bumped:
                err = np.abs(np.einsum("ij,ij->i", shape - fit.vertices,
                                       vertex_normals(fit.vertices, faces)))
                bare = dataclasses.replace(post, widening=1.0).vertex_sd()
                gain.append(np.mean(err <= 2 * post.vertex_sd()) - np.mean(err <= 2 * bare))
    assert "may not reach this shape" in dataclasses.replace(post, widening=2.0).message()
    assert "may not reach" not in dataclasses.replace(post, widening=1.0).message()
    # measured: 1.00 for all six in-span shapes; 1.0-4.1 (median 2.3) with the bump
    assert max(inside) == pytest.approx(1.0)
    assert sum(w > 1.3 for w in outside) >= 4, outside
    assert np.mean(gain) > 0.02 and min(gain) >= 0.0, gain


def test_the_widening_scales_the_laplace_part_and_not_the_mirror_mode():
    import dataclasses

    model = _smooth_model()
    v = model.mean
    ring = np.abs(v[:, 2] - 4.0) < 1.0
    pts = v[ring] * [1, 1, 0] + [0, 0, 4.0]  # one axial contour: a mirror mode
    post = fit_posterior(model, pts, np.zeros(4), np.eye(4), pose_mode="none")
    assert post.mirror is not None and post.widening == 1.0  # no fit: nothing measured
    wide = dataclasses.replace(post, widening=2.0)
    mirror_var = (post.normals @ post.mirror) ** 2
    laplace = post.vertex_sd() ** 2 / SD_CALIBRATION ** 2 - mirror_var
    np.testing.assert_allclose(wide.vertex_sd() ** 2 / SD_CALIBRATION ** 2,
                               4.0 * laplace + mirror_var, rtol=1e-9, atol=1e-12)
    idx, w = np.array([0, 1, 2]), np.full(3, 1.0 / 3.0)
    mirror_cov = np.outer(post.mirror, post.mirror)
    np.testing.assert_allclose(wide.point_covariance(idx, w) / SD_CALIBRATION ** 2,
                               4.0 * (post.point_covariance(idx, w) / SD_CALIBRATION ** 2
                                      - mirror_cov) + mirror_cov, rtol=1e-9, atol=1e-12)


def test_the_mirror_weight_follows_the_objective_gap_only_when_a_temperature_is_set(monkeypatch):
    """``MIRROR_TEMPERATURE`` (off by default): the mirror mode's weight is MIRROR_WEIGHT x
    2 / (1 + exp(gap / T)), the two starts' odds under the fit's objective; without a gap (no
    restart) or a temperature it is MIRROR_WEIGHT."""
    from types import SimpleNamespace

    from core.reconstruction import uncertainty as u

    fit = SimpleNamespace(mirror_gap=2.0)
    assert u.mirror_weight(fit) == u.MIRROR_WEIGHT
    monkeypatch.setattr(u, "MIRROR_TEMPERATURE", 1.0)
    assert u.mirror_weight(fit) == pytest.approx(u.MIRROR_WEIGHT * 2.0 / (1.0 + np.exp(2.0)))
    assert u.mirror_weight(SimpleNamespace(mirror_gap=0.0)) == pytest.approx(u.MIRROR_WEIGHT)
    assert u.mirror_weight(SimpleNamespace(mirror_gap=float("nan"))) == u.MIRROR_WEIGHT
    assert u.mirror_weight(None) == u.MIRROR_WEIGHT
