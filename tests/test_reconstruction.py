"""Shape-model fitting to points: exact recovery, pose recovery, sparse contours, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from core.evaluation.simulated_user import pca_model, simulate_user, synthetic_shapes
from core.geometry.toolkit import closest_points_on_triangles, rodrigues, surface_distance, vertex_normals
from core.reconstruction import FitResult, fit_points
from core.reconstruction.fit import PRIOR_WEIGHT
from core.runtime.progress import Cancelled


@pytest.fixture(scope="module")
def family():
    """25 corresponded bean shapes (642 vertices) and a PCA model of shapes 1..24."""
    shapes, faces = synthetic_shapes(25, subdivisions=3, seed=5, size=(3.0, 6.0, 14.0))
    return shapes, faces, pca_model(shapes[1:], faces)


def _similarity(rng: np.random.Generator, angle: float, scale: float, shift: float) -> np.ndarray:
    axis = rng.normal(size=3)
    t = np.eye(4)
    t[:3, :3] = scale * rodrigues(angle * axis / np.linalg.norm(axis))
    t[:3, 3] = rng.normal(size=3) * shift / np.sqrt(3)
    return t


def _apply(t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ t[:3, :3].T + t[:3, 3]


def _mean_surface_distance(a: np.ndarray, b: np.ndarray, faces: np.ndarray) -> float:
    return 0.5 * float(surface_distance(a, b, faces).mean() + surface_distance(b, a, faces).mean())


@pytest.mark.parametrize("method,spread", [("gmm-aniso", 1.2), ("gmm-iso", 1.2), ("icp", 1.2)])
def test_exact_recovery_of_a_model_instance_from_dense_points(family, method, spread):
    """Target = model instance (coefficients 1.2 s.d.), all vertices given, pose fixed."""
    _, faces, model = family
    rng = np.random.default_rng(1)
    coef = rng.normal(size=model.n_factors) * np.sqrt(model.coef_var) * spread
    truth = model.world_instance(coef)
    fit = fit_points(model, truth, method=method, pose="none", prior_weight=1.0,
                     min_sigma=0.01, max_iter=200)
    err = np.linalg.norm(fit.vertices - truth, axis=1)
    assert err.max() < 0.02, (method, err.max(), fit.stop_reason)
    # the leading coefficients (the ones the data pins down) are recovered
    assert np.allclose(fit.coef[:4], coef[:4], atol=0.02 * np.sqrt(model.coef_var[0]))
    assert fit.residual_mm < 0.01
    assert fit.pose == pytest.approx(np.eye(4))
    assert np.all(np.diff(fit.objective[1:]) <= 1e-6 * np.abs(fit.objective[1:-1]).max()) \
        or method == "icp"  # EM decreases the objective


@pytest.mark.parametrize("method,pose,degrees", [
    ("gmm-aniso", "similarity", 15.0), ("gmm-iso", "similarity", 15.0),
    ("gmm-aniso", "rigid", 15.0), ("gmm-iso", "rigid", 15.0)])
def test_pose_recovery_for_a_known_transform(family, method, pose, degrees):
    """The mean shape under a known similarity (or rigid) transform, every vertex given.

    (ICP is left out: point-to-vertex ICP stops at a fixed point of its nearest-vertex
    matching, here up to 0.7 mm off for a 1 mm shift, the weakness the GMM removes.)"""
    _, faces, model = family
    rng = np.random.default_rng(2)
    scale = 1.0 if pose == "rigid" else 1.12
    true_pose = _similarity(rng, angle=np.deg2rad(degrees), scale=scale,
                            shift=3.0)
    truth = _apply(true_pose, model.mean)
    fit = fit_points(model, truth, method=method, pose=pose, min_sigma=0.01, max_iter=300,
                     tol=1e-10, xtol=1e-5, pose_first=True)
    assert np.abs(fit.pose - true_pose).max() < 2e-3, (fit.pose, true_pose, fit.stop_reason)
    assert np.linalg.norm(fit.vertices - truth, axis=1).max() < 0.02
    assert fit.scale == pytest.approx(scale, abs=1e-3)


def test_world_transform_is_the_initial_placement(family):
    shapes, faces, model = family
    placed = pca_model(shapes[1:], faces)
    placed.world_transform = _similarity(np.random.default_rng(3), np.deg2rad(30), 1.0, 40.0)
    truth = placed.world_instance(np.zeros(placed.n_factors))
    fit = fit_points(placed, truth[::3], pose="none", min_sigma=0.01)
    assert fit.pose == pytest.approx(placed.world_transform)
    assert np.linalg.norm(fit.vertices - truth, axis=1).max() < 0.05


def test_anisotropic_gmm_beats_icp_on_three_contours(family):
    """Leave-one-out over 6 shapes, true pose perturbed, 3 contours (axial, coronal, sagittal)."""
    shapes, faces, _ = family
    errors = {"gmm-aniso": [], "icp": []}
    for case in range(6):
        model = pca_model(np.delete(shapes, case, axis=0), faces)
        rng = np.random.default_rng(100 + case)
        truth = _apply(_similarity(rng, np.deg2rad(5.0), 1.0, 1.7), shapes[case])
        user = simulate_user(truth, faces, 3, spacing=2.0, noise=0.3, rng=rng)
        assert 30 < len(user.points) < 120
        for method in errors:
            fit = fit_points(model, user.points, user.normals, method=method)
            errors[method].append(_mean_surface_distance(fit.vertices, truth, faces))
    aniso, icp = np.mean(errors["gmm-aniso"]), np.mean(errors["icp"])
    # 0.75 while ICP was point-to-point; point-to-plane ICP (issue 27) is closer
    assert aniso < 0.9 * icp, errors
    assert aniso < 0.35  # mm, on shapes about 6 x 12 x 28 mm


def test_warm_start_continues_from_the_previous_fit(family):
    shapes, faces, model = family
    rng = np.random.default_rng(4)
    user = simulate_user(shapes[0], faces, 4, rng=rng)
    cold = fit_points(model, user.points, user.normals)
    again = fit_points(model, user.points, user.normals, init=cold)
    assert again.n_iter < cold.n_iter
    assert np.abs(again.vertices - cold.vertices).max() < 0.1  # the cold fit stopped at xtol
    moved = user.points.copy()
    moved[0] += 0.5 * user.normals[0]  # one point dragged outwards by 0.5 mm
    warm = fit_points(model, moved, user.normals, init=cold)
    fresh = fit_points(model, moved, user.normals)
    assert warm.n_iter < fresh.n_iter
    # both end as close to the truth (sparse data: not necessarily the same local optimum)
    err_warm = _mean_surface_distance(warm.vertices, shapes[0], faces)
    err_fresh = _mean_surface_distance(fresh.vertices, shapes[0], faces)
    assert err_warm < 0.3 and abs(err_warm - err_fresh) < 0.1, (err_warm, err_fresh)


def test_callback_and_cancel(family):
    _, _, model = family
    pts = model.world_instance()[::5]
    seen = []
    fit_points(model, pts, callback=lambda i, e: seen.append((i, e)))
    assert [i for i, _ in seen] == list(range(len(seen))) and len(seen) >= 1

    def cancel(i, e):
        raise Cancelled()

    with pytest.raises(Cancelled):
        fit_points(model, pts, callback=cancel)


def test_bad_input_gives_clear_errors(family):
    _, _, model = family
    good = model.world_instance()[::10]
    with pytest.raises(ValueError, match="no points"):
        fit_points(model, np.zeros((0, 3)))
    with pytest.raises(ValueError, match="at least 3 points"):
        fit_points(model, good[:2], pose="similarity")
    fit_points(model, good[:2], pose="none")  # enough for a shape-only fit
    bad = good.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        fit_points(model, bad)
    far = good.copy()
    far[0] += 500.0
    with pytest.raises(ValueError, match="far outside the model"):
        fit_points(model, far)
    with pytest.raises(ValueError, match="unknown method"):
        fit_points(model, good, method="magic")
    with pytest.raises(ValueError, match="\\(P, 3\\)"):
        fit_points(model, good[:, :2])
    with pytest.raises(ValueError, match="normals"):
        fit_points(model, good, normals=np.ones((2, 3)))
    wrong = FitResult(coef=np.zeros(3), pose=np.eye(4), vertices=good)
    with pytest.raises(ValueError, match="warm-start"):
        fit_points(model, good, init=wrong)


def test_closest_point_on_triangle_matches_brute_force():
    rng = np.random.default_rng(5)
    a, b, c = (rng.normal(size=(200, 3)) for _ in range(3))
    q = rng.normal(size=(200, 3)) * 2
    got = closest_points_on_triangles(q, a, b, c)
    # brute force over a fine barycentric grid
    u, v = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    keep = (u + v) <= 1
    u, v = u[keep], v[keep]
    grid = a[:, None] + u[None, :, None] * (b - a)[:, None] + v[None, :, None] * (c - a)[:, None]
    brute = np.linalg.norm(grid - q[:, None], axis=2).min(axis=1)
    exact = np.linalg.norm(got - q, axis=1)
    assert np.all(exact <= brute + 1e-9)
    assert np.allclose(exact, brute, atol=0.02 * np.linalg.norm(b - a, axis=1).max())


def test_fit_cli_writes_mesh_and_json(tmp_path, family):
    import json

    from core.cli import main
    from core.io import load_mesh, save_model, save_points

    shapes, faces, model = family
    save_model(tmp_path / "model.npz", model)
    user = simulate_user(shapes[0], faces, 5, rng=np.random.default_rng(3))
    save_points(tmp_path / "pts.csv", user.points, user.normals)
    rc = main(["fit", "--model", str(tmp_path / "model.npz"), "--points", str(tmp_path / "pts.csv"),
               "--method", "gmm-aniso", "--out", str(tmp_path / "fitted.vtk"),
               "--json", str(tmp_path / "result.json")])
    assert rc == 0
    mesh = load_mesh(tmp_path / "fitted.vtk")
    assert mesh.vertices.shape == shapes[0].shape
    assert _mean_surface_distance(mesh.vertices, shapes[0], faces) < 0.3
    result = json.loads((tmp_path / "result.json").read_text())
    assert len(result["coef"]) == model.n_factors and np.shape(result["pose"]) == (4, 4)
    assert result["n_iter"] >= 1 and result["residual_mm"] < 0.5 and result["stop_reason"]
    (tmp_path / "nan.csv").write_text("x,y,z\n1,2,nan\n")
    assert main(["fit", "--model", str(tmp_path / "model.npz"), "--points",
                 str(tmp_path / "nan.csv"), "--out", str(tmp_path / "x.vtk")]) == 2


def test_fit_cli_takes_a_negative_placement_and_warns_of_an_implausible_fit(tmp_path, family,
                                                                          capsys):
    """``--placement -x,y,z`` is a coordinate list, not an option; a fit the GUI would flag
    as implausible (points far from any surface the model can take) is flagged headless too:
    one warning line, and ``warnings`` in --json, by the same policy."""
    import json

    from core.cli import main
    from core.io import save_model, save_points

    shapes, faces, model = family
    save_model(tmp_path / "model.npz", model)
    user = simulate_user(shapes[0], faces, 5, rng=np.random.default_rng(3))
    centre = model.world_instance().mean(axis=0)
    placement = ",".join(f"{v:.3f}" for v in centre - [abs(centre[0]) + 1.0, 0.0, 0.0])
    assert placement.startswith("-")  # argparse alone reads it as an unknown option
    save_points(tmp_path / "pts.csv", user.points, user.normals)
    rc = main(["fit", "--model", str(tmp_path / "model.npz"), "--points", str(tmp_path / "pts.csv"),
               "--placement", placement, "--out", str(tmp_path / "fitted.vtk"),
               "--json", str(tmp_path / "result.json")])
    assert rc == 0
    assert "warnings" in json.loads((tmp_path / "result.json").read_text())
    capsys.readouterr()
    # points scattered in a box three times the model's size: no shape fits them
    rng = np.random.default_rng(0)
    span = np.ptp(shapes[0], axis=0)
    scatter = shapes[0].mean(axis=0) + rng.uniform(-1.5, 1.5, size=(60, 3)) * span
    save_points(tmp_path / "scatter.csv", scatter)
    rc = main(["fit", "--model", str(tmp_path / "model.npz"), "--points",
               str(tmp_path / "scatter.csv"), "--out", str(tmp_path / "bad.vtk"),
               "--json", str(tmp_path / "bad.json")])
    assert rc == 0
    err = capsys.readouterr().err.strip().splitlines()
    flagged = [line for line in err if "warning: implausible fit" in line]
    assert len(flagged) == 1 and "mm from the surface" in flagged[0], err
    assert json.loads((tmp_path / "bad.json").read_text())["warnings"]


def test_pose_prior_steadies_a_single_contour_fit(family):
    """One axial contour leaves the pose nearly free: the prior on the deviation from the
    model's placement keeps the fit closer to the truth than an unconstrained similarity."""
    shapes, faces, _ = family
    with_prior, without = [], []
    for case in range(6):
        model = pca_model(np.delete(shapes, case, axis=0), faces)
        rng = np.random.default_rng(200 + case)
        truth = _apply(_similarity(rng, np.deg2rad(2.0), 1.0, 0.5), shapes[case])
        user = simulate_user(truth, faces, 1, orientations="axial", rng=rng)
        for sd, out in (((3.0, 1.0, 0.03), with_prior), (None, without)):
            fit = fit_points(model, user.points, user.normals, pose_sd=sd)
            out.append(_mean_surface_distance(fit.vertices, truth, faces))
    assert np.mean(with_prior) < 0.8 * np.mean(without), (with_prior, without)


def test_adaptive_anisotropy_follows_the_noise_and_the_coverage(family):
    """eta is the fitted tangential / normal variance ratio: about 1 for isotropic noise,
    the cap when the points only slide in the tangent plane; the coverage floor keeps it
    higher for two contours than for twelve; fixed when adaptive_anisotropy is off."""
    shapes, faces, model = family
    truth = shapes[0]
    normals = vertex_normals(truth, faces)
    rng = np.random.default_rng(3)
    noise = rng.normal(scale=0.3, size=truth.shape)
    tangential = noise - (noise * normals).sum(axis=1, keepdims=True) * normals
    iso = fit_points(model, truth + noise, pose="none", anisotropy=10.0)
    assert 1.0 <= iso.anisotropy < 2.0, iso.anisotropy
    slid = fit_points(model, truth + tangential, pose="none", anisotropy=10.0)
    assert slid.anisotropy == pytest.approx(10.0)
    fixed = fit_points(model, truth + noise, pose="none", anisotropy=10.0, adaptive_anisotropy=False)
    assert fixed.anisotropy == 10.0 and fit_points(model, truth + noise, method="gmm-iso").anisotropy == 1.0
    sparse = simulate_user(truth, faces, 2, rng=rng)
    dense = simulate_user(truth, faces, 12, rng=rng)
    eta_sparse = fit_points(model, sparse.points, sparse.normals).anisotropy
    eta_dense = fit_points(model, dense.points, dense.normals).anisotropy
    assert eta_sparse > 1.5 * eta_dense, (eta_sparse, eta_dense)


def _translation(shift) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = shift
    return t


def test_pose_prior_is_centred_on_the_placement(family):
    """Issue 11 defect 1: the anatomy sits 30 mm from the model file's placement and the user
    placed the model there (GUI *Place here*): a one-contour fit with ``placement=`` ends as
    close as with a model whose stored placement is already there (the prior at the
    placement), and closer than the fit whose prior stays at ``model.world_transform``."""
    shapes, faces, _ = family
    errors = {"placement": [], "stored": [], "init only": []}
    for case in range(3):
        model = pca_model(np.delete(shapes, case, axis=0), faces)
        placed = _translation([30.0, 0.0, 0.0])
        rng = np.random.default_rng(300 + case)
        truth = _apply(_similarity(rng, np.deg2rad(2.0), 1.0, 0.5) @ placed, shapes[case])
        user = simulate_user(truth, faces, 1, orientations="axial", rng=rng)
        moved = pca_model(np.delete(shapes, case, axis=0), faces)
        moved.world_transform = placed
        start = FitResult(coef=np.zeros(model.n_factors), pose=placed,
                          vertices=model.world_instance() + placed[:3, 3])
        fits = {"placement": fit_points(model, user.points, user.normals, placement=placed),
                "stored": fit_points(moved, user.points, user.normals),
                "init only": fit_points(model, user.points, user.normals, init=start)}
        for name, fit in fits.items():
            errors[name].append(_mean_surface_distance(fit.vertices, truth, faces))
    at_placement, stored = np.mean(errors["placement"]), np.mean(errors["stored"])
    assert at_placement <= 1.1 * stored, errors
    assert np.mean(errors["init only"]) > 2.0 * at_placement, errors  # the defect it fixes


def test_placement_is_the_pose_of_a_shape_only_fit(family):
    _, _, model = family
    placed = _similarity(np.random.default_rng(8), np.deg2rad(20.0), 1.1, 25.0)
    truth = _apply(placed, model.instance(np.sqrt(model.coef_var) * 0.5))
    fit = fit_points(model, truth[::4], pose="none", placement=placed, min_sigma=0.01)
    assert fit.pose == pytest.approx(placed)
    assert np.linalg.norm(fit.vertices - truth, axis=1).max() < 0.05
    with pytest.raises(ValueError, match="placement"):
        fit_points(model, truth[::4], placement=np.eye(3))


def test_fit_cache_follows_the_model_content(family):
    """Issue 11 defect 2: changing coef_var (or any model array) must change the fit."""
    shapes, faces, _ = family
    model = pca_model(shapes[1:], faces)
    user = simulate_user(shapes[0], faces, 3, rng=np.random.default_rng(9))
    first = fit_points(model, user.points, user.normals)
    model.coef_var = model.coef_var * 1e-6  # a new array: the prior now pins the mean shape
    tight = fit_points(model, user.points, user.normals)
    assert np.abs(tight.coef).max() < 0.05 * np.abs(first.coef).max()
    with pytest.raises(ValueError, match="read-only"):
        model.factors[0, 0, 0] = 1.0  # the model's arrays are immutable: no silent stale cache
    writable = np.array(model.coef_var) * 1e6  # the original variances, in a writable array
    model.coef_var = writable
    again = fit_points(model, user.points, user.normals)
    assert np.allclose(again.coef, first.coef, atol=1e-8)
    writable *= 1e-6  # in place, on a writable array: seen through the content digest
    assert np.abs(fit_points(model, user.points, user.normals).coef).max() < 0.05 * np.abs(first.coef).max()


@pytest.mark.parametrize("method", ["gmm-aniso", "gmm-iso", "icp"])
def test_prior_weight_zero_fits_without_a_singular_matrix(family, method):
    """Issue 11 defect 6: prior_weight=0 ("no prior") with fewer constraints than factors."""
    shapes, faces, model = family
    user = simulate_user(shapes[0], faces, 1, orientations="axial", rng=np.random.default_rng(10))
    fit = fit_points(model, user.points[:6], user.normals[:6], pose="none", prior_weight=0.0,
                     method=method)
    assert np.all(np.isfinite(fit.coef)) and np.all(np.isfinite(fit.vertices))
    # six points leave most factors free: bounded to the documented +-5 SD, not 190 SD
    assert np.all(np.abs(fit.coef) <= 5.0 * np.sqrt(model.coef_var) * (1 + 1e-9))
    assert fit.residual_mm < 0.5
    # dense exact data: without a prior the model instance is recovered exactly
    coef = np.sqrt(model.coef_var) * np.linspace(-2.0, 2.0, model.n_factors)
    truth = model.world_instance(coef)
    dense = fit_points(model, truth, pose="none", prior_weight=0.0, method=method, min_sigma=0.01)
    assert np.linalg.norm(dense.vertices - truth, axis=1).max() < 0.02


def test_fit_cli_placement_centres_the_start_and_the_prior(tmp_path, family):
    """``ssm-studio fit --placement x,y,z`` (or a 4x4 file) is passed to fit_points."""
    import json

    from core.cli import main
    from core.io import save_model, save_points

    shapes, faces, model = family
    save_model(tmp_path / "model.npz", model)
    shift = np.array([30.0, 0.0, 0.0])
    truth = shapes[0] + shift
    user = simulate_user(truth, faces, 1, orientations="axial", rng=np.random.default_rng(11))
    save_points(tmp_path / "pts.csv", user.points, user.normals)
    centre = model.world_instance().mean(axis=0) + shift
    np.savetxt(tmp_path / "placement.txt", _translation(shift))
    common = ["fit", "--model", str(tmp_path / "model.npz"), "--points", str(tmp_path / "pts.csv"),
              "--out", str(tmp_path / "fitted.vtk")]
    for value, name in ((",".join(f"{v:.6f}" for v in centre), "a.json"),
                        (str(tmp_path / "placement.txt"), "b.json")):
        assert main(common + ["--placement", value, "--json", str(tmp_path / name)]) == 0
    direct = fit_points(model, user.points, user.normals, placement=_translation(shift))
    for name in ("a.json", "b.json"):
        pose = np.array(json.loads((tmp_path / name).read_text())["pose"])
        assert np.abs(pose - direct.pose).max() < 1e-4
    assert main(common + ["--placement", str(tmp_path / "missing.txt")]) == 2


@pytest.mark.parametrize("method,adaptive", [("gmm-aniso", False), ("gmm-aniso", True),
                                             ("gmm-iso", True), ("icp", True)])
def test_objective_never_increases_from_the_first_step(family, method, adaptive):
    """Issue 11 defect 3: EM with the Gauss-Newton pose step, fixed or adaptive eta, and ICP:
    every recorded objective value, the first step included, is at most the previous one."""
    shapes, faces, _ = family
    rises = []
    for case in range(3):
        model = pca_model(np.delete(shapes, case, axis=0), faces)
        rng = np.random.default_rng(400 + case)
        truth = _apply(_similarity(rng, np.deg2rad(8.0), 1.05, 2.0), shapes[case])
        user = simulate_user(truth, faces, 2 + case, rng=rng)
        fit = fit_points(model, user.points, user.normals, method=method,
                         adaptive_anisotropy=adaptive, tol=1e-8, max_iter=60)
        e = np.asarray(fit.objective)
        assert len(e) >= 3, fit.stop_reason
        rises.append(float((np.diff(e) / np.abs(e[:-1])).max()))
    assert max(rises) <= 1e-9, rises


def _scaled_family(size_mm: float):
    """The bean family scaled so that the mean shape is ``size_mm`` long, and a PCA model."""
    shapes, faces = synthetic_shapes(13, subdivisions=3, seed=6, size=(3.0, 6.0, 14.0))
    shapes = shapes * (size_mm / 28.0)
    return shapes, faces, pca_model(shapes[1:], faces)


def test_defaults_are_relative_to_the_model_size():
    """Issue 11 defect 7: a 5 mm structure and a 5 cm one, three contours each (point spacing
    and noise in proportion, as a user drawing in voxels of the same relative size): both fits
    end much closer to the truth than the unfitted mean shape, with the same relative error."""
    relative = []
    for size in (5.0, 50.0):
        shapes, faces, model = _scaled_family(size)
        truth = _apply(_translation([0.02 * size, -0.01 * size, 0.0]), shapes[0])
        user = simulate_user(truth, faces, 3, spacing=size / 14.0, noise=size / 100.0,
                             rng=np.random.default_rng(12))
        fit = fit_points(model, user.points, user.normals)
        err = _mean_surface_distance(fit.vertices, truth, faces)
        unfitted = _mean_surface_distance(model.world_instance(), truth, faces)
        assert err < 0.5 * unfitted, (size, err, unfitted)
        relative.append(err / size)
    assert relative[0] == pytest.approx(relative[1], rel=0.05), relative


def test_fit_reports_plausibility_and_coefficient_covariance(family):
    shapes, faces, model = family
    placed = _translation([30.0, 0.0, 0.0])
    truth = _apply(placed, shapes[0])
    sparse = simulate_user(truth, faces, 1, orientations="axial", rng=np.random.default_rng(13))
    dense = simulate_user(truth, faces, 9, rng=np.random.default_rng(13))
    fits = [fit_points(model, u.points, u.normals, placement=placed) for u in (sparse, dense)]
    for fit in fits:
        info = fit.plausibility()
        centre_fit = fit.pose[:3, :3] @ model.mean.mean(axis=0) + fit.pose[:3, 3]
        centre_placed = placed[:3, :3] @ model.mean.mean(axis=0) + placed[:3, 3]
        assert info["placement_shift_mm"] == pytest.approx(np.linalg.norm(centre_fit - centre_placed),
                                                           abs=1e-9)
        z = np.abs(fit.coef) / np.sqrt(model.coef_var)
        assert info["max_abs_coef_sd"] == pytest.approx(z.max())
        assert info["n_coef_beyond_3sd"] == int((z > 3).sum())
        assert info["residual_relative"] == pytest.approx(fit.residual_mm / fit.model_size_mm)
        cov = fit.coef_covariance
        assert cov.shape == (model.n_factors,) * 2 and np.allclose(cov, cov.T)
        assert np.linalg.eigvalsh(cov).min() > 0
        assert np.all(np.diag(cov) <= model.coef_var * (1 + 1e-6))  # the data only narrow it
    assert np.trace(fits[1].coef_covariance) < 0.5 * np.trace(fits[0].coef_covariance)
    assert fits[0].to_dict()["plausibility"]["placement_shift_mm"] >= 0


# -- issue 27: correlated residuals, placement far from the points ----------------------------


def _circle_points(radial: np.ndarray, radius: float = 10.0) -> np.ndarray:
    """Points on the equator of a sphere of ``radius``, moved along the normal by ``radial``."""
    theta = np.linspace(0, 2 * np.pi, len(radial), endpoint=False)
    r = radius + radial
    return np.column_stack([r * np.cos(theta), r * np.sin(theta), np.zeros_like(theta)])


def test_residual_correlation_tells_white_noise_from_a_smooth_misfit():
    """Known residuals on a sphere's equator: white noise has a lag-one correlation within a
    few standard errors (1/sqrt(P)) of 0 and no inflation; a smooth offset along the contour
    (what a shape outside the model's span leaves) has rho near 1, and the information of P
    points shrinks to P (1 - rho) / (1 + rho)."""
    from analytic import sphere

    from core.reconstruction.fit import information_inflation, residual_correlation

    v, f = sphere(10.0, [0, 0, 0], 5)
    rng = np.random.default_rng(0)
    p = 150
    white = residual_correlation(_circle_points(rng.normal(scale=0.1, size=p)), v, f)
    theta = np.linspace(0, 2 * np.pi, p, endpoint=False)
    smooth = residual_correlation(_circle_points(0.3 * np.sin(3 * theta)), v, f)
    assert abs(white[0]) < 3 / np.sqrt(p), white
    assert white[1] == pytest.approx(0.1, rel=0.25)  # the RMS normal residual
    assert smooth[0] > 0.9, smooth
    assert information_inflation(white[0] if white[0] < 1 / np.sqrt(p) else 0.0, p) == (0.0, 1.0)
    rho, inflation = information_inflation(smooth[0], p)
    assert rho == pytest.approx(min(smooth[0] - 1 / np.sqrt(p), 0.8))
    assert inflation == pytest.approx((1 + rho) / (1 - rho))


def test_tempered_fit_is_the_fit_with_the_prior_weight_inflated(family):
    """A held-out shape outside the model's span on two parallel contours: residuals along
    the contours are correlated, and the fit is the one with the priors' weight multiplied
    by (1 + rho) / (1 - rho) (the tempered likelihood), run from the same start."""
    shapes, faces, model = family
    truth = shapes[0] + 0.0
    n = vertex_normals(truth, faces)
    centre = truth[np.argmax(truth[:, 2])] * 0.5
    truth = truth + (1.2 * np.exp(-((truth - centre) ** 2).sum(1) / (2 * 3.0 ** 2)))[:, None] * n
    user = simulate_user(truth, faces, 2, orientations="axial", spacing=1.0, noise=0.05,
                         rng=np.random.default_rng(4))
    fit = fit_points(model, user.points, user.normals, pose="none")
    assert fit.prior_inflation > 1.2, (fit.residual_correlation, fit.prior_inflation)
    plain = fit_points(model, user.points, user.normals, pose="none", correlated_residuals=False,
                       prior_weight=PRIOR_WEIGHT * fit.prior_inflation)
    assert np.abs(fit.vertices - plain.vertices).max() < 1e-6
    assert plain.prior_inflation == 1.0 and plain.residual_correlation == 0.0


def test_points_far_from_the_placement_warn_and_placement_at_the_points_fixes_it(family):
    """The held-out shape 12 mm from the model's stored placement: the fit warns with the
    distance and the remedy; placed at the points' centre it needs no warning and lands
    within 1 mm of the truth (the stored placement leaves it several mm off)."""
    shapes, faces, model = family
    truth = shapes[0] + np.array([8.0, -6.0, 6.0])
    user = simulate_user(truth, faces, 3, orientations="mixed", rng=np.random.default_rng(2))
    stored = fit_points(model, user.points, user.normals)
    assert stored.warnings and "--placement" in stored.warnings[0], stored.warnings
    placed = fit_points(model, user.points, user.normals, placement="points")
    assert placed.warnings == []
    err_stored = np.linalg.norm(stored.vertices - truth, axis=1).mean()
    err_placed = np.linalg.norm(placed.vertices - truth, axis=1).mean()
    assert err_placed < 1.0 < err_stored, (err_placed, err_stored)
    assert "warnings" in stored.to_dict()
    # a correctly placed shape of the population does not warn
    assert fit_points(model, simulate_user(shapes[0], faces, 3, rng=np.random.default_rng(2)).points
                      ).warnings == []
    with pytest.raises(ValueError, match="placement"):
        fit_points(model, user.points, placement="centre")


def test_icp_is_robust_on_two_parallel_contours(resources_dir):
    """Demo caudates, leave-one-out PCA-10 of the other shapes, two parallel axial contours
    (2 mm spacing, 0.2 mm noise), similarity pose: point-to-plane ICP ends within 0.6 mm of
    the truth on average (point-to-point ICP: 1.52 mm, every case over 0.9 mm; gmm-aniso
    0.34 mm), because the nearest vertices no longer drag the shape along the surface."""
    data = np.load(resources_dir / "demo" / "ground_truth.npz")
    shapes, faces = data["corresponded_shapes"], data["base_faces"]
    model = pca_model(shapes[6:], faces, n_factors=10)
    errors = []
    for case in range(6):
        user = simulate_user(shapes[case], faces, 2, orientations="axial", spacing=2.0,
                             noise=0.2, rng=np.random.default_rng(case))
        fit = fit_points(model, user.points, user.normals, method="icp")
        errors.append(float(np.linalg.norm(fit.vertices - shapes[case], axis=1).mean()))
    assert np.mean(errors) < 0.6, errors
    assert max(errors) < 1.0, errors


def _thin_tubes(n_shapes: int = 26):
    """Thin curved tubes (``core.datasets.families``' ``thin`` maths on one lattice: known
    correspondences) and a PCA-10 model of all but the first 6."""
    from core.datasets.families import _thin, sphere_lattice

    m, faces = sphere_lattice(1200)
    rng = np.random.default_rng(3)
    shapes = np.stack([_thin(m, faces, rng)[0] for _ in range(n_shapes)])
    return shapes, faces, pca_model(shapes[6:], faces, n_factors=10)


def _two_parallel_contours_of_a_turned_tube(shape, faces, case: int, angle: float):
    """The shape rotated by ``angle`` degrees about its centre and shifted ~5 mm; two parallel
    axial contours at +-1/4 of its height (2 mm spacing, 0.2 mm noise)."""
    from core.geometry.toolkit import random_rotation

    r = np.random.default_rng(50 + case)
    centre = shape.mean(axis=0)
    truth = (shape - centre) @ random_rotation(r, angle).T + centre + r.normal(size=3) * 5
    lo, hi = truth.min(axis=0), truth.max(axis=0)
    z = np.eye(3)[2]
    planes = [(0.5 * (lo + hi) + s * 0.25 * (hi[2] - lo[2]) * z, z) for s in (-1.0, 1.0)]
    return truth, simulate_user(truth, faces, 0, spacing=2.0, noise=0.2, planes=planes,
                                rng=np.random.default_rng(case))


def test_icp_keeps_its_pose_on_two_parallel_contours_of_a_thin_tube():
    """Issue 27: thin tubes (:func:`_thin_tubes`), a held-out tube shifted (and rotated 20
    degrees), two parallel axial contours, placed at the points (*Place here*). Without a
    pose prior point-to-plane ICP slid and scaled away (unrotated: mean surface distance 0.20
    mm, one case 0.81 mm at scale 1.22; rotated: scale up to 1.38); with gmm-aniso's pose
    prior it stays within 0.05 / 0.15 of scale 1 (rotated: at most 1.099 with the shape
    prior's weight 1, 1.108 with today's 1.4; the errors are the same)."""
    from core.geometry.toolkit import symmetric_surface_distance

    shapes, faces, model = _thin_tubes()
    for angle, bound in ((0.0, 0.05), (20.0, 0.15)):
        errors, scales = [], []
        for case in range(6):
            truth, user = _two_parallel_contours_of_a_turned_tube(shapes[case], faces, case, angle)
            fit = fit_points(model, user.points, user.normals, method="icp", placement="points")
            errors.append(symmetric_surface_distance(fit.vertices, faces, truth, faces))
            scales.append(fit.scale)
        assert np.abs(np.array(scales) - 1.0).max() < bound, (angle, scales)
        if angle == 0.0:
            assert np.mean(errors) < 0.16 and max(errors) < 0.5, errors


def test_correlated_residuals_do_not_tighten_the_pose_prior():
    """Issue 27: a pose that is off also leaves smoothly varying (correlated) residuals. The
    correlated-residual refit used to multiply the pose prior's precision by the inflation
    too, and so held the fit at the wrong pose: thin tubes turned 30 degrees and shifted,
    two parallel contours, left at the stored placement, mean surface distance 1.60 mm (the
    two tempered cases 3.45 and 2.30 mm; on one tube 1.36 mm tempered against 0.85 mm
    without the refit). Tempering only the shape prior, a tempered fit is no worse than the
    same fit without the refit (measured, turned 30 and 40 degrees: 2.56 / 1.47 / 1.08 mm
    against 2.76 / 1.78 / 1.06), and the mean stays near 1.1 mm."""
    from core.geometry.toolkit import symmetric_surface_distance

    shapes, faces, model = _thin_tubes()
    errors, tempered = [], []
    for case in range(6):
        for angle in (30.0, 40.0):
            truth, user = _two_parallel_contours_of_a_turned_tube(shapes[case], faces, case, angle)
            # the tempering alone (the mirror restart, tested apart, changes which cases it
            # tempers)
            fit = fit_points(model, user.points, user.normals, mirror_restart=False)
            errors.append(symmetric_surface_distance(fit.vertices, faces, truth, faces))
            if fit.prior_inflation > 1.2:
                plain = fit_points(model, user.points, user.normals, correlated_residuals=False,
                                   mirror_restart=False)
                tempered.append((errors[-1], symmetric_surface_distance(plain.vertices, faces,
                                                                        truth, faces)))
    assert len(tempered) >= 2, "the refit was not exercised"
    assert np.mean(errors) < 1.3, errors
    assert all(with_refit <= 1.05 * without for with_refit, without in tempered), tempered


def test_overrelaxed_em_reaches_a_lower_objective_in_fewer_iterations():
    """Issue 27: on two parallel contours plain EM crawls along the pose/shape directions the
    points hardly determine and stopped on its tolerance short of its optimum (tubes turned
    20 degrees, placed at the points: 237 iterations over 6 cases). The adaptive
    over-relaxation (Salakhutdinov & Roweis 2003) ends at an objective at least as low in
    every case with the shape prior's weight 1, in about half the iterations (131), and keeps
    the record non-increasing. With today's weight 1.4 one case of the 6 ends in another
    basin 0.1 % higher (391.74 against 391.34; 147 against 282 iterations in all)."""
    shapes, faces, model = _thin_tubes()
    iterations = {True: 0, False: 0}
    lower = 0
    for case in range(6):
        _, user = _two_parallel_contours_of_a_turned_tube(shapes[case], faces, case, 20.0)
        fits = {relax: fit_points(model, user.points, user.normals, placement="points",
                                  correlated_residuals=False, overrelax=relax)
                for relax in (True, False)}
        for relax, fit in fits.items():
            iterations[relax] += fit.n_iter
        record = np.asarray(fits[True].objective)
        assert np.all(np.diff(record) <= 1e-9 * abs(record[0])), case
        assert record[-1] <= fits[False].objective[-1] + 2e-3 * abs(record[-1]), case
        lower += record[-1] <= fits[False].objective[-1] + 1e-6 * abs(record[-1])
    assert lower >= 5, lower
    assert iterations[True] < 0.75 * iterations[False], iterations


def test_slice_stack_finds_one_plane_or_parallel_slices_of_one_view():
    from core.reconstruction.mirror import mirror_shift, slice_stack

    rng = np.random.default_rng(0)
    circle = np.c_[np.cos(np.linspace(0, 6, 40)), np.sin(np.linspace(0, 6, 40)), np.zeros(40)] * 5
    turned = circle @ rodrigues(np.array([0.3, -0.2, 0.1])).T + [1.0, 2.0, 3.0]
    one = slice_stack(turned)
    assert one is not None and one.n_planes == 1
    assert abs(abs(one.normal @ rodrigues(np.array([0.3, -0.2, 0.1]))[:, 2]) - 1) < 1e-9
    two = slice_stack(np.r_[circle + [0, 0, 2.0], circle + [0, 0, 6.0]])
    assert two is not None and two.n_planes == 2 and two.middle == pytest.approx(4.0)
    assert abs(two.normal[2]) == 1.0
    assert slice_stack(np.r_[circle + [0, 0, 2.0], circle + [0, 0, 6.0]], parallel=False) is None
    crossing = np.r_[circle, circle[:, [2, 0, 1]], circle[:, [1, 2, 0]]]
    assert slice_stack(crossing) is None and slice_stack(rng.normal(size=(50, 3))) is None
    # a surface centred 1.5 mm above the slices' middle plane: its mirror mode is 3 mm below
    surface = rng.normal(size=(200, 3)) + [0, 0, 5.5]
    shift = mirror_shift(surface - surface.mean(axis=0) + [0, 0, 5.5], two)
    np.testing.assert_allclose(shift, [0, 0, -3.0], atol=1e-9)


def test_two_parallel_contours_restart_from_the_mirror_mode():
    """Issue 27: two parallel contours cannot tell on which side of their middle plane the
    shape's centre lies, and the fit from the points' centre sometimes settles on the wrong
    side. The restart from the mirror mode keeps the lower of the two objectives (never a
    higher one than the plain fit); on these turned beans it recovers one case (0.85 -> 0.74
    mm mean vertex error; 0.64 -> 0.47 with the shape prior's weight 1) and moves no other by
    more than 0.01 mm. It is not tried for one contour, three
    orthogonal ones, ICP, or a warm start from a fit that looked at the same slices."""
    shapes, faces = synthetic_shapes(26, subdivisions=3, seed=11, size=(3.0, 6.0, 14.0))
    model = pca_model(shapes[6:], faces, n_factors=10)
    from core.geometry.toolkit import random_rotation

    rng = np.random.default_rng(27)
    errors, kept = {True: [], False: []}, []
    for h, shape in enumerate(shapes[:6]):
        centre = shape.mean(axis=0)
        truth = (shape - centre) @ random_rotation(rng, 25.0).T + centre + rng.normal(scale=10.0, size=3)
        user = simulate_user(truth, faces, 2, orientations="axial", spacing=2.0, noise=0.2,
                             rng=np.random.default_rng(100 * h + 2))
        fits = {restart: fit_points(model, user.points, user.normals, placement="points",
                                    mirror_restart=restart, correlated_residuals=False)
                for restart in (True, False)}
        assert fits[True].objective[-1] <= fits[False].objective[-1] + 1e-9, h
        assert fits[False].mirror_restart == "" and fits[True].mirror_restart in ("fit", "mirror")
        # the other start's objective minus the kept one's; not measured without the restart
        assert fits[True].mirror_gap >= 0.0 and np.isnan(fits[False].mirror_gap)
        kept.append(fits[True].mirror_restart)
        for restart, fit in fits.items():
            errors[restart].append(float(np.linalg.norm(fit.vertices - truth, axis=1).mean()))
        if h == 0:
            # a warm start from a fit of the same slices stays on its side; one from a fit
            # that did not look at the mirror (the GUI's live refit of a new slice) looks
            warm = fit_points(model, user.points, user.normals, init=fits[True])
            fresh = fit_points(model, user.points, user.normals, init=fits[False])
            icp = fit_points(model, user.points, user.normals, placement="points", method="icp")
            assert warm.mirror_restart == "" and icp.mirror_restart == ""
            assert fresh.mirror_restart in ("fit", "mirror")
            # drawn on: from a fit of a third of the points, it looks again
            third = fit_points(model, user.points[::3], user.normals[::3], placement="points")
            more = fit_points(model, user.points, user.normals, init=third)
            assert third.mirror_restart in ("fit", "mirror") and more.mirror_restart in ("fit", "mirror")
            for k, orientation in ((1, "axial"), (3, "mixed")):
                other = simulate_user(truth, faces, k, orientations=orientation, spacing=2.0,
                                      noise=0.2, rng=np.random.default_rng(h))
                fit = fit_points(model, other.points, other.normals, placement="points")
                assert fit.mirror_restart == "", k
    assert "mirror" in kept, kept
    gains = np.subtract(errors[False], errors[True])
    assert gains.max() > 0.1 and gains.min() > -0.01, errors
