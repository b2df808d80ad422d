"""Multi-image registration by transformation synchronisation (core.registration.multi_image,
``ssm-studio register-images``) on images with known transforms."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.cli import main as cli_main
from core.datasets.images import downsample, moved_copy, random_affine
from core.io import load_volume, save_volume
from core.registration.multi_image import knn_pairs, register_images, robust_synchronize

TEMPLATE = "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz"
FAST = {"levels_mm": (10.0, 5.0), "n_samples": 6000}


@pytest.fixture(scope="module")
def cohort(resources_dir, tmp_path_factory):
    """Five 5 mm copies of the MNI T1 under known random affines, noise and bias fields, plus
    brain-mask points (template grey + white matter > 0.5) to measure errors on."""
    t = load_volume(resources_dir / TEMPLATE)
    gm = load_volume(resources_dir / "mni_icbm152_gm_tal_nlin_sym_09a.nii.gz")
    wm = load_volume(resources_dir / "mni_icbm152_wm_tal_nlin_sym_09a.nii.gz")
    brain = (gm.data.astype(float) + wm.data.astype(float)) / 255.0 > 0.5
    ijk = np.argwhere(brain)[::400].astype(float)
    mask = ijk @ t.affine[:3, :3].T + t.affine[:3, 3]
    data, affine = downsample(t.data, t.affine, 5.0)
    folder = tmp_path_factory.mktemp("cohort")
    rng = np.random.default_rng(11)
    paths, truths = [], []
    for k in range(5):
        truth = random_affine(rng, rotation_deg=10, translation_mm=15, scale=0.08,
                              center=np.array([0.0, -18.0, 18.0]))
        m = moved_copy(data, affine, truth, rng, scanner_offset_mm=rng.uniform(-60, 60, 3))
        path = folder / f"subject{k}.nii.gz"
        save_volume(path, m.data, m.affine)
        paths.append(path)
        truths.append(m.truth)
    return paths, np.stack(truths), mask


def _pair_error(transforms, truths, mask) -> float:
    """Mean over ordered pairs of the mean displacement (mm) over the brain between the
    estimated and the true map image j -> image i (gauge-free)."""
    errs = []
    n = len(truths)
    for i in range(n):
        for j in range(n):
            if i != j:
                diff = (np.linalg.inv(transforms[i]) @ transforms[j]
                        - truths[i] @ np.linalg.inv(truths[j]))[:3]
                x = mask @ truths[j][:3, :3].T + truths[j][:3, 3]
                errs.append(np.linalg.norm(x @ diff[:, :3].T + diff[:, 3], axis=1).mean())
    return float(np.mean(errs))


def test_sync_is_consistent_and_beats_reference(cohort, tmp_path):
    paths, truths, mask = cohort
    sync = register_images(paths, "affine", method="sync", n_jobs=1, registration=FAST,
                           out_dir=tmp_path / "sync")
    ref = register_images(paths, "affine", method="reference", n_jobs=1, registration=FAST)
    assert all(sync.ok) and all(ref.ok)
    t = sync.transforms
    # Transitive consistency of the implied pairwise maps, to machine precision.
    implied = np.linalg.inv(t)[:, None] @ t[None, :]  # [i, j]: j -> i
    for i, j, k in [(0, 1, 2), (3, 1, 4), (2, 4, 0)]:
        np.testing.assert_allclose(implied[i, j] @ implied[j, k], implied[i, k], atol=1e-9)
    e_sync = _pair_error(t, truths, mask)
    e_ref = _pair_error(ref.transforms, truths, mask)
    assert e_sync < e_ref, (e_sync, e_ref)
    assert e_sync < 3.0
    # The unbiased template and the resampled images are on one grid.
    template = load_volume(tmp_path / "sync" / "template.nii.gz")
    assert template.shape == tuple(sync.grid_shape)
    one = load_volume(sync.outputs["resampled"][2])
    np.testing.assert_allclose(one.affine, template.affine)
    assert np.corrcoef(one.data.ravel(), template.data.ravel())[0, 1] > 0.8


def test_robust_synchronisation_drops_a_wrong_pair():
    """Exact pairwise transforms plus one grossly wrong one: it is dropped and the rest is exact."""
    rng = np.random.default_rng(1)
    n = 6
    truth = np.stack([random_affine(rng) for _ in range(n)])  # item k -> common
    samples = [rng.normal(0, 30, (200, 3)) for _ in range(n)]
    pairs = [(i, j, np.linalg.inv(truth[i]) @ truth[j]) for i in range(n) for j in range(i + 1, n)]
    bad = 4
    wrong = pairs[bad][2].copy()
    wrong[:3, 3] += [25.0, -10.0, 5.0]
    pairs[bad] = (pairs[bad][0], pairs[bad][1], wrong)
    transforms, used, resid = robust_synchronize(n, pairs, samples, "affine")
    assert not used[bad] and used.sum() == len(pairs) - 1
    implied = np.linalg.inv(transforms[0]) @ transforms[3]
    np.testing.assert_allclose(implied, np.linalg.inv(truth[0]) @ truth[3], atol=1e-6)


def test_knn_pairs_connect_the_graph():
    rng = np.random.default_rng(0)
    d = np.concatenate([rng.normal(0, 1, (10, 6)), rng.normal(50, 1, (10, 6))])  # two clusters
    pairs = knn_pairs(d, 2)
    from core.registration.multi_image import _components

    assert _components(20, set(pairs)).max() == 0
    assert all(i < j for i, j in pairs)
    assert len(pairs) < 20 * 19 / 2 / 3


def test_register_images_cli_reports_an_unreadable_image(cohort, tmp_path, capsys):
    paths, _, _ = cohort
    bad = tmp_path / "broken.nii.gz"
    bad.write_bytes(b"\x1f\x8b garbage")
    out = tmp_path / "out"
    code = cli_main(["register-images", str(paths[0]), str(bad), str(paths[1]), str(paths[2]),
                     "--out", str(out), "--pairs", "knn:1", "--levels", "10,5", "--samples",
                     "6000", "--jobs", "1"])
    assert code == 1
    err = capsys.readouterr().err
    assert "broken.nii.gz" in err
    doc = json.loads((out / "transforms.json").read_text())
    assert [im["ok"] for im in doc["images"]] == [True, False, True, True]
    assert doc["images"][1]["transform"] is None and doc["images"][1]["error"]
    assert len(doc["images"][0]["transform"]) == 4
    assert all(p["fixed"] != str(bad) and p["moving"] != str(bad) for p in doc["pairs"])
    assert (out / "template.nii.gz").exists()
    assert len(list((out / "resampled").glob("*.nii.gz"))) == 3
