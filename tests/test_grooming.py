"""Grooming before correspondence (core.correspondence.grooming) and the batch's per-shape
handling of bad inputs."""

from __future__ import annotations

import numpy as np
import pytest

from core import correspondence as corr
from core.correspondence import grooming
from core.datasets.factors import ellipsoid_surface
from core.datasets.shapes import known_homology_shapes
from core.geometry import mesh as meshops
from core.geometry.toolkit import closest_points_on_surface
from core.types import TriMesh


def _messy():
    """An ellipsoid (642 vertices) with a stray island, a hole, flipped faces and STL-style
    duplicated vertices."""
    v, f = ellipsoid_surface(3)
    island_v, island_f = ellipsoid_surface(1, (1.5, 1.5, 1.5))
    faces = np.vstack([f[1:], island_f + len(v)])  # f[0] removed: a 3-edge hole
    faces[10:60] = faces[10:60, ::-1]
    verts = np.vstack([v, island_v + [40.0, 0, 0]])
    # Unweld: every face gets its own copy of its corners (as STL stores them).
    return TriMesh(verts[faces].reshape(-1, 3), np.arange(3 * len(faces)).reshape(-1, 3), "messy.stl"), (v, f)


def test_grooming_repairs_a_messy_mesh_and_says_what_it_did():
    mesh, (v, f) = _messy()
    out, report = grooming.groom_mesh(mesh, {"vertices": 400})
    assert report.welded_vertices > 0
    assert report.dropped_pieces == 1 and 0 < report.dropped_area_share < 0.05
    assert report.filled_holes == 1
    assert report.flipped_faces == 50
    assert report.remeshed and 360 <= report.output_vertices <= 440
    assert meshops.is_closed(out.faces) and meshops.is_consistently_oriented(out.faces)
    assert meshops.n_components(out.faces, out.n_vertices) == 1
    # Same surface: volume within 3% of the repaired ellipsoid's (the 400-vertex remesh's
    # chords cut the 642-vertex input's curvature), vertices on it.
    assert meshops.volume(out.vertices, out.faces) == pytest.approx(meshops.volume(v, f), rel=0.03)
    _, dist = closest_points_on_surface(out.vertices, v, f)
    assert dist.mean() < 0.02
    # Even density: edge lengths vary little.
    e = meshops.edges(out.faces)
    length = np.linalg.norm(out.vertices[e[:, 0]] - out.vertices[e[:, 1]], axis=1)
    assert length.std() < 0.35 * length.mean()


def test_each_grooming_step_can_be_switched_off():
    mesh, _ = _messy()
    with pytest.raises(grooming.GroomingError, match="not a closed surface"):
        grooming.groom_mesh(mesh, {"fill_holes": False, "remesh": False})
    out, report = grooming.groom_mesh(mesh, {"remesh": False, "fix_orientation": True})
    assert not report.remeshed and out.n_vertices == 642  # the 3-edge hole: one triangle


def test_grooming_refuses_what_it_cannot_fix_with_the_reason():
    v, f = ellipsoid_surface(2)
    two = TriMesh(np.vstack([v, v + 50.0]), np.vstack([f, f + len(v)]), "two.vtk")
    with pytest.raises(grooming.GroomingError, match="largest connected piece has only 50%"):
        grooming.groom_mesh(two)
    flat = TriMesh(v * [1.0, 1.0, 0.0], f, "flat.vtk")
    with pytest.raises(grooming.GroomingError, match="no volume|not a closed surface"):
        grooming.groom_mesh(flat, {"remesh": False})
    # a hole across a third of the surface is no small hole: refused, with its size
    z = v[f].mean(axis=1)[:, 2]
    cut = TriMesh(v, f[z < 0.5 * v[:, 2].max()], "cut.vtk")
    with pytest.raises(grooming.GroomingError,
                       match=r"boundary edges remain in 1 hole\(s\), the largest [0-9.]+ mm around"):
        grooming.groom_mesh(cut, {"remesh": False})


def test_a_stray_triangle_touching_the_surface_at_three_vertices_comes_off():
    """Three non-manifold vertices (a triangle glued on by its corners): split, the triangle
    is a piece of its own and is dropped; the rest is the closed ellipsoid again."""
    v, f = ellipsoid_surface(2)
    stray = TriMesh(v, np.vstack([f, np.array([[0, 1, 100]])]), "nm.vtk")
    out, report = grooming.groom_mesh(stray, {"remesh": False, "fill_holes": False})
    assert report.split_vertices == 3 and report.dropped_pieces == 1
    assert meshops.is_closed_manifold(out.faces, out.n_vertices) and len(out.faces) == len(f)


def test_tiny_coarse_mesh_is_remeshed_and_corresponds():
    """A 14-vertex mesh of a tiny structure next to normal ones: remeshed to the common count,
    it corresponds, and it is not chosen as the reference."""
    pop = known_homology_shapes("bean", 4, seed=3, n_points=(380, 420))
    tiny = known_homology_shapes("bean", 1, seed=4, n_points=(14, 15)).meshes[0]
    tiny.name = "tiny"
    meshes = pop.meshes + [tiny]
    result = corr.establish_correspondence(meshes, "auto", n_jobs=1, vertices=400, refine=0)
    assert not result.failures, result.failures
    assert result.reference_name != "tiny" and "tiny (coarse" in result.reference_reason
    assert result.grooming["tiny"]["remeshed"] and result.grooming["tiny"]["input_vertices"] == 14
    n = len(result.meshes[0].vertices)
    assert 360 <= n <= 440 and all(m.n_vertices == n for m in result.meshes)
    report = result.to_report()
    assert report["reference_reason"] and report["shapes"][4]["grooming"]["input_vertices"] == 14


def test_bad_inputs_are_caught_per_shape_and_the_rest_completes():
    pop = known_homology_shapes("bean", 6, seed=5, n_points=(380, 420))
    good = pop.meshes
    v, f = good[1].vertices.copy(), good[1].faces
    nan = TriMesh(np.where(np.arange(len(v))[:, None] == 7, np.nan, v), f, "nan")
    other = known_homology_shapes("ring", 1, seed=6, n_points=(380, 420)).meshes[0]
    other.name = "ring"
    centre = good[3].vertices[good[3].faces].mean(axis=1)
    keep = centre @ (good[3].vertices[0] - good[3].vertices.mean(axis=0)) < np.quantile(
        centre @ (good[3].vertices[0] - good[3].vertices.mean(axis=0)), 0.85)
    opened = TriMesh(good[3].vertices, good[3].faces[keep], "open")  # a cap cut off
    inputs = good + [nan, other, opened]
    result = corr.establish_correspondence(inputs, "auto", n_jobs=1, vertices=400, refine=0)
    fail = result.failures
    assert set(fail) == {"nan", "ring", "open"}, fail
    assert "NaN" in fail["nan"]
    assert "far from every other training shape" in fail["ring"]
    assert "boundary edges" in fail["open"]
    assert all(m is not None for m in result.meshes[:6])


def test_a_mirrored_side_of_a_chiral_structure_is_caught_and_the_rest_completes():
    # Twisted beans are chiral: a mirrored one (a left/right mix-up) cannot be rotated onto
    # the others. Mirror shape 4 (and flip its faces to keep them outward).
    pop = known_homology_shapes("twist", 6, seed=2, n_points=(380, 420))
    meshes = list(pop.meshes)
    m = meshes[4]
    meshes[4] = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], "mirrored")
    result = corr.establish_correspondence(meshes, 0, n_jobs=1, vertices=400, refine=0)
    assert set(result.failures) == {"mirrored"}, result.failures
    assert result.failures["mirrored"].startswith("mirrored: its mirror image fits the other")
    assert "turn the mirror check off" in result.failures["mirrored"]  # the way out is named
    assert result.meshes[4] is None
    assert all(result.meshes[k] is not None for k in (0, 1, 2, 3, 5))


def test_a_chiral_feature_of_either_sign_is_not_a_mix_up():
    # The tuning family of global modes twists and bends each shape by a random amount of
    # either sign: no common handedness, so a shape of the minority sign is a member. Before
    # the handedness rule two of these six were left out as "mirrored" (ratios below 0.8).
    from core.correspondence import checks
    from core.datasets.families import population

    pop = population("global", 6, 102, size=(400, 500))
    result = corr.establish_correspondence(list(pop.meshes), "auto", n_jobs=1, refine=0,
                                           safeguard=False)
    assert result.failures == {}, result.failures
    found = result.mirror_report  # what the check saw, and why it kept them
    mirrored = [n for n, r in found["suspects"].items() if r < checks.MIRROR_RATIO]
    assert len(mirrored) == 2, found
    assert found["handedness"] < 1.0 / checks.MIRROR_RATIO and found["flagged"] == []
    assert found["note"].startswith("kept: ") and "either sign" in found["note"]
    assert result.to_report()["mirror_report"] == found


def test_two_mirrored_sides_are_both_caught():
    # Two left/right mix-ups of one side: the four correctly sided twisted beans share one
    # hand (handedness above 1 / MIRROR_RATIO), so both mirrored inputs are still flagged.
    pop = known_homology_shapes("twist", 6, seed=3, n_points=(380, 420))
    meshes = list(pop.meshes)
    for k in (1, 4):
        m = meshes[k]
        meshes[k] = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], f"mirrored{k}")
    result = corr.establish_correspondence(meshes, "auto", n_jobs=1, refine=0, safeguard=False)
    assert set(result.failures) == {"mirrored1", "mirrored4"}, result.failures
    assert all(f.startswith("mirrored: ") for f in result.failures.values())
    found = result.mirror_report
    assert sorted(found["flagged"]) == ["mirrored1", "mirrored4"] and found["note"] == ""
    assert found["handedness"] >= 1.25, found  # the four correctly sided beans share a hand


def test_no_mirror_check_keeps_a_mirrored_input(tmp_path):
    """`correspond --no-mirror-check` (a population in which a chiral feature takes either
    sign) keeps the input the check would leave out; without it, the input is reported."""
    import json

    from core.cli import main
    from core.io import save_mesh

    pop = known_homology_shapes("twist", 6, seed=2, n_points=(380, 420))
    paths = []
    for k, m in enumerate(pop.meshes):
        if k == 4:
            m = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], "mirrored")
        paths.append(tmp_path / "in" / f"shape_{k}.vtk")
        paths[-1].parent.mkdir(exist_ok=True)
        save_mesh(paths[-1], m)
    common = [*map(str, paths), "--reference", str(paths[0]), "--refine", "0", "--vertices", "400",
              "--jobs", "1", "--no-safeguard"]
    assert main(["correspond", *common, "--out", str(tmp_path / "checked")]) == 1  # one input left out
    report = json.loads((tmp_path / "checked" / "correspondence.json").read_text())
    assert any("mirrored" in str(v) for v in report["failures"].values()), report["failures"]
    flagged = report["mirror_report"]["flagged"]  # named as in failures (here, the input's path)
    assert len(flagged) == 1 and flagged[0].endswith("shape_4.vtk") and flagged[0] in report["failures"]
    assert main(["correspond", *common, "--out", str(tmp_path / "kept"), "--no-mirror-check"]) == 0
    report = json.loads((tmp_path / "kept" / "correspondence.json").read_text())
    assert not report["failures"] and (tmp_path / "kept" / "shape_4.vtk").exists()


def test_build_model_takes_no_mirror_check(tmp_path, capsys):
    """`build-model --correspond --no-mirror-check` trains on the input the check would leave
    out (6 shapes, not 5); without --correspond the option is a one-line error."""
    from core.cli import main
    from core.io import load_model, save_mesh

    pop = known_homology_shapes("twist", 6, seed=2, n_points=(380, 420))
    paths = []
    for k, m in enumerate(pop.meshes):
        if k == 4:
            m = TriMesh(m.vertices * np.array([-1.0, 1.0, 1.0]), m.faces[:, ::-1], "mirrored")
        paths.append(tmp_path / f"shape_{k}.vtk")
        save_mesh(paths[-1], m)
    common = ["build-model", *map(str, paths), "--correspond", "--reference", "0", "--jobs", "1",
              "--factors", "3"]
    assert main([*common, "--out", str(tmp_path / "checked.npz")]) == 0
    assert "skipped shape_4.vtk: mirrored" in capsys.readouterr().err
    assert main([*common, "--out", str(tmp_path / "kept.npz"), "--no-mirror-check"]) == 0
    captured = capsys.readouterr()
    assert "skipped" not in captured.err and "6 training shapes" in captured.out
    assert load_model(tmp_path / "kept.npz").n_factors == 3
    assert main(["build-model", *map(str, paths), "--no-mirror-check",
                 "--out", str(tmp_path / "x.npz")]) != 0
    err = capsys.readouterr().err
    assert "--no-mirror-check applies to build-model --correspond" in err and "Traceback" not in err


def test_a_poorly_corresponded_shape_of_the_right_structure_is_not_dropped_as_an_outlier():
    # Bent tube 1 of this set corresponds 1.5 mm off the truth and lies 2.3x the median
    # Procrustes distance from the mean: with a 2x threshold it was flagged "far from every
    # other training shape" and left out; a ring or a tube among beans lies at 3.9-4.4x.
    # (the safeguard keeps the remesh and the normal-offsets pass here: that path, without its trials)
    pop = known_homology_shapes("tube", 6, seed=101, n_points=(1100, 1300))
    result = corr.establish_correspondence(pop.meshes, "auto", n_jobs=2, vertices=1200, refine=1,
                                           safeguard=False)
    assert result.failures == {}
    assert all(m is not None for m in result.meshes)


def test_a_clean_tube_that_decimation_folds_is_still_groomed():
    # This clean, closed tube (1,281 vertices) came out of quadric decimation at 1,200 vertices
    # with one edge on three triangles, and was refused ("remeshing did not give one closed
    # surface"); the remesh now decimates again to a target 2-4 % off.
    pop = known_homology_shapes("tube", 6, seed=3, n_points=(1100, 1300), features=6, n_bumps=3,
                                bump_mm=0.5, retessellate=True)
    mesh = pop.meshes[5]
    assert meshops.is_closed(mesh.faces)
    groomed, report = grooming.groom_mesh(mesh, {"vertices": 1200})
    assert report.remeshed
    assert meshops.is_closed(groomed.faces) and meshops.n_components(groomed.faces, groomed.n_vertices) == 1
    assert meshops.euler_characteristic(groomed.n_vertices, groomed.faces) == 2  # a sphere's topology
    assert 1150 <= groomed.n_vertices <= 1250
