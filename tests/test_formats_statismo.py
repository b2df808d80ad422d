"""statismo / Scalismo models (.h5): an independent writer, round trips, convert-model, fitting."""

from __future__ import annotations

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")

FLIP = np.array([-1.0, -1.0, 1.0])


def _pca_parts(seed: int = 0, n_shapes: int = 9):
    """Mean (N, 3), orthonormal basis U (3N, M), variances (M,), faces, from synthetic shapes."""
    from core.evaluation.simulated_user import synthetic_shapes

    shapes, faces = synthetic_shapes(n_shapes, subdivisions=2, seed=seed)
    shapes = shapes + np.array([-23.0, 11.0, 4.0])  # off the origin: a left-hemisphere structure
    mean = shapes.mean(axis=0)
    x = (shapes - mean).reshape(len(shapes), -1)
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    keep = s > 1e-6 * s[0]
    return mean, vt[keep].T, s[keep] ** 2 / (len(shapes) - 1), faces


def write_like_statismo(path, mean_lps, basis, variance, faces, *, noise=0.0, version=(0, 9),
                        noise_shape=(), drop=(), representer="itkStandardMeshRepresenter",
                        dataset_type="POLYGON_MESH", modelinfo=True):
    """Write a model as statismo's C++ library does (documented layout; float32, fixed strings).

    Written here, independently of core.io: the layout of statismo's StatisticalModel::Save
    and itkStandardMeshRepresenter (model/, representer/, version/, modelinfo/).
    """
    n = len(mean_lps)
    with h5py.File(path, "w") as h5:
        stored_basis = basis * np.sqrt(variance) if version == (0, 8) else basis
        datasets = {
            "model/mean": mean_lps.reshape(-1).astype(np.float32),
            "model/pcaBasis": stored_basis.astype(np.float32),
            "model/pcaVariance": variance.astype(np.float32),
            "model/noiseVariance": np.full(noise_shape, noise, dtype=np.float32),
            "representer/points": mean_lps.T.astype(np.float32),
            "representer/cells": faces.T.astype(np.uint32),
            "version/majorVersion": np.int32(version[0]),
            "version/minorVersion": np.int32(version[1]),
        }
        for name, value in datasets.items():
            if name not in drop:
                h5.create_dataset(name, data=value)
        rep = h5.require_group("representer")
        rep.attrs["name"] = np.bytes_(representer.encode())
        rep.attrs["datasetType"] = np.bytes_(dataset_type.encode())
        if modelinfo:
            h5.create_dataset("modelinfo/build-time", data=np.bytes_(b"Mon Jan  5 10:00:00 2015"))
            h5.create_dataset("modelinfo/scores", data=np.zeros((len(variance), 4), np.float32))
            h5.create_dataset("modelinfo/modelBuilder-0/builderName",
                              data=np.bytes_(b"PCAModelBuilder"))
    return n


@pytest.mark.parametrize("version", [(0, 9), (0, 8)])
def test_reads_a_model_written_as_statismo_writes_it(tmp_path, version):
    from core.io import load_model

    mean, basis, variance, faces = _pca_parts()
    write_like_statismo(tmp_path / "m.h5", mean * FLIP, basis, variance, faces, noise=0.5,
                        version=version)
    model = load_model(tmp_path / "m.h5")
    assert model.n_vertices == len(mean) and np.array_equal(model.faces, faces)
    # the file is LPS: the model's world placement is the RAS mean
    assert np.allclose(model.world_instance(), mean, atol=1e-4)
    assert np.allclose(model.coef_var, variance, rtol=1e-5)
    # world displacement of factor m = RAS version of the file's basis column m
    world_factors = np.einsum("mnj,ij->mni", model.factors, model.world_transform[:3, :3])
    expect = (basis.T.reshape(len(variance), -1, 3) * FLIP)
    assert np.allclose(world_factors, expect, atol=1e-5)
    assert model.info["noise_variance"] == pytest.approx(0.5)
    assert model.info["statismo_modelinfo"]["modelBuilder-0"]["builderName"] == "PCAModelBuilder"


def test_h5_round_trip_of_a_non_orthonormal_model(tmp_path):
    """npz -> h5 -> npz: exact model back; a foreign reader sees the same Gaussian (PCA form)."""
    from core.io import load_model, save_model
    from core.models.shape_model import ShapeModel

    mean, basis, variance, faces = _pca_parts(seed=3)
    rng = np.random.default_rng(0)
    mix = np.linalg.qr(rng.standard_normal((len(variance), len(variance))))[0]
    factors = (basis @ mix * 2.0).T.reshape(len(variance), -1, 3)  # rotated, scaled: not PCA
    placement = np.eye(4)
    placement[:3, :3] = 1.1 * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    placement[:3, 3] = (5.0, -7.0, 30.0)
    model = ShapeModel(mean - mean.mean(0), factors, np.linspace(4.0, 0.5, len(variance)),
                       faces, placement, method="lsf", params={"k": 3},
                       info={"noise_variance": 0.2})
    save_model(tmp_path / "m.h5", model)
    back = load_model(tmp_path / "m.h5")
    assert back.method == "lsf" and back.params == {"k": 3}
    for name in ("mean", "factors", "coef_var", "world_transform"):
        assert np.allclose(getattr(back, name), getattr(model, name), atol=1e-12), name
    # what another tool reads: drop our extension group
    with h5py.File(tmp_path / "m.h5", "a") as h5:
        del h5["ssmstudio"]
        u = h5["model/pcaBasis"][()].astype(np.float64)
        assert np.abs(u.T @ u - np.eye(u.shape[1])).max() < 1e-5  # orthonormal columns
    foreign = load_model(tmp_path / "m.h5")
    assert np.allclose(foreign.world_instance(), model.world_instance(), atol=1e-4)

    def world_cov(m):
        lin = m.world_transform[:3, :3]
        b = np.einsum("mnj,ij->mni", m.factors, lin).reshape(m.n_factors, -1).T
        return (b * m.coef_var) @ b.T

    cov, cov_foreign = world_cov(model), world_cov(foreign)
    assert np.abs(cov_foreign - cov).max() < 1e-5 * np.abs(cov).max()
    coef = np.sqrt(foreign.coef_var) * rng.standard_normal(foreign.n_factors)
    assert np.all(np.isfinite(foreign.world_instance(coef)))


def test_convert_model_both_ways_keeps_mean_basis_variances_and_faces(tmp_path, capsys):
    from core.cli import main
    from core.io import load_model, save_model
    from core.evaluation.simulated_user import pca_model, synthetic_shapes

    shapes, faces = synthetic_shapes(8, subdivisions=2, seed=5)
    model = pca_model(shapes, faces)
    save_model(tmp_path / "a.npz", model)
    assert main(["convert-model", str(tmp_path / "a.npz"), str(tmp_path / "b.h5")]) == 0
    with h5py.File(tmp_path / "b.h5", "a") as h5:  # statismo's layout, LPS world
        del_mean = h5["model/mean"][()].reshape(-1, 3) - model.world_instance() * FLIP
        assert np.abs(del_mean).max() < 1e-4
        assert h5["representer/points"].shape == (3, model.n_vertices)
        assert np.array_equal(h5["representer/cells"][()].T, faces)
        assert h5["representer"].attrs["datasetType"] == b"POLYGON_MESH"
        assert int(h5["version/minorVersion"][()]) == 9
        del h5["ssmstudio"]  # convert back as if the file came from elsewhere
    assert main(["convert-model", str(tmp_path / "b.h5"), str(tmp_path / "c.npz")]) == 0
    back = load_model(tmp_path / "c.npz")
    assert np.allclose(back.world_instance(), model.world_instance(), atol=1e-4)
    assert np.allclose(back.coef_var, model.coef_var, rtol=1e-5)
    assert np.array_equal(back.faces, faces)
    a = model.factors.reshape(model.n_factors, -1)
    b = np.einsum("mnj,ij->mni", back.factors, back.world_transform[:3, :3]).reshape(
        back.n_factors, -1)
    assert np.allclose(np.abs(np.sum(a * b, axis=1)), 1.0, atol=1e-5)  # same basis up to sign
    assert "b.h5" in capsys.readouterr().out


def test_noise_variance_floors_the_fit_variance(tmp_path):
    """model/noiseVariance is the GMM variance floor of the fit (a plain info attribute)."""
    from core.io import load_model
    from core.reconstruction import fit_points
    from core.evaluation.simulated_user import simulate_user, synthetic_shapes

    mean, basis, variance, faces = _pca_parts(seed=1)
    shapes, _ = synthetic_shapes(1, subdivisions=2, seed=11)
    target = shapes[0] + np.array([-23.0, 11.0, 4.0])
    user = simulate_user(target, faces, 4, noise=0.05, rng=np.random.default_rng(2))
    results = {}
    for noise in (0.0, 2.25):
        write_like_statismo(tmp_path / f"n{noise}.h5", mean * FLIP, basis, variance, faces,
                            noise=noise, noise_shape=(1,))
        model = load_model(tmp_path / f"n{noise}.h5")
        results[noise] = fit_points(model, user.points, user.normals, max_iter=30)
    assert results[0.0].sigma2 < 1.0
    assert results[2.25].sigma2 >= 2.25 - 1e-9


def test_reads_a_statismo_08_file_with_an_embedded_vtk_reference(tmp_path):
    """Old files (vtkPolyDataRepresenter): the reference mesh is a VTK file stored as bytes."""
    from core.io import TriMesh, load_model, save_mesh

    mean, basis, variance, faces = _pca_parts(seed=2)
    save_mesh(tmp_path / "ref.vtk", TriMesh(mean * FLIP, faces))
    raw = np.frombuffer((tmp_path / "ref.vtk").read_bytes(), dtype=np.uint8)
    write_like_statismo(tmp_path / "old.h5", mean * FLIP, basis, variance, faces, version=(0, 8),
                        representer="vtkPolyDataRepresenter", dataset_type="",
                        drop=("representer/points", "representer/cells", "version/majorVersion",
                              "version/minorVersion"), modelinfo=False)
    with h5py.File(tmp_path / "old.h5", "a") as h5:
        h5.create_dataset("representer/reference", data=raw)
    model = load_model(tmp_path / "old.h5")
    assert np.array_equal(model.faces, faces)
    assert np.allclose(model.world_instance(), mean, atol=1e-4)
    assert np.allclose(model.coef_var, variance, rtol=1e-5)
    gram = model.basis.T @ model.basis  # the U sqrt(lambda) of 0.8 became orthonormal U
    assert np.allclose(gram, np.eye(len(gram)), atol=1e-4)


def test_demo_model_as_foreign_statismo_file_fits_to_the_same_surface(tmp_path):
    """The demo LSF model written as .h5 and read back as another tool would (PCA form, LPS,
    no ssmstudio group): the same Gaussian, so the fit to the demo contours is the same."""
    from pathlib import Path

    from core.io import load_model, load_points, save_model
    from core.reconstruction import fit_points

    demo = Path(__file__).resolve().parents[1] / "resources" / "demo"
    if not (demo / "model.npz").exists() or not (demo / "contour_points.csv").exists():
        pytest.skip("demo model or contour points missing")
    model = load_model(demo / "model.npz")
    save_model(tmp_path / "demo.h5", model)
    with h5py.File(tmp_path / "demo.h5", "a") as h5:
        del h5["ssmstudio"]
    foreign = load_model(tmp_path / "demo.h5")
    assert foreign.method == "statismo" and foreign.n_factors == model.n_factors
    points = load_points(demo / "contour_points.csv")
    ours = fit_points(model, points.points, points.normals)
    theirs = fit_points(foreign, points.points, points.normals)
    # float32 storage in the file: agreement to ~1e-4 mm on a 50 mm structure
    assert np.abs(ours.vertices - theirs.vertices).max() < 1e-3
    assert theirs.residual_mm == pytest.approx(ours.residual_mm, abs=1e-4)


def test_fit_model_space_reads_an_h5_written_in_ras(tmp_path, capsys):
    """A model file in RAS (not statismo's LPS): --model-space ras places it right."""
    import json

    from core.cli import main
    from core.io import save_points
    from core.evaluation.simulated_user import simulate_user, synthetic_shapes

    mean, basis, variance, faces = _pca_parts(seed=6)
    write_like_statismo(tmp_path / "ras.h5", mean, basis, variance, faces)  # RAS, not LPS
    shapes, _ = synthetic_shapes(1, subdivisions=2, seed=12)
    user = simulate_user(shapes[0] + np.array([-23.0, 11.0, 4.0]), faces, 5,
                         rng=np.random.default_rng(3))
    save_points(tmp_path / "p.csv", user.points, user.normals)
    residuals = {}
    for space in ("ras", "lps"):
        rc = main(["fit", "--model", str(tmp_path / "ras.h5"), "--model-space", space,
                   "--points", str(tmp_path / "p.csv"), "--out", str(tmp_path / f"{space}.vtk"),
                   "--json", str(tmp_path / f"{space}.json")])
        if rc == 0:
            residuals[space] = json.loads((tmp_path / f"{space}.json").read_text())["residual_mm"]
        else:
            residuals[space] = float("inf")  # read mirrored: the points lie far from the model
    capsys.readouterr()
    assert residuals["ras"] < 0.5
    assert residuals["lps"] > 2 * residuals["ras"]
