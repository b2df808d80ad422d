"""statismo / Scalismo models (.h5): an independent writer, round trips, convert-model, fitting."""

from __future__ import annotations

import os
from pathlib import Path

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
    from core.evaluation.simulated_user import pca_model, synthetic_shapes
    from core.io import load_model, save_model

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
    from core.evaluation.simulated_user import simulate_user, synthetic_shapes
    from core.io import load_model
    from core.reconstruction import fit_points

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
    from core.evaluation.simulated_user import simulate_user, synthetic_shapes
    from core.io import save_points

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


# ---- each writer's own layout ------------------------------------------------------------

REAL = Path(__file__).resolve().parent / "data" / "real" / "statismo"
# ../shared beside the clone (CI); SSM_STUDIO_SHARED_DATA points elsewhere (a worktree)
SHARED = Path(os.environ.get("SSM_STUDIO_SHARED_DATA", Path(__file__).resolve().parents[1].parent
                             / "shared" / "data" / "real")) / "statismo"


def _fixed_string(text: str, *, array: bool) -> np.ndarray:
    """A NUL-terminated fixed-length string (length + 1, as statismo's C++ HDF5Utils and
    Scalismo write them): a scalar (statismo) or a 1-element array (Scalismo)."""
    value = np.array(text.encode(), dtype=f"S{len(text) + 1}")
    return value.reshape(1) if array else value


def write_like(path, style, mean_lps, basis, variance, faces, *, noise=0.0, root="/"):
    """Write a model with the exact dataset dtypes and attribute kinds of one writer:

    - ``statismo``: statismo's C++ library (as RvtkStatismo's mandibles): scalar int32
      versions, scalar fixed strings, uint32 cells, scalar noiseVariance, representer
      version "1.0", empty cellData/pointData groups;
    - ``statismo-array``: the same with versions as 1-element int32 arrays (a published
      statismo model collection);
    - ``scalismo``: Scalismo's StatismoIO: 1-element string-array attributes (including
      representer version/majorVersion), (1,) noiseVariance, int32 cells, (1,) strings;
    - ``faces``: scalismo-faces' MoMoIO: the model in group ``root`` with its own version
      group, gravis::MeshShapeRepresenter, and a root version group.
    """
    scalismo = style in ("scalismo", "faces")
    base = root.rstrip("/")
    versions = (np.array([0], np.int32), np.array([9], np.int32)) if style == "statismo-array" \
        else (np.int32(0), np.int32(9))
    with h5py.File(path, "a") as h5:
        h5.create_dataset(f"{base}/model/mean", data=mean_lps.reshape(-1).astype(np.float32))
        h5.create_dataset(f"{base}/model/pcaBasis", data=basis.astype(np.float32))
        h5.create_dataset(f"{base}/model/pcaVariance", data=variance.astype(np.float32))
        h5.create_dataset(f"{base}/model/noiseVariance",
                          data=np.full((1,) if scalismo else (), noise, np.float32))
        h5.create_dataset(f"{base}/representer/points", data=mean_lps.T.astype(np.float32))
        h5.create_dataset(f"{base}/representer/cells",
                          data=faces.T.astype(np.int32 if scalismo else np.uint32))
        rep = h5[f"{base}/representer"]
        name = {"statismo": "vtkStandardMeshRepresenter", "statismo-array":
                "itkStandardMeshRepresenter", "scalismo": "itkStandardMeshRepresenter",
                "faces": "gravis::MeshShapeRepresenter"}[style]
        rep.attrs["name"] = _fixed_string(name, array=scalismo)
        rep.attrs["datasetType"] = _fixed_string("POLYGON_MESH", array=scalismo)
        if style == "scalismo":
            rep.attrs["version/majorVersion"] = _fixed_string("0", array=True)
            rep.attrs["version/minorVersion"] = _fixed_string("9", array=True)
        else:
            rep.attrs["version"] = _fixed_string("1.0", array=scalismo)
            if not scalismo:
                rep.create_group("cellData")
                rep.create_group("pointData")
        for group in dict.fromkeys((base, "")):
            if f"{group}/version" not in h5:
                h5.create_dataset(f"{group}/version/majorVersion", data=versions[0])
                h5.create_dataset(f"{group}/version/minorVersion", data=versions[1])
        h5.create_dataset(f"{base}/modelinfo/build-time",
                          data=_fixed_string("Wed Jun 03 10:49:56 CEST 2015", array=scalismo))
        h5.create_dataset(f"{base}/modelinfo/modelBuilder-0/builderName",
                          data=_fixed_string("PCAModelBuilder", array=scalismo))
        h5.create_group(f"{base}/modelinfo/modelBuilder-0/parameters")
        if not scalismo:
            h5.create_dataset(f"{base}/modelinfo/scores",
                              data=np.zeros((len(variance), 5), np.float32))


@pytest.mark.parametrize("style", ["statismo", "statismo-array", "scalismo"])
def test_reads_each_writers_exact_layout(tmp_path, style):
    """statismo C++ (scalar or 1-element int32 versions) and Scalismo (string arrays):
    mean, variances and basis exactly as written."""
    from core.io import load_model

    mean, basis, variance, faces = _pca_parts(seed=4)
    write_like(tmp_path / "m.h5", style, mean * FLIP, basis, variance, faces, noise=0.25)
    with h5py.File(tmp_path / "m.h5") as h5:  # the layout is the writer's, not ours
        assert h5["version/majorVersion"].shape == ((1,) if style == "statismo-array" else ())
        assert isinstance(h5["representer"].attrs["name"], np.ndarray if style == "scalismo"
                          else np.bytes_)
    model = load_model(tmp_path / "m.h5")
    assert np.allclose(model.world_instance(), mean, atol=1e-4)
    assert np.allclose(model.coef_var, variance, rtol=1e-5)
    world_factors = np.einsum("mnj,ij->mni", model.factors, model.world_transform[:3, :3])
    assert np.allclose(world_factors, basis.T.reshape(len(variance), -1, 3) * FLIP, atol=1e-5)
    assert model.info["noise_variance"] == pytest.approx(0.25)
    assert model.info["source_format"] == "statismo 0.9"
    assert model.info["statismo_modelinfo"]["modelBuilder-0"]["builderName"] == "PCAModelBuilder"
    assert model.info["statismo_basis_orthonormality"] < 1e-5


def _gp_parts(seed: int = 7):
    """A model in the convention of Scalismo's GP models (its ASM test model): the basis
    columns are eigenfunctions sampled at the points, normalised over the domain
    (||u_m||^2 ~ N) and not orthogonal in R^3N; samples are mean + U diag(sqrt(lambda)) a."""
    mean, u, variance, faces = _pca_parts(seed=seed)
    rng = np.random.default_rng(seed)
    m = u.shape[1]
    mix = np.eye(m) + 0.08 * rng.standard_normal((m, m))  # columns no longer orthogonal
    basis = u @ mix * np.sqrt(len(mean))
    return mean, basis, variance, faces


def test_non_orthonormal_basis_is_read_as_scalismo_reads_it(tmp_path, capsys):
    """Scalismo's DiscreteLowRankGaussianProcess and statismo's DrawSample use the stored
    basis as it is: the model read must give the same mean and covariance U diag(lambda) U^T;
    converted both ways (h5 -> npz -> h5, read as a foreign file) it keeps that Gaussian."""
    from core.cli import main
    from core.io import load_model
    from core.models.shape_model import covariance_gap

    mean, basis, variance, faces = _gp_parts()
    write_like(tmp_path / "gp.h5", "scalismo", mean * FLIP, basis, variance, faces)
    model = load_model(tmp_path / "gp.h5")
    norms = np.linalg.norm(basis, axis=0)
    assert norms.min() > 5.0  # far from unit columns, as in Scalismo's ASM model
    assert model.info["statismo_basis_orthonormality"] > 1.0
    assert np.allclose(model.world_instance(), mean, atol=1e-4)
    assert np.allclose(model.coef_var, variance, rtol=1e-5)
    world_factors = np.einsum("mnj,ij->mni", model.factors, model.world_transform[:3, :3])
    assert np.allclose(world_factors.reshape(len(variance), -1).T, (basis.reshape(-1, 3, basis.shape[1])
                       * FLIP[None, :, None]).reshape(basis.shape), rtol=1e-5, atol=1e-4)
    b = basis.reshape(-1, 3, basis.shape[1]) * FLIP[None, :, None]
    b = b.reshape(basis.shape)
    truth = b * np.sqrt(variance)  # Scalismo's covariance (RAS) is truth @ truth.T
    gram = truth.T @ truth  # the gap from the truth, as core.models.shape_model.covariance_gap
    read = model.world_factor_matrix()
    gap = np.sum(gram ** 2) + np.sum((read.T @ read) ** 2) - 2 * np.sum((truth.T @ read) ** 2)
    assert np.sqrt(max(gap, 0.0) / np.sum(gram ** 2)) < 1e-6
    # a sample with coefficients a: mean + sum a_m factor_m, as Scalismo's instance(c / sd)
    coef = np.sqrt(variance) * np.linspace(-1.5, 1.5, len(variance))
    expect = mean + (b @ coef).reshape(-1, 3)
    assert np.allclose(model.world_instance(coef), expect, atol=1e-3)

    assert main(["convert-model", str(tmp_path / "gp.h5"), str(tmp_path / "gp.npz")]) == 0
    assert main(["convert-model", str(tmp_path / "gp.npz"), str(tmp_path / "back.h5")]) == 0
    with h5py.File(tmp_path / "back.h5", "a") as h5:
        del h5["ssmstudio"]  # as statismo or Scalismo would read it
        u = h5["model/pcaBasis"][()].astype(np.float64)
        assert np.abs(u.T @ u - np.eye(u.shape[1])).max() < 1e-4  # written orthonormal
    back = load_model(tmp_path / "back.h5")
    assert np.allclose(back.world_instance(), mean, atol=1e-4)
    assert covariance_gap(model, back) < 1e-5
    capsys.readouterr()


def test_faces_catalog_is_refused_and_its_shape_model_opens_by_group(tmp_path, capsys):
    """A scalismo-faces catalog: one line naming '#shape'; FILE#shape, FILE#/shape and the
    catalog entry FILE#MorphableModel.shape read the shape model; #color is refused."""
    from core.cli import main
    from core.io import load_model

    mean, basis, variance, faces = _pca_parts(seed=8)
    path = tmp_path / "face.h5"
    write_like(path, "faces", mean * FLIP, basis, variance, faces, root="/shape")
    write_like(path, "faces", mean * 0 + 0.5, basis, variance, faces, root="/color")
    with h5py.File(path, "a") as h5:
        h5["color/representer"].attrs["name"] = _fixed_string("gravis::MeshColorRepresenter",
                                                              array=True)
        h5.create_dataset("color/representer/colorspace", data=_fixed_string("RGB", array=True))
        for entry, where, kind in (("MorphableModel", "/", "CUSTOM_MODEL"),
                                   ("MorphableModel.shape", "//shape", "POLYGON_MESH_MODEL"),
                                   ("MorphableModel.color", "//color", "POLYGON_MESH_DATA_MODEL")):
            h5.create_dataset(f"catalog/{entry}/modelPath", data=_fixed_string(where, array=True))
            h5.create_dataset(f"catalog/{entry}/modelType", data=_fixed_string(kind, array=True))
    rc = main(["convert-model", str(path), str(tmp_path / "o.npz")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and str(path) in err[0] and f"{path}#shape" in err[0]
    for member in ("shape", "/shape", "MorphableModel.shape"):
        model = load_model(f"{path}#{member}")
        assert np.allclose(model.world_instance(), mean, atol=1e-4), member
        assert model.info["statismo_submodel"] == "/shape"
    assert main(["convert-model", f"{path}#shape", str(tmp_path / "shape.npz")]) == 0
    assert np.allclose(load_model(tmp_path / "shape.npz").world_instance(), mean, atol=1e-4)
    rc = main(["convert-model", f"{path}#color", str(tmp_path / "c.npz")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "colour model" in err[0] and "#shape" in err[0]
    assert not (tmp_path / "c.npz").exists()


def _mean_surface_points(model, n_slices: int = 5):
    """Contour points on the model's own mean surface (world RAS), no noise."""
    from core.evaluation.simulated_user import simulate_user

    vertices = model.world_instance()
    extent = float(np.ptp(vertices, axis=0).max())
    user = simulate_user(vertices, model.faces, n_slices, noise=0.0, spacing=extent / 40,
                         rng=np.random.default_rng(0))
    return user, extent


REAL_MODELS = {
    "statismo mandibles (RvtkStatismo)": (SHARED / "RvtkStatismo_mandibles.h5", 7516, 14),
    "Scalismo ASM model (GP basis)": (SHARED / "scalismo_asmData_model.h5", 1400, 50),
    "scalismo-faces l4 #shape": (SHARED / "scalismo-faces_random-l4.h5#shape", 1529, 19),
    "scalismo-faces momo #shape": (REAL / "scalismo-faces_random-momo.h5#shape", 25, 10),
}


@pytest.mark.parametrize("case", sorted(REAL_MODELS))
def test_real_statismo_and_scalismo_files_load_convert_and_fit(tmp_path, capsys, case):
    """Each real surface model: loads, converts h5 -> npz -> h5 -> (as a foreign file) with
    the same mean and covariance, and fits points taken from its own mean surface."""
    import json

    from core.cli import main
    from core.io import load_model, save_points
    from core.io.registry import split_member
    from core.models.shape_model import covariance_gap

    source, n_vertices, n_factors = REAL_MODELS[case]
    if not split_member(source)[0].exists():
        pytest.skip(f"{source} not present")
    model = load_model(source)
    assert (model.n_vertices, model.n_factors) == (n_vertices, n_factors)
    assert main(["convert-model", str(source), str(tmp_path / "m.npz")]) == 0
    assert main(["convert-model", str(tmp_path / "m.npz"), str(tmp_path / "m.h5")]) == 0
    with h5py.File(tmp_path / "m.h5", "a") as h5:
        del h5["ssmstudio"]
    back = load_model(tmp_path / "m.h5")
    assert np.allclose(back.world_instance(), model.world_instance(), atol=1e-3)
    assert covariance_gap(model, back) < 1e-5
    if n_vertices < 100:
        return  # too coarse to slice (25 points): load and conversion only
    user, extent = _mean_surface_points(model)
    save_points(tmp_path / "p.csv", user.points, user.normals)
    rc = main(["fit", "--model", str(source), "--points", str(tmp_path / "p.csv"),
               "--out", str(tmp_path / "fit.vtk"), "--json", str(tmp_path / "fit.json"),
               "--max-iter", "30"])
    assert rc == 0, capsys.readouterr().err
    residual = json.loads((tmp_path / "fit.json").read_text())["residual_mm"]
    assert residual < 0.01 * extent, residual  # the mean surface is in the model
    capsys.readouterr()


# ---- bad model files: one line naming the file and what is wrong -------------------------

def _good(path: Path, **changes) -> Path:
    mean, basis, variance, faces = _pca_parts(seed=9, n_shapes=6)
    write_like(path, "statismo", mean * FLIP, basis, variance, faces)
    return path


def _replace(path: Path, name: str, **create) -> Path:
    with h5py.File(path, "a") as h5:
        del h5[name]
        if create:
            h5.create_dataset(name, **create)
    return path


def _edited(t: Path, edit) -> Path:
    """A good model file changed by ``edit(h5, other)``; ``other`` is a second good file."""
    other = _good(t / "other.h5")
    path = _good(t / "m.h5")
    with h5py.File(path, "a") as h5:
        edit(h5, other)
    return path


def _set_link(name: str, link):
    def edit(h5, other):
        del h5[name]
        h5[name] = link(other) if callable(link) else link
    return edit


def _external_storage(t: Path, target: str) -> Path:
    def edit(h5, other):
        n = h5["model/mean"].shape[0]
        del h5["model/mean"]
        # no data written: HDF5 only records where the bytes would be
        h5.create_dataset("model/mean", shape=(n,), dtype="f4", external=[(target, 0, 4 * n)])
    return _edited(t, edit)


def _virtual(h5, other) -> None:
    n = h5["model/mean"].shape[0]
    del h5["model/mean"]
    layout = h5py.VirtualLayout(shape=(n,), dtype="f4")
    layout[:] = h5py.VirtualSource(str(other), "model/mean", shape=(n,))
    h5.create_virtual_dataset("model/mean", layout)


def _soft_to_external(h5, other) -> None:
    h5["elsewhere"] = h5py.ExternalLink(str(other), "/model")
    _set_link("model/mean", h5py.SoftLink("/elsewhere/mean"))(h5, other)


def _soft_loop(h5, other) -> None:
    _set_link("model/mean", h5py.SoftLink("/model/loop"))(h5, other)
    h5["model/loop"] = h5py.SoftLink("/model/mean")


def _huge(t: Path, **options) -> Path:
    path = _good(t / "m.h5")
    with h5py.File(path, "a") as h5:
        rows = h5["model/pcaBasis"].shape[0]
        del h5["model/pcaBasis"], h5["model/pcaVariance"]
        cols = (10 << 30) // (4 * rows)  # 10 GB declared, nothing stored
        h5.create_dataset("model/pcaBasis", shape=(rows, cols), dtype="f4", **options)
        h5.create_dataset("model/pcaVariance", data=np.ones(cols, np.float32)[:1])
    return path


def _huge_sparse(t: Path) -> Path:
    """10 GB allocated early and never written: st_size 10 GB, a few kB on disk."""
    from h5py import h5d, h5p, h5s, h5t

    path = _good(t / "m.h5")
    with h5py.File(path, "a") as h5:
        rows = h5["model/pcaBasis"].shape[0]
        del h5["model/pcaBasis"]
        dcpl = h5p.create(h5p.DATASET_CREATE)
        dcpl.set_alloc_time(h5d.ALLOC_TIME_EARLY)
        dcpl.set_fill_time(h5d.FILL_TIME_NEVER)
        h5d.create(h5["model"].id, b"pcaBasis", h5t.NATIVE_FLOAT,
                   h5s.create_simple((rows, (10 << 30) // (4 * rows))), dcpl=dcpl)
    if path.stat().st_size < 10 << 30 or path.stat().st_blocks * 512 > 100 << 20:
        pytest.skip("this filesystem does not keep sparse files")
    return path


def _truncated(t: Path) -> Path:
    good = _good(t / "good.h5")
    data = good.read_bytes()
    (t / "m.h5").write_bytes(data[: len(data) * 2 // 3])
    return t / "m.h5"


def _version(value) -> callable:
    return lambda t: _replace(_good(t / "m.h5"), "version/minorVersion", data=value)


def _nan_mean(t: Path) -> Path:
    path = _good(t / "m.h5")
    with h5py.File(path, "a") as h5:
        mean = h5["model/mean"][()]
        mean[7] = np.nan
        h5["model/mean"][...] = mean
    return path


def _reshaped(name: str, fn) -> callable:
    def make(t: Path) -> Path:
        path = _good(t / "m.h5")
        with h5py.File(path, "a") as h5:
            value = fn(h5[name][()])
        return _replace(path, name, data=value)
    return make


BAD_MODELS = {
    "external storage -> /etc/passwd": (lambda t: _external_storage(t, "/etc/passwd"),
                                        "model/mean", "another file"),
    "external storage -> a local file": (
        lambda t: (t / "x.txt").write_text("a" * 4096) and _external_storage(t, str(t / "x.txt")),
        "model/mean", "another file"),
    "external link to an HDF5 file": (
        lambda t: _edited(t, _set_link("model/mean", lambda o: h5py.ExternalLink(str(o),
                                                                                 "/model/mean"))),
        "model/mean", "external link"),
    "external link to a non-HDF5 file": (
        lambda t: (t / "x.txt").write_text("not hdf5\n" * 50) and _edited(
            t, _set_link("model/mean", h5py.ExternalLink(str(t / "x.txt"), "/data"))),
        "model/mean", "external link"),
    "external link to /etc/passwd": (
        lambda t: _edited(t, _set_link("model/mean", h5py.ExternalLink("/etc/passwd", "/x"))),
        "model/mean", "external link"),
    "virtual dataset": (lambda t: _edited(t, _virtual), "model/mean", "virtual dataset"),
    "soft link through an external link": (lambda t: _edited(t, _soft_to_external),
                                           "elsewhere", "external link"),
    "soft link loop": (lambda t: _edited(t, _soft_loop), "model/mean", "loop"),
    "external link in modelinfo": (
        lambda t: _edited(t, lambda h5, o: h5.__setitem__("modelinfo/more", h5py.ExternalLink(
            str(o), "/modelinfo"))), "modelinfo/more", "external link"),
    "10 GB declared, nothing stored": (_huge, "model/pcaBasis", "declares"),
    "10 GB declared, chunked and compressed": (
        lambda t: _huge(t, chunks=(64, 64), compression="gzip"), "model/pcaBasis", "declares"),
    "10 GB declared in a sparse file": (_huge_sparse, "model/pcaBasis", "sparse"),
    "truncated file": (_truncated, "HDF5", "truncated or corrupt"),
    "version a float": (_version(np.float32(9.5)), "version", "not an integer"),
    "version a word": (_version(np.bytes_(b"nine")), "version", "not an integer"),
    "version two numbers": (_version(np.array([0, 9], np.int32)), "version", "not an integer"),
    "NaN in mean": (_nan_mean, "model/mean", "NaN"),
    "mean of the wrong length": (_reshaped("model/mean", lambda v: v[:-3]), "model/mean",
                                 "3N"),
    "points transposed": (_reshaped("representer/points", lambda v: v.T),
                          "representer/points", "(3, N)"),
    "basis of the wrong height": (_reshaped("model/pcaBasis", lambda v: v[:-1]),
                                  "model/pcaBasis", "(3N, M)"),
    "cells 4 x F (tetrahedra)": (_reshaped("representer/cells", lambda v: np.vstack([v, v[:1]])),
                                 "representer/cells", "tetrahedr"),
    "mean holds text": (lambda t: _replace(_good(t / "m.h5"), "model/mean",
                                           data=np.bytes_(b"1 2 3")), "model/mean", "numbers"),
}


@pytest.mark.parametrize("case", sorted(BAD_MODELS))
def test_bad_model_file_is_a_one_line_error_naming_file_and_dataset(tmp_path, capsys, case):
    """convert-model and fit: exit 2, one line naming the file and the dataset, nothing
    written; never a traceback, never data from another file."""
    from core.cli import main

    make, dataset, words = BAD_MODELS[case]
    path = Path(make(tmp_path))
    capsys.readouterr()
    others = [p for p in (tmp_path / "other.h5", tmp_path / "x.txt") if p.exists()]
    for other in others:  # read times set far back: a read would move them (relatime)
        os.utime(other, (0, other.stat().st_mtime))
    (tmp_path / "p.csv").write_text("x,y,z\n0,0,0\n1,0,0\n0,1,0\n")
    for argv in (["convert-model", str(path), str(tmp_path / "out.npz")],
                 ["fit", "--model", str(path), "--points", str(tmp_path / "p.csv"),
                  "--out", str(tmp_path / "out.vtk")]):
        rc = main(argv)
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert rc == 2 and len(lines) == 1, err
        assert str(path) in lines[0] and "Traceback" not in err
        assert dataset.lower() in lines[0].lower() and words.lower() in lines[0].lower(), lines[0]
    assert not (tmp_path / "out.npz").exists() and not (tmp_path / "out.vtk").exists()
    if others and _reads_update_atime(tmp_path):
        for other in others:  # never opened on the model's behalf
            assert other.stat().st_atime == 0, other


def _reads_update_atime(folder: Path) -> bool:
    probe = folder / "atime-probe"
    probe.write_bytes(b"x")
    os.utime(probe, (0, probe.stat().st_mtime))
    probe.read_bytes()
    return probe.stat().st_atime != 0


def test_the_gui_loader_is_the_same_reader(tmp_path):
    """app/ opens models with core.io.load_model (SessionController.open_model): the same
    refusal reaches it, and nothing from /etc/passwd becomes a model."""
    from core.io import DataFileError, load_model

    path = _external_storage(tmp_path, "/etc/passwd")
    with pytest.raises(DataFileError, match="another file"):
        load_model(path)


@pytest.mark.parametrize("name, words", [
    ("scalismo_TetraMeshModel1.h5", "truncated or corrupt"),
    ("scalismo_TetraMeshModel2.h5", "tetrahedral"),
    ("scalismo-faces_random-momo.h5", "#shape"),
])
def test_real_files_that_are_not_one_surface_model_are_one_line_refusals(tmp_path, capsys,
                                                                        name, words):
    from core.cli import main

    path = REAL / name
    rc = main(["convert-model", str(path), str(tmp_path / "o.npz")])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and str(path) in lines[0], err
    assert words in lines[0]


def test_member_syntax_only_splits_a_path_that_is_not_a_file(tmp_path):
    """'a#b.h5' that exists is that file; 'm.npz#x' names no model (an .npz holds one)."""
    from core.io import DataFileError, load_model, save_model
    from core.io.registry import split_member

    mean, basis, variance, faces = _pca_parts(seed=10)
    write_like(tmp_path / "left#1.h5", "statismo", mean * FLIP, basis, variance, faces)
    assert split_member(tmp_path / "left#1.h5") == (tmp_path / "left#1.h5", None)
    assert np.allclose(load_model(tmp_path / "left#1.h5").world_instance(), mean, atol=1e-4)
    assert split_member(f"{tmp_path}/m.h5#/shape") == (tmp_path / "m.h5", "/shape")
    save_model(tmp_path / "m.npz", load_model(tmp_path / "left#1.h5"))
    with pytest.raises(DataFileError, match="holds one model"):
        load_model(f"{tmp_path / 'm.npz'}#shape")
    with pytest.raises(DataFileError, match="file not found"):
        load_model(f"{tmp_path / 'missing.h5'}#shape")
