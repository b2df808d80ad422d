"""Shared pieces of the correspondence benchmarks (``bench_correspondence.py`` and its tables).

- the peers, on the same inputs: :func:`ours` (:func:`core.correspondence.correspond_pair`),
  :func:`plain_rustcpd` (rustcpd rigid + nonrigid CPD with the same parameters, then every
  deformed reference vertex projected to its nearest point on the target surface) and
  :func:`plain_pycpd` (the same plain pipeline on pycpd 2.x, pure numpy; benchmark-only);
- the plain batch runners (:func:`plain_batch`, :func:`plain_batch_timed`: one process per
  worker, as ours' batch);
- per-pair quality metrics against the reference's triangulation (:func:`area_distortion`,
  :func:`flipped_fraction`, :func:`degenerate_fraction`);
- data: the demo set's ground truth (:func:`demo_population`), synthetic beans with known
  homologues from :mod:`core.datasets.shapes` (:func:`synthetic_truth`, :func:`true_points`),
  the known-homology populations of the spread tables (:func:`populations`) and the groomed
  meshes SSM Studio's batch gets (:func:`groomed_meshes`);
- :func:`load_averages` (times on a shared machine are upper bounds).

Import it from a script in this folder (``from correspondence_common import plain_rustcpd``).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.io import TriMesh  # noqa: E402

# The two populations of core.datasets.shapes: "bumps", independent random bumps
# on every shape (the generator's defaults); "features", six consistent features a kind whose
# size varies between shapes, smaller independent bumps, and independent even remeshes.
POPULATIONS = {"bumps": {},
               "features": {"features": 6, "n_bumps": 3, "bump_mm": 0.5, "retessellate": True}}

# truth(ref, k, points) -> (P, 3): the true homologues on mesh k of points on mesh ref's surface
Truth = Callable[[int, int, np.ndarray], np.ndarray]


# ----------------------------------------------------------------------------- data

def demo_population(folder: Path) -> tuple[list[TriMesh], Truth]:
    """The demo set (``resources/demo``): meshes and their truth function.

    ``truth(ref, k, points)``: the true homologues on mesh k of ``points`` on mesh ``ref``'s
    surface: the true homologues of ``ref``'s vertices (through the barycentric remeshing
    record of ground_truth.npz), interpolated on ``ref``'s triangles (exact at its vertices).
    """
    from core.geometry.toolkit import surface_coordinates
    from core.io import load_mesh

    gt = np.load(folder / "ground_truth.npz")
    names = [str(n) for n in gt["mesh_names"]]
    meshes = []
    for name in names:
        mesh = load_mesh(folder / "meshes" / name)
        mesh.name = name
        meshes.append(mesh)
    offsets, tris, bary = gt["remesh_offsets"], gt["remesh_triangles"], gt["remesh_barycentric"]
    base_faces, shapes = gt["base_faces"], gt["corresponded_shapes"]

    def truth(ref: int, k: int, points: np.ndarray) -> np.ndarray:
        rows = np.arange(offsets[ref], offsets[ref + 1])
        corners = base_faces[tris[rows]]  # (N_ref, 3)
        at_vertices = np.einsum("nl,nlc->nc", bary[rows], shapes[k][corners])
        tri, weights, _ = surface_coordinates(points, meshes[ref].vertices, meshes[ref].faces)
        return np.einsum("pj,pjc->pc", weights, at_vertices[meshes[ref].faces[tri]])

    return meshes, truth


def true_points(pop, k: int, material: np.ndarray) -> np.ndarray:
    """The points of shape ``k`` of a known-homology population whose material points are
    ``material`` (P, 3): located on shape k's tessellation of the base surface, then
    interpolated on shape k."""
    from core.geometry.toolkit import surface_coordinates

    mesh = pop.meshes[k]
    tri, bary, _ = surface_coordinates(material, pop.material[k], mesh.faces)
    return np.einsum("pj,pjc->pc", bary, mesh.vertices[mesh.faces[tri]])


def synthetic_truth(n_shapes: int, seed: int = 0) -> tuple[list[TriMesh], Truth]:
    """Posed bean shapes of :func:`core.datasets.shapes.known_homology_shapes` (its defaults:
    1,800-2,300 vertices, six random bumps, scaling, poses within 45 degrees and 40 mm) and
    their truth function (as :func:`demo_population`'s)."""
    from core.datasets.shapes import known_homology_shapes, material_points

    pop = known_homology_shapes("bean", n_shapes, seed=seed)

    def truth(ref: int, k: int, points: np.ndarray) -> np.ndarray:
        return true_points(pop, k, material_points(points, pop.meshes[ref], pop.material[ref]))

    return pop.meshes, truth


def populations(n_shapes: int, vertices: int, seed: int, repeats: int = 1,
                population: str = "bumps") -> Iterator[tuple[str, object]]:
    """(kind, known-homology population) for the bean, tube and ring, seeds seed, seed+1,
    seed+2; with ``repeats`` R, R populations a kind (seeds seed + i + 3 r), kind by kind;
    ``population``: a key of :data:`POPULATIONS`."""
    from core.datasets.shapes import known_homology_shapes

    for i, kind in enumerate(("bean", "tube", "ring")):
        for r in range(repeats):
            yield kind, known_homology_shapes(kind, n_shapes, seed=seed + i + 3 * r,
                                              n_points=(vertices - 100, vertices + 100),
                                              **POPULATIONS[population])


def groomed_meshes(meshes: list[TriMesh], vertices: int) -> list[TriMesh]:
    """Every mesh groomed as SSM Studio's batch grooms it with ``vertices=vertices``
    (:func:`core.correspondence.grooming.groom_mesh`, the batch's per-shape grooming job)."""
    from core.correspondence.grooming import groom_mesh

    return [groom_mesh(m, {"vertices": vertices})[0] for m in meshes]


def load_averages() -> str:
    """The 1, 5 and 15 minute load averages (times on a shared machine are upper bounds)."""
    import os

    return ", ".join(f"{x:.2f}" for x in os.getloadavg())


# ----------------------------------------------------------------------------- peers

def normalised(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Points centred and scaled to unit RMS radius, the centre and the scale: the peers get
    the product's own normalisation (:func:`core.correspondence.pair.normalise`)."""
    from core.correspondence.pair import normalise

    return normalise(np.asarray(points, dtype=np.float64))


def plain_rustcpd(reference: TriMesh, target: TriMesh, params: dict) -> np.ndarray:
    """rustcpd alone: rigid + nonrigid CPD on all points, then nearest-point projection."""
    import rustcpd

    from core.geometry.toolkit import SurfaceProjector

    xn, centre, scale = normalised(target.vertices)
    yn, _, _ = normalised(reference.vertices)
    rigid = rustcpd.register_rigid(xn, yn, scale=True, tolerance=params["tolerance"],
                                   max_iterations=params["rigid_iterations"])
    nonrigid = rustcpd.register_deformable(xn, rigid.points, alpha=params["lam"], beta=params["beta"],
                                           low_rank=params["low_rank"], low_rank_method="pivoted_cholesky",
                                           tolerance=params["tolerance"],
                                           max_iterations=params["max_iterations"])
    moved = np.asarray(nonrigid.points) * scale + centre
    return SurfaceProjector(target.vertices, target.faces)(moved)[0]


def plain_pycpd(reference: TriMesh, target: TriMesh, params: dict) -> np.ndarray:
    """pycpd: rigid + nonrigid CPD (pure numpy), then nearest-point projection."""
    from pycpd import DeformableRegistration, RigidRegistration

    from core.geometry.toolkit import SurfaceProjector

    xn, centre, scale = normalised(target.vertices)
    yn, _, _ = normalised(reference.vertices)
    rigid = RigidRegistration(X=xn, Y=yn, tolerance=params["tolerance"],
                              max_iterations=params["rigid_iterations"])
    posed, _ = rigid.register()
    nonrigid = DeformableRegistration(X=xn, Y=posed, alpha=params["lam"], beta=params["beta"],
                                      tolerance=params["tolerance"],
                                      max_iterations=params["max_iterations"])
    moved, _ = nonrigid.register()
    return SurfaceProjector(target.vertices, target.faces)(moved * scale + centre)[0]


def ours(reference: TriMesh, target: TriMesh, params: dict) -> np.ndarray:
    """SSM Studio's pair correspondence (:func:`core.correspondence.correspond_pair`)."""
    from core.correspondence import correspond_pair

    return correspond_pair(reference, target, params)["vertices"]


def _plain_timed(reference: TriMesh, target: TriMesh, params: dict) -> tuple[np.ndarray, float]:
    """:func:`plain_rustcpd` and its seconds in the worker (as ours' per-shape task seconds)."""
    t0 = time.perf_counter()
    out = plain_rustcpd(reference, target, params)
    return out, time.perf_counter() - t0


def plain_batch_timed(reference: TriMesh, meshes: list, params: dict, jobs: int
                      ) -> tuple[list, float, float]:
    """Plain rustcpd CPD-then-project of every mesh onto the reference in ``jobs`` processes:
    the outputs, the wall seconds and the sum of the per-shape task seconds (the ``task s``
    column, measured as ours' ``cpu_total``: inside the workers, so less sensitive to the
    pool's start-up and to other users' load than the wall time)."""
    import multiprocessing as mp

    t0 = time.perf_counter()
    ctx = mp.get_context("forkserver")
    with ctx.Pool(jobs) as pool:
        done = pool.starmap(_plain_timed, [(reference, m, params) for m in meshes])
    return [d[0] for d in done], time.perf_counter() - t0, float(sum(d[1] for d in done))


def plain_batch(reference: TriMesh, meshes: list, params: dict, jobs: int) -> tuple[list, float]:
    """:func:`plain_batch_timed` without the task seconds: the outputs and the wall seconds."""
    out, wall, _ = plain_batch_timed(reference, meshes, params, jobs)
    return out, wall


# ----------------------------------------------------------------------------- quality

def area_distortion(vertices: np.ndarray, reference: np.ndarray, faces: np.ndarray) -> float:
    """Mean |log| ratio of each triangle's share of the total area, output vs reference.

    0 when the output reproduces the reference's vertex distribution on the new shape;
    grows where vertices bunch up or spread out (the irregularities fairing removes).
    """
    def shares(v):
        t = v[faces]
        a = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
        return np.maximum(a, 1e-12) / a.sum()

    return float(np.abs(np.log(shares(vertices) / shares(reference))).mean())


def flipped_fraction(vertices: np.ndarray, faces: np.ndarray, target: TriMesh) -> float:
    """Fraction of output triangles facing inwards (normal against the target's local normal):
    fold-overs, where the output surface doubles back on itself."""
    from scipy.spatial import cKDTree

    from core.geometry.toolkit import face_normals, vertex_normals

    centroids = vertices[faces].mean(axis=1)
    _, nearest = cKDTree(target.vertices).query(centroids)
    target_normals = vertex_normals(target.vertices, target.faces)[nearest]
    return float((np.einsum("ij,ij->i", face_normals(vertices, faces), target_normals) < 0).mean())


def degenerate_fraction(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Fraction of triangles with less than 5 % of the mean triangle area (slivers, collapses)."""
    v = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    return float((area < 0.05 * area.mean()).mean())
