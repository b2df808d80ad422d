"""Shape populations with known homologies, to measure correspondence against the truth.

Each shape is a smooth deformation of one base surface B (a map from a parameter domain to
mm) with planted local bumps (Gaussian bumps along the base normal at random places, random
heights), a random anisotropic scaling and a random pose, and **its own tessellation**
(its own vertex count, rotation or offset of the parameter lattice, and triangulation).
Every vertex knows its parameter, hence its material point: the position B(m) on the base
surface. Two shapes' points are homologous when their material points coincide.

Base surfaces:

- ``"bean"``: a bent, tapered ellipsoid with a one-sided bulge (genus 0, ~36 x 20 x 15 mm),
  parameter on the unit sphere (Fibonacci lattice, convex-hull triangulation);
- ``"tube"``: a long bent tube closed at both ends (genus 0, ~60 x 8 mm);
- ``"ring"``: a torus whose tube thickens on one side (genus 1, ~40 mm across), parameter
  on the flat torus (a sheared, offset grid, each quad split along a random diagonal);
- ``"twist"``: the bean twisted by 100 degrees about its long axis, a clearly chiral shape
  (no mirror symmetry), to tell a mirrored side (a left/right mix-up) from a rotated one.

Two kinds of population:

- **independent bumps** (the default): each shape's bumps are its own, at random places. There
  is no population structure, and under broad bumps the truth is a convention (offsets along
  the base normals) more than something the surfaces show.
- **consistent features** (``features=K``): K local bumps at the same material points in every
  shape of a kind (fixed per kind, whatever the seed), each with a mean height and a
  per-shape factor ``1 + feature_cv * N(0, 1)``, as anatomy has homologous features whose
  size varies between subjects; the independent bumps, smaller, add per-subject variation.
  What population-based correspondence methods are built for.

:func:`unevenly_decimated` gives each shape of a population an uneven tessellation instead
(a random quadric decimation).

``retessellate=True`` replaces each shape's lattice by an independent even remesh of its
surface (material points carried by barycentric interpolation): the lattice's vertex
density follows the material parameter, a cue of the truth that CPD's density matching uses
and a scan's mesh does not have.

:func:`material_points` gives, for points on a shape's surface, their material points by
barycentric interpolation over the shape's triangles; :func:`homology_spread` the mean
distance (mm, on the base surface) of corresponded points from their points' common mean:
zero for perfect correspondences, whatever the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.geometry import mesh as meshops
from core.geometry.toolkit import face_normals, random_rotation, surface_coordinates
from core.types import TriMesh

KINDS = ("bean", "tube", "ring", "twist")


def _base(kind: str, m: np.ndarray) -> np.ndarray:
    """Base surface points (P, 3) mm at parameters ``m`` (sphere: unit vectors; ring: angles)."""
    if kind == "twist":
        p = _base("bean", m)
        angle = np.deg2rad(100.0) * p[:, 0] / 36.0  # about the long (x) axis
        c, s = np.cos(angle), np.sin(angle)
        return np.column_stack([p[:, 0], c * p[:, 1] - s * p[:, 2], s * p[:, 1] + c * p[:, 2]])
    if kind == "bean":
        x = 18.0 * m[:, 0]
        taper = 1.0 - 0.5 * m[:, 0]
        y = 8.0 * m[:, 1] * taper + 0.012 * (x + 18.0) ** 2
        z = 6.0 * m[:, 2] * taper + 5.0 * np.exp(-((x - 9.0) ** 2) / 30.0) * (1.0 + m[:, 2]) / 2.0
        return np.column_stack([x, y, z])
    if kind == "tube":
        s = 30.0 * m[:, 0]  # along the tube
        r = 4.0 * (1.0 + 0.2 * m[:, 0])
        y, z = r * m[:, 1], r * m[:, 2]
        bend = 0.02 * s ** 2  # bent in the x-y plane
        return np.column_stack([s, y + bend, z])
    theta, phi = m[:, 0], m[:, 1]
    tube = 6.0 + 2.5 * np.cos(theta)  # thicker on one side
    rad = 16.0 + tube * np.cos(phi)
    return np.column_stack([rad * np.cos(theta), rad * np.sin(theta), tube * np.sin(phi)])


def _normals(kind: str, m: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """Unit normals of the base surface at ``m`` by central differences (oriented outward)."""
    if kind == "ring":
        d1 = _base(kind, m + [eps, 0]) - _base(kind, m - [eps, 0])
        d2 = _base(kind, m + [0, eps]) - _base(kind, m - [0, eps])
    else:
        helper = np.where(np.abs(m[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        t1 = np.cross(m, helper)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(m, t1)  # (t1, t2, m) right-handed: the normal is outward
        d1 = _base(kind, m + eps * t1) - _base(kind, m - eps * t1)
        d2 = _base(kind, m + eps * t2) - _base(kind, m - eps * t2)
    n = np.cross(d1, d2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return -n if kind == "ring" else n  # (theta, phi) orders the ring's tangents inward


def _tessellation(kind: str, n_points: int, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Parameters (N, D) and faces (F, 3) of one shape's own triangulation."""
    if kind == "ring":
        n_phi = max(int(round(np.sqrt(n_points / 2.2))), 6)
        n_theta = max(n_points // n_phi, 8)
        i, j = np.meshgrid(np.arange(n_theta), np.arange(n_phi), indexing="ij")
        shear, offset = rng.uniform(0, 1), rng.uniform(0, 2 * np.pi, 2)
        theta = offset[0] + 2 * np.pi * (i + shear * j / n_phi) / n_theta
        phi = offset[1] + 2 * np.pi * j / n_phi
        m = np.column_stack([theta.ravel(), phi.ravel()])
        idx = lambda a, b: (a % n_theta) * n_phi + (b % n_phi)  # noqa: E731
        a, b = i.ravel(), j.ravel()
        q = np.stack([idx(a, b), idx(a + 1, b), idx(a + 1, b + 1), idx(a, b + 1)], axis=1)
        diag = rng.random(len(q)) < 0.5
        f1 = np.where(diag[:, None], q[:, [0, 1, 2]], q[:, [0, 1, 3]])
        f2 = np.where(diag[:, None], q[:, [0, 2, 3]], q[:, [1, 2, 3]])
        return m, np.vstack([f1, f2])
    from scipy.spatial import ConvexHull

    k = np.arange(n_points) + 0.5
    z = 1.0 - 2.0 * k / n_points
    ang = np.pi * (1.0 + 5 ** 0.5) * k
    r = np.sqrt(1.0 - z ** 2)
    m = np.column_stack([r * np.cos(ang), r * np.sin(ang), z]) @ random_rotation(rng).T
    return m, ConvexHull(m).simplices


@dataclass
class KnownHomologyShapes:
    """A population: ``meshes`` (posed, own tessellations) and per mesh the base-surface
    positions of its vertices' material points, ``material`` (N_k, 3) mm."""

    kind: str
    meshes: list
    material: list

    def spread(self, corresponded: list) -> np.ndarray:
        """Per corresponded vertex, the mean distance (mm) of its material points from their
        mean over the shapes (:func:`homology_spread`)."""
        return homology_spread([material_points(v, self.meshes[k], self.material[k])
                                for k, v in enumerate(corresponded) if v is not None])


def known_homology_shapes(kind: str = "bean", n_shapes: int = 10, *, seed: int = 0,
                          n_points: tuple[int, int] = (1800, 2300), n_bumps: int = 6,
                          bump_mm: float = 1.5, bump_width_mm: float = 7.0,
                          max_angle_deg: float = 45.0, translation_mm: float = 40.0,
                          features: int = 0, feature_mm: float = 2.0,
                          feature_width_mm: float = 4.0, feature_cv: float = 0.35,
                          retessellate: bool = False) -> KnownHomologyShapes:
    """``n_shapes`` shapes of the base ``kind`` (module docstring), reproducible from ``seed``.

    ``features``: consistent features a kind (0: independent bumps only), mean heights
    +-``feature_mm`` x U(0.7, 1.3), width ``feature_width_mm``, per-shape height factor
    ``1 + feature_cv * N(0, 1)``; ``retessellate``: each shape an independent even remesh.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    rng = np.random.default_rng(seed)
    feature_centres, feature_heights = _features(kind, features, feature_mm)
    meshes, material = [], []
    for s in range(n_shapes):
        n_vertices = int(rng.integers(*n_points))
        # A retessellated shape starts from a finer lattice, so its own remesh is not tied to it.
        m, faces = _tessellation(kind, 3 * n_vertices if retessellate else n_vertices, rng)
        faces = _outward(kind, m, faces)
        base = _base(kind, m)
        normals = _normals(kind, m)
        if kind == "ring":  # bump centres on the surface
            centres = _base(kind, rng.uniform(0, 2 * np.pi, size=(n_bumps, 2)))
        else:  # inside the shape: broad, smooth bumps
            centres = _base(kind, rng.normal(size=(n_bumps, 3)) / 1.7)
        heights = rng.normal(size=n_bumps) * bump_mm
        d2 = ((base[:, None, :] - centres[None]) ** 2).sum(axis=2)
        offset = np.exp(-d2 / (2 * bump_width_mm ** 2)) @ heights
        if features:
            sizes = feature_heights * (1.0 + feature_cv * rng.normal(size=features))
            d2 = ((base[:, None, :] - feature_centres[None]) ** 2).sum(axis=2)
            offset = offset + np.exp(-d2 / (2 * feature_width_mm ** 2)) @ sizes
        shape = base + offset[:, None] * normals
        if retessellate:
            shape, faces, base = _retessellated(faces, shape, base, n_vertices)
        shape = shape * rng.uniform(0.9, 1.1, size=3)
        rot = random_rotation(rng, max_angle_deg)
        shape = shape @ rot.T + rng.uniform(-translation_mm, translation_mm, size=3)
        # Faces counter-clockwise seen from outside: the ring's grid is consistent and only
        # needs the global sign (the sphere lattice was oriented face by face; a remesh is
        # consistently oriented).
        if meshops.volume(shape, faces) < 0:
            faces = faces[:, ::-1]
        perm = rng.permutation(len(shape))
        inverse = np.argsort(perm)
        meshes.append(TriMesh(shape[perm], inverse[faces], f"{kind}_{s:02d}"))
        material.append(base[perm])
    return KnownHomologyShapes(kind, meshes, material)


def _outward(kind: str, m: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The lattice's faces counter-clockwise seen from outside the parameter sphere, face by
    face (the convex hull's are not); the ring's grid is left as it is."""
    if kind == "ring":
        return faces
    inward = np.einsum("ij,ij->i", face_normals(m, faces, normalize=False), m[faces].mean(axis=1)) < 0
    return np.where(inward[:, None], faces[:, ::-1], faces)


def _features(kind: str, n: int, height_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (n, 3) on the base surface and mean heights (n,) of a kind's consistent
    features: the same for every population of the kind (their own fixed seed)."""
    rng = np.random.default_rng(1000 + KINDS.index(kind))
    if kind == "ring":
        centres = _base(kind, rng.uniform(0, 2 * np.pi, size=(n, 2)))
    else:
        u = rng.normal(size=(n, 3))
        centres = _base(kind, u / np.linalg.norm(u, axis=1, keepdims=True))
    heights = rng.choice([-1.0, 1.0], n) * height_mm * rng.uniform(0.7, 1.3, n)
    return centres, heights


def _retessellated(faces: np.ndarray, shape: np.ndarray, base: np.ndarray,
                   n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An independent even remesh of one shape's surface: vertices, faces and the vertices'
    base-surface (material) positions, interpolated over the lattice's triangles."""
    from core.correspondence.grooming import remesh

    vertices, new_faces = remesh(shape, faces, n_vertices)
    return vertices, new_faces, material_points(vertices, TriMesh(shape, faces), base)


def unevenly_decimated(population: KnownHomologyShapes, *, seed: int = 0,
                       reduction: tuple[float, float] = (0.3, 0.85)) -> KnownHomologyShapes:
    """The population with every shape decimated by its own random share (quadric decimation,
    Garland & Heckbert 1997, in VTK: denser where the surface curves, uneven triangles) and
    its vertices shuffled again; the material points carried over by barycentric
    interpolation. The uneven tessellation style of issue 27's reviewer population."""
    import pyvista as pv

    rng = np.random.default_rng(seed)
    meshes, material = [], []
    for mesh, mat in zip(population.meshes, population.material):
        faces = np.asarray(mesh.faces)
        poly = pv.PolyData(np.asarray(mesh.vertices, float),
                           np.column_stack([np.full(len(faces), 3), faces]).ravel())
        out = poly.decimate(float(rng.uniform(*reduction)))
        v = np.asarray(out.points, dtype=np.float64)
        f = np.asarray(out.faces).reshape(-1, 4)[:, 1:]
        perm = rng.permutation(len(v))
        v, f = v[perm], np.argsort(perm)[f]
        meshes.append(TriMesh(v, f, mesh.name))
        material.append(material_points(v, mesh, mat))
    return KnownHomologyShapes(population.kind, meshes, material)


def material_points(points: np.ndarray, mesh: TriMesh, material: np.ndarray) -> np.ndarray:
    """Material points (P, 3) (base-surface positions, mm) of ``points`` on ``mesh``."""
    tri, bary, _ = surface_coordinates(points, mesh.vertices, mesh.faces)
    return np.einsum("pj,pjc->pc", bary, material[np.asarray(mesh.faces)[tri]])


def homology_spread(material: list) -> np.ndarray:
    """Mean distance (P,) of each corresponded point's material points from their mean."""
    stack = np.stack(material)  # (K, P, 3)
    return np.linalg.norm(stack - stack.mean(axis=0), axis=2).mean(axis=0)
