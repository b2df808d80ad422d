"""core.build.stages: the model build cached stage by stage (no Qt).

Shapes share one topology (planted local deformations of an ellipsoid), so the correspondence
stage is the cheap "already corresponded" check and each build takes milliseconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from core.build.stages import (
    DEFAULT_N_REFERENCES,
    NO_CORRESPONDENCE,
    STAGES,
    BuildSettings,
    StageCache,
    StagedBuild,
)
from core.datasets.factors import ellipsoid_surface, planted_shapes
from core.io import TriMesh


@pytest.fixture(scope="module")
def meshes() -> list[TriMesh]:
    base, faces = ellipsoid_surface(2)
    planted = planted_shapes(base, faces, n_shapes=8, n_factors=3, noise=0.05, random_state=0)
    # a random rigid pose per shape, so that the alignment has work to do
    rng = np.random.default_rng(1)
    out = []
    for k, shape in enumerate(planted.shapes):
        q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
        q *= np.sign(np.linalg.det(q))
        out.append(TriMesh(shape @ q.T + rng.normal(0, 20, 3), faces, f"s{k}"))
    return out


def settings(meshes, **changes) -> BuildSettings:
    values = dict(meshes=meshes, reference=NO_CORRESPONDENCE, align_method="gpa",
                  align_transform="rigid", method="pca", params={"n_factors": None})
    values.update(changes)
    return BuildSettings(**values)


def test_plan_reruns_only_the_stages_whose_inputs_changed(meshes):
    build = StagedBuild()
    base = settings(meshes)
    assert build.plan(base) == list(STAGES)
    model = build.run(base)
    assert build.plan(base) == []
    corr = build.cache["correspondence"].result
    aligned = build.cache["alignment"].result

    # model parameters: only the model
    fewer = settings(meshes, params={"n_factors": 3})
    assert build.plan(fewer) == ["model"]
    small = build.run(fewer)
    assert small.n_factors == 3 and model.n_factors == len(meshes) - 1
    assert build.cache["correspondence"].result is corr  # reused, not recomputed
    assert build.cache["alignment"].result is aligned
    # parameters compared by value, in any order
    assert build.plan(settings(meshes, params=dict({"n_factors": 3}))) == []

    # alignment: alignment and model
    assert build.plan(settings(meshes, align_transform="similarity",
                               params={"n_factors": 3})) == ["alignment", "model"]
    # the training set: everything
    assert build.plan(settings(meshes[:-1], params={"n_factors": 3})) == list(STAGES)
    # n_references only matters for the automatic reference
    assert build.plan(settings(meshes, n_references=7, params={"n_factors": 3})) == []
    assert settings(meshes, reference="auto").keys() != \
        settings(meshes, reference="auto", n_references=7).keys()


def test_storing_a_stage_drops_later_stages_built_on_other_inputs(meshes):
    build = StagedBuild()
    base = settings(meshes)
    build.run(base)
    keys = base.keys()
    assert build.cache.status(keys) == dict.fromkeys(STAGES, "done")
    # the same alignment again: the model built on it stays
    build.store("alignment", keys["alignment"], build.cache["alignment"].result)
    assert list(build.cache) == list(STAGES)
    # a different alignment: the model built on the old one goes
    other = settings(meshes, align_transform="similarity")
    result = build.job("alignment", other)(progress=None)
    build.store("alignment", other.keys()["alignment"], result)
    assert list(build.cache) == ["correspondence", "alignment"]
    assert build.cache.status(other.keys()) == {"correspondence": "done", "alignment": "done",
                                                "model": "not run"}
    assert build.cache.status(keys)["alignment"] == "out of date"
    assert build.cache.status(None)["correspondence"] == "out of date"
    # a new correspondence drops both later stages
    build.store("correspondence", ("new",), build.cache["correspondence"].result)
    assert list(build.cache) == ["correspondence"]


def test_jobs_need_their_inputs_and_report_errors(meshes):
    build = StagedBuild()
    with pytest.raises(ValueError, match="correspondence stage is not up to date"):
        build.job("model", settings(meshes))
    with pytest.raises(ValueError, match="at least 3 training meshes"):
        build.plan(settings(meshes[:2]))
    with pytest.raises(ValueError, match="unknown stage 'fit'"):
        build.job("fit", settings(meshes))
    with pytest.raises(ValueError, match="unknown stage"):
        StageCache().store("fit", (), None)
    with pytest.raises(ValueError, match="2 cache tokens for 8 meshes"):
        settings(meshes, tokens=[1, 2]).keys()


def test_built_model_spans_the_aligned_shapes_and_reports_explained_variance(meshes):
    build = StagedBuild()
    model = build.run(settings(meshes))
    aligned = build.cache["alignment"].result.aligned
    # K - 1 PCA factors reproduce every aligned training shape
    coef = np.linalg.lstsq(model.basis, (aligned - model.mean).reshape(len(aligned), -1).T,
                           rcond=None)[0]
    recon = model.mean + (model.basis @ coef).T.reshape(aligned.shape)
    assert np.abs(recon - aligned).max() < 1e-8
    # explained shares: the eigenvalue ratios of the centred shapes' covariance
    centred = (aligned - aligned.mean(axis=0)).reshape(len(aligned), -1)
    singular = np.linalg.svd(centred, compute_uv=False)
    ratio = singular ** 2 / np.sum(singular ** 2)
    stored = np.asarray(model.info["explained_variance_ratio"])
    np.testing.assert_allclose(stored, ratio[:model.n_factors], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(model.explained_variance_share(), stored)
    assert model.info["correspondence"]["reference"] == "(input topology)"
    assert set(model.info["timings"]) == {f"{s}_seconds" for s in STAGES}
    # fewer factors explain less than everything
    small = build.run(settings(meshes, params={"n_factors": 2}))
    share = np.asarray(small.info["explained_variance_ratio"])
    assert share.sum() < 0.999 and np.all(np.diff(share) <= 1e-12)
    np.testing.assert_allclose(share, stored[:2], rtol=1e-6)  # the same leading PCA factors


def test_shape_model_read_outs(meshes):
    model = StagedBuild().run(settings(meshes))
    m = 1
    np.testing.assert_allclose(model.factor_magnitudes()[m], np.sqrt(model.coef_var[m])
                               * np.sqrt(np.sum(model.factors[m] ** 2, axis=1)))
    np.testing.assert_allclose(model.factor_magnitudes(-2.0), 2 * model.factor_magnitudes())
    # without a stored ratio: shares of the model's own variance (sum 1)
    model.info.pop("explained_variance_ratio")
    share = model.explained_variance_share()
    assert abs(share.sum() - 1) < 1e-12 and np.all(share > 0)
    samples = model.sample(4000, random_state=3)
    np.testing.assert_allclose(samples[:5], model.sample(5, random_state=3), atol=1e-12)
    coef = np.linalg.lstsq(model.basis, (samples - model.mean).reshape(len(samples), -1).T,
                           rcond=None)[0]
    # coefficients ~ N(0, coef_var): sample variances within ~10% (4000 draws)
    np.testing.assert_allclose(coef.var(axis=1), model.coef_var, rtol=0.1)
    d = model.distance_to_mean(samples[:3])
    assert d.shape == (3, model.n_vertices)
    np.testing.assert_allclose(d[1], np.sqrt(np.sum((samples[1] - model.mean) ** 2, axis=1)))


def test_default_number_of_references_is_the_engines():
    import inspect

    from core.correspondence import establish_correspondence

    default = inspect.signature(establish_correspondence).parameters["n_references"].default
    assert DEFAULT_N_REFERENCES == default


def test_mirror_check_setting_reaches_the_correspondence_stage():
    """``BuildSettings(mirror_check=False)`` keeps an input the check leaves out (a mirrored
    twisted bean among correctly sided ones), and toggling it re-runs the correspondence."""
    from core.datasets.shapes import known_homology_shapes

    pop = known_homology_shapes("twist", 6, seed=2, n_points=(380, 420))
    meshes = list(pop.meshes)
    m = meshes[4]
    meshes[4] = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], "mirrored")
    checked = BuildSettings(meshes, reference=0, method="pca", params={"n_factors": 3})
    kept = BuildSettings(meshes, reference=0, method="pca", params={"n_factors": 3},
                         mirror_check=False)
    assert checked.keys()["correspondence"] != kept.keys()["correspondence"]
    # without correspondence the setting changes nothing
    assert settings(meshes, mirror_check=False).keys() == settings(meshes).keys()
    build = StagedBuild()
    build.run(kept)
    corr = build.cache["correspondence"].result
    assert corr.failures == {} and all(mesh is not None for mesh in corr.meshes)
    assert build.plan(checked) == list(STAGES)
