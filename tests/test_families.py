"""The known-truth families of the correspondence protocol (core.datasets.families)."""

from __future__ import annotations

import numpy as np
import pytest

from core.datasets.families import FAMILIES, REPORT, TUNING, gate_problem, population
from core.datasets.shapes import homology_spread, material_points
from core.geometry import mesh as meshops
from core.geometry.toolkit import SurfaceProjector


@pytest.fixture(scope="module", params=FAMILIES)
def family_population(request):
    return request.param, population(request.param, 2, seed=5)


def test_split_is_fixed_and_disjoint():
    assert set(TUNING).isdisjoint(REPORT) and len(TUNING) == len(REPORT) == 4
    assert TUNING == ("global", "concave", "coarse", "labels_1mm")
    assert REPORT == ("ovoid", "thin", "twolobe", "labels_05mm")


def test_closed_manifold_own_tessellations(family_population):
    family, pop = family_population
    for mesh, material in zip(pop.meshes, pop.material):
        assert meshops.is_closed_manifold(mesh.faces, mesh.n_vertices), mesh.name
        assert meshops.euler_characteristic(mesh.n_vertices, mesh.faces) == 2
        assert meshops.volume(mesh.vertices, mesh.faces) > 0  # outward
        assert material.shape == mesh.vertices.shape
    assert pop.meshes[0].n_vertices != pop.meshes[1].n_vertices  # own tessellations


def test_material_points_lie_on_the_base_surface(family_population):
    """Material points of two shapes are on one base surface: each shape's material mesh
    (its faces over its material points) is close to the other's (the base sampled twice)."""
    family, pop = family_population
    a, b = pop.material
    fb = pop.meshes[1].faces
    d = SurfaceProjector(b, fb)(a)[1]
    edge = meshops.mean_edge_length(b, fb)
    assert np.percentile(d, 99) < 0.25 * edge + 0.05, (family, np.percentile(d, 99), edge)
    # the material's extent is a shape's extent: no collapsed or exploded base
    extent = np.ptp(a, axis=0).max() / np.ptp(pop.meshes[0].vertices @ np.eye(3), axis=0).max()
    assert 0.6 < extent < 1.6


def test_self_correspondence_has_zero_spread(family_population):
    """A shape corresponded to itself under a random vertex permutation: spread ~0; a
    one-ring shift of every vertex is measurably off (the measure sees errors)."""
    family, pop = family_population
    mesh, material = pop.meshes[0], pop.material[0]
    rng = np.random.default_rng(0)
    perm = rng.permutation(mesh.n_vertices)
    from core.types import TriMesh

    permuted = TriMesh(mesh.vertices[perm], np.argsort(perm)[mesh.faces])
    perfect = homology_spread([material_points(mesh.vertices, mesh, material),
                               material_points(permuted.vertices[np.argsort(perm)], permuted,
                                               material[perm])])
    assert perfect.max() < 1e-6
    neighbour = mesh.faces[rng.integers(len(mesh.faces), size=mesh.n_vertices), 0]
    wrong = pop.spread([mesh.vertices, mesh.vertices[neighbour]])
    assert wrong.mean() > 0.05


def test_pose_and_reproducibility():
    pop = population("ovoid", 3, seed=11)
    again = population("ovoid", 3, seed=11)
    other = population("ovoid", 3, seed=12)
    assert np.array_equal(pop.meshes[2].vertices, again.meshes[2].vertices)
    assert not np.array_equal(pop.meshes[0].vertices[:5], other.meshes[0].vertices[:5])
    centres = np.array([m.vertices.mean(axis=0) for m in pop.meshes])
    assert np.linalg.norm(centres, axis=1).max() > 8.0  # shifted 10-40 mm


def test_vertex_order_is_random():
    pop = population("coarse", 1, seed=3)
    mesh, material = pop.meshes[0], pop.material[0]
    # neighbouring indices are not neighbours on the surface
    step = np.linalg.norm(np.diff(mesh.vertices, axis=0), axis=1).mean()
    assert step > 3 * meshops.mean_edge_length(mesh.vertices, mesh.faces)
    assert np.isfinite(material).all()


def test_gate_problems_are_small():
    for family in ("coarse", "twolobe"):
        g = gate_problem(family)
        assert len(g.meshes) == 5
        assert max(m.n_vertices for m in g.meshes) < 1000


def test_bad_family_is_a_one_line_error():
    with pytest.raises(ValueError, match="family must be one of"):
        population("banana", 2, 0)
