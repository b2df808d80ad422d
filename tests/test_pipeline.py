"""core.build.pipeline and the build-model / evaluate commands: stages, world placement of the model
(its mean must lie on the training shapes), errors, files written."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core.build.pipeline import align, build_model, corresponded_shapes, fit_model, world_placement
from core.cli import main as cli_main
from core.datasets.factors import ellipsoid_surface, planted_shapes
from core.geometry.toolkit import closest_points_on_surface, symmetric_surface_distance
from core.io import TriMesh, load_model, save_mesh

WORLD_CENTRE = np.array([-13.0, 8.0, 12.0])  # e.g. a caudate in MNI space


@pytest.fixture(scope="module")
def posed():
    """Planted shapes, each with its own small pose around a world position (mm)."""
    base, faces = ellipsoid_surface(2, radii=(12.0, 8.0, 6.0))  # 162 vertices
    data = planted_shapes(base, faces, n_shapes=10, n_factors=4, amplitude=1.5, noise=0.02,
                          random_state=3)
    rng = np.random.default_rng(7)
    shapes = []
    for s in data.shapes:
        rot = Rotation.from_rotvec(rng.normal(size=3) * 0.08).as_matrix()
        scale = 1.0 + 0.03 * rng.normal()
        shapes.append(scale * s @ rot.T + WORLD_CENTRE + rng.normal(size=3) * 2.0)
    return np.stack(shapes), faces, data


def test_world_placement_puts_the_mean_on_the_training_shapes(posed):
    shapes, faces, _ = posed
    for method in ("pca", "lsf"):
        res = build_model(shapes, faces=faces, method=method, n_factors=6)
        placed = res.model.world_instance()
        average = shapes.mean(axis=0)
        dist = np.linalg.norm(placed - average, axis=1)
        size = np.linalg.norm(np.ptp(average, axis=0))
        assert dist.mean() < 0.02 * size, (method, dist.mean())
        assert np.linalg.norm(placed.mean(0) - shapes.mean(axis=(0, 1))) < 0.05
        # the aligned frame is not the world: the placement does real work
        assert np.linalg.norm(res.model.mean.mean(0) - WORLD_CENTRE) > 5
        # the transforms map every world shape onto its aligned copy
        k = 3
        t = res.transforms[k]
        np.testing.assert_allclose(shapes[k] @ t[:3, :3].T + t[:3, 3], res.aligned[k], atol=1e-8)
        assert set(res.timings) >= {"alignment", "model", "total"}


def test_stages_are_separately_callable(posed):
    shapes, faces, _ = posed
    aligned = align(shapes, method="gpa", transform="rigid")
    assert aligned.aligned.shape == shapes.shape
    a = fit_model(aligned.aligned, faces, method="varimax", n_factors=3)
    b = fit_model(aligned.aligned, faces, method="pca", n_factors=3)
    assert a.n_factors_ == b.n_factors_ == 3
    none = align(shapes, method="none")
    np.testing.assert_allclose(none.aligned, shapes)
    # with no alignment the model frame is the world: placement ~ identity
    w = world_placement(fit_model(none.aligned, faces, method="pca").mean_, shapes, "rigid")
    np.testing.assert_allclose(w, np.eye(4), atol=1e-8)


def test_corresponded_shapes_errors(posed):
    shapes, faces, _ = posed
    meshes = [TriMesh(s, faces, f"m{i}.vtk") for i, s in enumerate(shapes[:4])]
    names, stacked, f = corresponded_shapes(meshes)
    assert names[0] == "m0.vtk" and stacked.shape == (4, 162, 3)
    odd = TriMesh(shapes[0][:-1], faces[:-4], "odd.vtk")
    with pytest.raises(ValueError, match="odd.vtk has 161 vertices.*--correspond"):
        corresponded_shapes(meshes + [odd])
    flipped = TriMesh(shapes[1], faces[:, ::-1], "flipped.vtk")
    with pytest.raises(ValueError, match="flipped.vtk has different triangles"):
        corresponded_shapes(meshes + [flipped])
    with pytest.raises(ValueError, match="at least 3"):
        corresponded_shapes(meshes[:2])
    with pytest.raises(ValueError, match="alignment must be one of"):
        build_model(meshes, align="icp")


@pytest.fixture(scope="module")
def mesh_dir(tmp_path_factory, posed):
    shapes, faces, _ = posed
    folder = tmp_path_factory.mktemp("meshes")
    for i, s in enumerate(shapes):
        save_mesh(folder / f"shape_{i:02d}.vtk", TriMesh(s, faces))
    return folder


def test_cli_build_model(mesh_dir, tmp_path, posed, capsys):
    shapes, _, _ = posed
    out = tmp_path / "model.npz"
    rc = cli_main(["build-model", str(mesh_dir), "--method", "lsf", "--factors", "8",
                   "--param", "max_iter=80", "--out", str(out)])
    assert rc == 0
    model = load_model(out)
    assert model.method == "lsf" and model.params["max_iter"] == 80
    assert model.source_meshes[0] == "shape_00.vtk" and len(model.source_meshes) == 10
    assert np.linalg.norm(model.world_instance().mean(0) - shapes.mean((0, 1))) < 0.05
    assert "lsf model" in capsys.readouterr().out
    rc = cli_main(["build-model", *sorted(str(p) for p in mesh_dir.iterdir()), "--method", "pca",
                   "--variance", "0.9", "--align", "gpa", "--out", str(tmp_path / "p.npz")])
    assert rc == 0 and load_model(tmp_path / "p.npz").n_factors <= 9


def test_cli_build_model_errors(mesh_dir, tmp_path, posed, capsys):
    shapes, faces, _ = posed
    save_mesh(tmp_path / "other.vtk", TriMesh(*ellipsoid_surface(1)))
    rc = cli_main(["build-model", str(mesh_dir), str(tmp_path / "other.vtk"), "--out",
                   str(tmp_path / "x.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "other.vtk has 42 vertices" in err and "--correspond" in err
    rc = cli_main(["build-model", str(mesh_dir), "--method", "lsf", "--param", "lambda=3",
                   "--out", str(tmp_path / "x.npz")])
    assert rc == 2 and "unknown parameter" in capsys.readouterr().err
    rc = cli_main(["build-model", str(tmp_path / "missing.vtk"), "--out", str(tmp_path / "x.npz")])
    assert rc == 2 and "missing.vtk: file not found" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_cli_evaluate(mesh_dir, tmp_path, capsys):
    rc = cli_main(["evaluate", str(mesh_dir), "--methods", "pca,varimax", "--factors", "4",
                   "--json", str(tmp_path / "m.json"), "--plot", str(tmp_path / "m.png"),
                   "--samples", "50", "--jobs", "1"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "pca" in out and "varimax" in out
    data = json.loads((tmp_path / "m.json").read_text())
    assert data["units"] == "mm"
    assert len(data["methods"]["pca"]["generalisation"]["avg"]) == 10
    assert len(data["methods"]["varimax"]["specificity"]["max"]) == 50
    assert (tmp_path / "m.png").stat().st_size > 10_000
    rc = cli_main(["evaluate", str(mesh_dir), "--methods", "pca,ica"])
    assert rc == 2 and "unknown model method 'ica'" in capsys.readouterr().err


def test_cli_evaluate_true_leave_one_out(mesh_dir, tmp_path, posed, capsys):
    """--loo refit re-aligns every fold (the JSON and the table say so) and gives the values of
    core.evaluation with Realign folds; --noise-var is recorded and used."""
    from core.build.pipeline import align
    from core.evaluation import Realign, evaluate_model

    rc = cli_main(["evaluate", str(mesh_dir), "--methods", "pca", "--factors", "3", "--loo",
                   "refit", "--noise-var", "0.01", "--jobs", "1", "--samples", "20",
                   "--json", str(tmp_path / "t.json")])
    assert rc == 0 and "true leave-one-out (each fold re-aligned)" in capsys.readouterr().out
    res = json.loads((tmp_path / "t.json").read_text())["methods"]["pca"]
    assert res["protocol"] == {"leave_one_out": "realign", "sparse_noise_var": 0.01,
                               "specificity_covariance": "full"}
    shapes, faces, _ = posed
    direct = evaluate_model("pca", align(shapes).aligned, faces, n_factors=3, n_jobs=1,
                            measures=("generalisation",), folds=Realign(shapes, faces))
    np.testing.assert_allclose(res["generalisation"]["avg"], direct["generalisation"]["avg"],
                               rtol=1e-6)


@pytest.mark.slow
def test_build_model_with_correspondence(tmp_path):
    """Raw meshes (each with its own vertex order) -> correspond -> align -> model."""
    base, faces = ellipsoid_surface(2, radii=(12.0, 8.0, 6.0))
    data = planted_shapes(base, faces, n_shapes=5, n_factors=3, amplitude=1.0, noise=0.0,
                          random_state=4)
    rng = np.random.default_rng(0)
    meshes = []
    for i, s in enumerate(data.shapes):
        perm = rng.permutation(len(s))
        inverse = np.argsort(perm)
        meshes.append(TriMesh(s[perm], inverse[faces], f"raw{i}.vtk"))
    with pytest.raises(ValueError, match="different triangles"):
        build_model(meshes)
    res = build_model(meshes, correspond=True, method="pca", n_factors=3, n_jobs=1)
    assert res.model.n_vertices == res.faces.max() + 1
    assert len(res.names) + len(res.failures) == 5
    assert res.correspondence is not None and "correspondence" in res.timings
    # the model keeps what the correspondence safeguard tried and kept, through its file
    from core.io import load_model, save_model

    save_model(tmp_path / "m.npz", res.model)
    kept = load_model(tmp_path / "m.npz").info["correspondence"]
    assert kept["safeguard"] == res.correspondence.safeguard and kept["safeguard"]["enabled"]
    assert {s["stage"] for s in kept["safeguard"]["stages"]} == {"remesh", "refinement"}
    assert kept["reference"] == res.correspondence.reference_name
    # corresponded meshes reproduce the inputs' surfaces: every vertex on its input's surface
    # (the final projection is exact) and the surfaces close (0.02-0.07 mm measured; fairing
    # moves vertices along the surface, off the input's vertices, so the piecewise-linear
    # surfaces of these 162-vertex meshes differ a little)
    for m, raw in zip(res.meshes, meshes):
        _, on_input = closest_points_on_surface(m.vertices, raw.vertices, raw.faces)
        assert on_input.max() < 1e-6
        assert symmetric_surface_distance(m.vertices, m.faces, raw.vertices, raw.faces) < 0.1
