"""Benchmark: the whole correspondence step per shape, SSM Studio vs plain CPD pipelines.

Peers, on the same inputs in the same run:

- ``ssm-studio``: :func:`core.correspondence.correspond_pair` (rustcpd rigid + nonrigid CPD,
  log-posterior linear assignment, fairing on the target surface);
- ``rustcpd``: rustcpd rigid + nonrigid CPD with the same parameters, then each deformed
  reference vertex projected to its nearest point on the target surface;
- ``pycpd``: the same plain pipeline on pycpd 2.x (pure numpy; benchmark-only dependency).

Quality is measured on shapes with known homologues (synthetic, or the demo set's ground truth
when present): the distance of every corresponded vertex to its true homologue (mean and max,
mm). Then the whole batch (``establish_correspondence``, auto reference) is timed on 2 workers.

Run: ``.venv/bin/python benchmarks/bench_correspondence.py [--shapes 6] [--pycpd 2]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.io import TriMesh  # noqa: E402


# ----------------------------------------------------------------------------- synthetic data

def _random_rotation(rng: np.random.Generator, max_angle_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(rng.uniform(-max_angle_deg, max_angle_deg))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _sphere_mesh(n_points: int, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Near-uniform sphere triangulation: a Fibonacci lattice of ``n_points`` and its hull."""
    from scipy.spatial import ConvexHull

    i = np.arange(n_points) + 0.5
    z = 1.0 - 2.0 * i / n_points
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    r = np.sqrt(1.0 - z ** 2)
    pts = np.column_stack([r * np.cos(phi), r * np.sin(phi), z]) @ rotation.T
    faces = ConvexHull(pts).simplices
    # Orient counter-clockwise seen from outside.
    v = pts[faces]
    normal = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", normal, v.mean(axis=1)) < 0
    faces[flip] = faces[flip][:, ::-1]
    return pts, faces


def bean(u: np.ndarray) -> np.ndarray:
    """Base shape from unit vectors: a bent, tapered ellipsoid with a one-sided bulge.

    About 36 x 20 x 15 mm, caudate-like, and without rotational symmetry, so that its pose
    is well defined.
    """
    x = 18.0 * u[:, 0]
    taper = 1.0 - 0.5 * u[:, 0]
    y = 8.0 * u[:, 1] * taper + 0.012 * (x + 18.0) ** 2
    z = 6.0 * u[:, 2] * taper + 5.0 * np.exp(-((x - 9.0) ** 2) / 30.0) * (1.0 + u[:, 2]) / 2.0
    return np.column_stack([x, y, z])


def bean_normals(u: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """Outward unit normals of :func:`bean` at unit vectors ``u`` (P, 3), by finite differences."""
    helper = np.where(np.abs(u[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(u, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(u, t1)
    d1 = bean(u + eps * t1) - bean(u - eps * t1)
    d2 = bean(u + eps * t2) - bean(u - eps * t2)
    n = np.cross(d1, d2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n * np.sign(np.einsum("ij,ij->i", n, bean(u) - bean(u).mean(axis=0)))[:, None]


def smooth_deformation(rng: np.random.Generator, n_bumps: int = 6, amplitude: float = 1.5,
                       width: float = 7.0):
    """A random smooth shape change: Gaussian bumps along the surface normal, then an
    anisotropic scaling. Maps unit vectors (P, 3) to points (P, 3).

    The bumps move material points along the normal only, so the true homologues are
    determined by the geometry (a tangential field would make them unobservable).
    """
    centres = bean(rng.normal(size=(n_bumps, 3)) / 1.7)
    heights = rng.normal(size=n_bumps) * amplitude
    scale = rng.uniform(0.9, 1.1, size=3)

    def f(u: np.ndarray) -> np.ndarray:
        p = bean(u)
        d2 = ((p[:, None, :] - centres[None]) ** 2).sum(axis=2)
        bump = np.exp(-d2 / (2 * width ** 2)) @ heights
        return (p + bump[:, None] * bean_normals(u)) * scale

    return f


def synthetic_population(n_shapes: int = 20, *, seed: int = 0, max_angle_deg: float = 45.0,
                         translation_mm: float = 40.0,
                         n_points: tuple[int, int] = (1800, 2300)) -> tuple[list[TriMesh], tuple]:
    """Remeshed, permuted and posed smooth deformations of one bean shape, with known truth.

    Returns the meshes and, per mesh, ``truth(u)``: the posed position on that shape of the
    material point with unit-sphere parameter(s) ``u`` (P, 3), plus each mesh's own parameters
    in ``params[k]``. Two meshes' points are homologous when their parameters are equal.
    """
    rng = np.random.default_rng(seed)
    meshes, truths, params = [], [], []
    for k in range(n_shapes):
        u, faces = _sphere_mesh(int(rng.integers(*n_points)), _random_rotation(rng, 180.0))
        perm = rng.permutation(len(u))
        inverse = np.argsort(perm)
        u = u[perm]
        faces = inverse[faces]
        deform = smooth_deformation(rng)
        rot = _random_rotation(rng, max_angle_deg)
        trans = rng.uniform(-translation_mm, translation_mm, size=3)

        def truth(uu, deform=deform, rot=rot, trans=trans):
            return deform(uu) @ rot.T + trans

        meshes.append(TriMesh(truth(u), faces, f"synthetic_{k:02d}"))
        truths.append(truth)
        params.append(u)
    return meshes, (truths, params)
