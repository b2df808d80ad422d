"""Known-truth population families for the correspondence validation protocol (issue 27).

Each family is a different generator of shapes whose every vertex knows its material point
(its position on the family's base surface), so :func:`core.datasets.shapes.homology_spread`
measures a correspondence against the truth. The method is the same for all families: a
shape is built on a FINE mesh (about 10,000 vertices) whose vertices carry exact material
points, posed (rotation up to 30 degrees about a random axis, a shift of 10-40 mm in a random
direction), then given its own tessellation in the family's style, and the new vertices get
their material by closest point and barycentric interpolation on the fine mesh
(:func:`core.datasets.shapes.material_points`); vertex order is random.

Tessellation styles: ``uneven`` (a randomly rotated icosphere or the fine lattice decimated by
a random amount: quadric decimation, Garland & Heckbert, SIGGRAPH 1997, in VTK; triangles
follow curvature and the parameter's density), ``even`` (the product's own even remesh,
:func:`core.correspondence.grooming.remesh`), ``mc`` (marching cubes, VTK flying edges, of the
signed distance to the shape on a grid, then light windowed-sinc smoothing, no decimation)
and ``labels`` (the shape voxelised to a label map, :func:`core.geometry.segmentation.voxelize`,
and meshed by the product's label-map path, :func:`core.correspondence.mesh_labels.mask_surface`:
Surface Nets and windowed-sinc smoothing, the staircase's remains included).

Families (the split was fixed before any number was looked at):

- ``global``: an elongated ellipsoid (40 x 16 x 10 mm) with per-shape bending, tapering and
  twisting plus three small independent bumps; uneven (rotated icosphere, decimated);
- ``concave``: a kidney (32 x 18 x 14 mm) with a deep dent at its hilum (a concavity ringed by
  saddles), varying bend, dent depth and place; uneven (quadric decimation of a fine mesh);
- ``coarse``: a smooth blob (28 x 20 x 16 mm) with low-order global modes and local bumps,
  decimated to 300-600 vertices;
- ``labels_1mm``: the bean of :mod:`core.datasets.shapes` with random scaling and bumps,
  voxelised at 1 mm, Surface Nets surface;
- ``ovoid``: the kind of issue 27: a bent, tapered ovoid (30 x 18 x 14 mm) with a global
  smooth wobble and 4 planted bumps along the normal (4 mm wide, about 1 mm high, at the same
  material points in every shape, random heights); uneven (rotated icosphere, decimated);
- ``thin``: a thin curved tube (50 x 5 mm, a caudate tail or an STN), bent along an arc by a
  random angle, tapered, slightly S-shaped; even;
- ``twolobe``: a peanut (two lobes joined by a neck, 26 x 14 x 10 mm) with varying lobe sizes
  and neck width; marching cubes at 0.5 mm;
- ``labels_05mm``: a bent thalamus-like ovoid (26 x 16 x 15 mm), voxelised at 0.5 x 0.5 x 1 mm,
  Surface Nets surface.

The ovoid's maths (:func:`ovoid_shape`) is also the ``ovoid`` family of
``benchmarks/recon_families.py`` (on its fixed lattice).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from core.datasets.shapes import KnownHomologyShapes, material_points
from core.geometry import mesh as meshops
from core.geometry.toolkit import face_normals, random_rotation, vertex_normals
from core.types import TriMesh

# The split was fixed before any number was looked at.
TUNING = ("global", "concave", "coarse", "labels_1mm")
REPORT = ("ovoid", "thin", "twolobe", "labels_05mm")
FAMILIES = TUNING + REPORT

FINE_POINTS = 10000  # fine Fibonacci lattice (the icosphere families: subdivision 5, 10,242)

# family: (tessellation style, vertex-count range of the output, or voxel / grid spacing mm)
STYLE = {"global": ("uneven", (1000, 1800)), "concave": ("uneven", (1000, 1800)),
         "coarse": ("uneven", (300, 600)), "labels_1mm": ("labels", (1.0, 1.0, 1.0)),
         "ovoid": ("uneven", (1000, 1800)), "thin": ("even", (900, 1400)),
         "twolobe": ("mc", (0.5, 0.5, 0.5)), "labels_05mm": ("labels", (0.5, 0.5, 1.0))}
ICOSPHERE = ("global", "ovoid")  # the fine lattice a randomly rotated icosphere

# Gate problems: a few shapes, 600-900 vertices (coarser grids for the grid-made families).
GATE: dict[str, dict[str, Any]] = {"global": {"size": (700, 900)}, "concave": {"size": (700, 900)},
        "coarse": {"size": (300, 600)}, "labels_1mm": {"size": (1.6, 1.6, 1.6)},
        "ovoid": {"size": (700, 900)}, "thin": {"size": (700, 900)},
        "twolobe": {"size": (1.1, 1.1, 1.1)}, "labels_05mm": {"size": (1.0, 1.0, 2.0)}}
GATE_SHAPES = 5
GATE_SEED = 2027


# ----------------------------------------------------------------------------- lattices

def sphere_lattice(n_points: int, rng: np.random.Generator | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Unit-sphere Fibonacci lattice (randomly rotated with ``rng``) and its outward hull faces."""
    from scipy.spatial import ConvexHull

    k = np.arange(n_points) + 0.5
    z = 1.0 - 2.0 * k / n_points
    ang = np.pi * (1.0 + 5 ** 0.5) * k
    r = np.sqrt(1.0 - z ** 2)
    m = np.column_stack([r * np.cos(ang), r * np.sin(ang), z])
    if rng is not None:
        m = m @ random_rotation(rng).T
    faces = ConvexHull(m).simplices
    inward = np.einsum("ij,ij->i", face_normals(m, faces, normalize=False), m[faces].mean(axis=1)) < 0
    return m, np.where(inward[:, None], faces[:, ::-1], faces)


@lru_cache(maxsize=2)
def _fixed_lattice(n_points: int) -> tuple[np.ndarray, np.ndarray]:
    return sphere_lattice(n_points)


def _icosphere(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A randomly rotated subdivision-5 icosphere (10,242 vertices), outward faces."""
    m, faces = _ico5()
    m = m @ random_rotation(rng).T
    return m, faces


@lru_cache(maxsize=1)
def _ico5() -> tuple[np.ndarray, np.ndarray]:
    import pyvista as pv

    ico = pv.Icosphere(radius=1.0, nsub=5)
    m = np.asarray(ico.points, dtype=np.float64)
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    faces = np.asarray(ico.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
    if meshops.volume(m, faces) < 0:
        faces = faces[:, ::-1].copy()
    return m, faces


# ----------------------------------------------------------------------------- shape maths

def normal_bumps(x: np.ndarray, normals: np.ndarray, centres: np.ndarray, heights: np.ndarray,
                 width: float) -> np.ndarray:
    """``x`` moved along ``normals`` by Gaussian bumps (sigma ``width`` mm) at ``centres``."""
    d2 = ((x[:, None, :] - centres[None]) ** 2).sum(axis=2)
    return x + (np.exp(-d2 / (2 * width ** 2)) @ heights)[:, None] * normals


def ovoid_base(m: np.ndarray) -> np.ndarray:
    """The ovoid's base surface (its mean bend and taper, no wobble, no bumps) at ``m``."""
    t = m[:, 0]
    taper = 1.0 - 0.25 * t
    x = np.column_stack([15.0 * t, 9.0 * m[:, 1] * taper, 7.0 * m[:, 2] * taper])
    x[:, 1] += 0.12 * 15.0 * t ** 2
    return x


def ovoid_shape(m: np.ndarray, faces: np.ndarray, rng: np.random.Generator,
                centres: np.ndarray | None = None) -> np.ndarray:
    """A bent, tapered ovoid (30 x 18 x 14 mm) at unit vectors ``m`` on the mesh ``faces``:
    random bend and taper, a global wobble (random radial harmonics of degree 1-3 of the
    parameter) and 4 bumps along the normal (sigma 2 mm, heights N(0, 1) mm), at random
    vertices, or at the lattice vertices closest to the unit vectors ``centres`` (4, 3)."""
    t = m[:, 0]
    taper = 1.0 - (0.25 + 0.1 * rng.normal()) * t
    x = np.column_stack([15.0 * t, 9.0 * m[:, 1] * taper, 7.0 * m[:, 2] * taper])
    x[:, 1] += (0.12 + 0.05 * rng.normal()) * 15.0 * t ** 2  # bend
    x[:, 2] += 0.04 * rng.normal() * 15.0 * t ** 2
    normals = vertex_normals(x, faces)
    wobble = sum(rng.normal() * 0.35 * m[:, a] * m[:, b] for a in range(3) for b in range(a, 3))
    wobble = wobble + 0.3 * rng.normal() * np.sin(3 * np.arctan2(m[:, 1], m[:, 2]))
    x = x + wobble[:, None] * normals
    at = rng.choice(len(x), 4, replace=False) if centres is None else np.argmax(m @ centres.T, axis=0)
    return normal_bumps(x, vertex_normals(x, faces), x[at], rng.normal(size=4) * 1.0, 2.0)


OVOID_CENTRES = np.array([[0.6, 0.7, 0.38], [-0.5, -0.3, 0.81], [0.1, -0.9, -0.42],
                          [-0.8, 0.5, -0.33]])
OVOID_CENTRES = OVOID_CENTRES / np.linalg.norm(OVOID_CENTRES, axis=1, keepdims=True)


def _random_bumps(x: np.ndarray, faces: np.ndarray, rng, n: int, height: float, width: float):
    at = rng.choice(len(x), n, replace=False)
    return normal_bumps(x, vertex_normals(x, faces), x[at], rng.normal(size=n) * height, width)


def _global(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Elongated ellipsoid (elliptic cross-section) with random bending, tapering and
    twisting about a mean of each (so that no symmetry hides the truth), small bumps."""
    t = m[:, 0]

    def bent(taper: float, twist: float, bend_y: float, bend_z: float, length: float):
        c, s = np.cos(twist * t), np.sin(twist * t)
        y, z = 8.0 * m[:, 1] * (1.0 - taper * t), 5.0 * m[:, 2] * (1.0 - taper * t)
        x = np.column_stack([20.0 * length * t, c * y - s * z, s * y + c * z])
        x[:, 1] += bend_y * 20.0 * t ** 2
        x[:, 2] += bend_z * 20.0 * t ** 2
        return x

    x = bent(0.3 + 0.12 * rng.normal(), 0.35 * rng.normal(), 0.2 + 0.08 * rng.normal(),
             0.08 * rng.normal(), rng.uniform(0.9, 1.1))
    return _random_bumps(x, faces, rng, 3, 0.6, 3.0), bent(0.3, 0.0, 0.2, 0.0, 1.0)


def _kidney(m: np.ndarray, bend: float, depth: float, shift: float) -> np.ndarray:
    x = 16.0 * m[:, 0]
    y = 9.0 * m[:, 1] + bend * 8.0 * (x / 16.0) ** 2
    z = 7.0 * m[:, 2]
    hilum = np.exp(-((x - shift) ** 2) / (2 * 4.0 ** 2) - z ** 2 / (2 * 4.0 ** 2))
    y = y - depth * hilum * np.clip(m[:, 1], 0.0, None) ** 1.5
    return np.column_stack([x, y, z])


def _concave(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Kidney with a deep dent at the hilum (concavity ringed by saddles), varying."""
    x = _kidney(m, 0.6 + 0.15 * rng.normal(), 5.0 + 0.8 * rng.normal(), 2.0 * rng.normal())
    x = x * rng.uniform(0.92, 1.08, size=3)
    return _random_bumps(x, faces, rng, 2, 0.5, 3.0), _kidney(m, 0.6, 5.0, 0.0)


def _radial_modes(m: np.ndarray, rng, sd: float) -> np.ndarray:
    """A smooth radial factor: a fixed egg-like asymmetry plus random harmonics of degree
    1-2 of the unit vectors."""
    quad = sum(rng.normal() * sd * m[:, a] * m[:, b] for a in range(3) for b in range(a, 3))
    return _egg(m) + quad + m @ (rng.normal(size=3) * sd / 2)


def _egg(m: np.ndarray) -> np.ndarray:
    return 1.0 + 0.15 * m[:, 0] + 0.12 * m[:, 0] * m[:, 1] - 0.08 * m[:, 2] ** 2


def _coarse(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Smooth blob with global modes (radial harmonics) plus local bumps."""
    radii = np.array([14.0, 10.0, 8.0])
    x = m * radii * _radial_modes(m, rng, 0.08)[:, None]
    return _random_bumps(x, faces, rng, 3, 1.0, 3.0), m * radii * _egg(m)[:, None]


def _labels_1mm(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """The bean of core.datasets.shapes, randomly scaled, with broad bumps."""
    from core.datasets.shapes import _base

    base = _base("bean", m)
    x = base * rng.uniform(0.9, 1.1, size=3)
    return _random_bumps(x, faces, rng, 4, 1.2, 5.0), base


def _thalamus(m: np.ndarray, bend: float, taper: float) -> np.ndarray:
    t = m[:, 0]
    x = np.column_stack([13.0 * t, 8.0 * m[:, 1] * (1 - taper * t), 7.5 * m[:, 2] * (1 - taper * t)])
    x[:, 2] += bend * 13.0 * t ** 2
    return x


def _labels_05mm(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Bent thalamus-like ovoid with a random bend, taper, scaling and bumps."""
    x = _thalamus(m, 0.15 + 0.06 * rng.normal(), 0.3 + 0.08 * rng.normal())
    x = x * rng.uniform(0.9, 1.1, size=3)
    return _random_bumps(x, faces, rng, 4, 0.8, 3.0), _thalamus(m, 0.15, 0.3)


def _ovoid(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    return ovoid_shape(m, faces, rng, OVOID_CENTRES), ovoid_base(m)


def _tube_base(m: np.ndarray) -> np.ndarray:
    """Straight capsule-like tube 50 x 5 mm: (x/25)^2 + (r/2.5)^4 = 1."""
    t = m[:, 0]
    ring = np.sqrt(np.clip(1.0 - t ** 2, 1e-12, None))
    r = 2.5 * np.clip(1.0 - t ** 2, 0.0, None) ** 0.25
    return np.column_stack([25.0 * t, r * m[:, 1] / ring, r * m[:, 2] / ring])


def _thin(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """The tube bent along an arc (43-100 degrees), tapered, thickened, slightly S-shaped."""
    base = _tube_base(m)
    x = base.copy()
    x[:, 1:] *= (rng.uniform(0.85, 1.15) * (1.0 - rng.uniform(0.1, 0.4) * x[:, 0] / 25.0))[:, None]
    x[:, 2] += rng.normal() * 1.5 * np.sin(np.pi * x[:, 0] / 25.0)
    kappa = rng.uniform(0.015, 0.035)  # 1/mm
    phi = kappa * x[:, 0]
    rad = 1.0 / kappa - x[:, 1]
    x = np.column_stack([rad * np.sin(phi), 1.0 / kappa - rad * np.cos(phi), x[:, 2]])
    return _random_bumps(x, faces, rng, 2, 0.4, 3.0), base


def _peanut(m: np.ndarray, lobes: float, neck: float, length: float, bend: float) -> np.ndarray:
    t = m[:, 0]
    profile = (1.0 + lobes * np.tanh(3.0 * t)) * (1.0 - neck * np.exp(-t ** 2 / 0.05))
    x = np.column_stack([13.0 * length * t, 6.0 * profile * m[:, 1], 4.5 * profile * m[:, 2]])
    x[:, 2] += bend * 13.0 * t ** 2
    return x


def _twolobe(m: np.ndarray, faces: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Two lobes (elliptic sections) joined by a neck, bent a little: random lobe-size
    ratio about a bigger +x lobe, neck width, length and bend."""
    x = _peanut(m, 0.15 + 0.07 * rng.normal(), rng.uniform(0.3, 0.55), rng.uniform(0.9, 1.1),
                0.12 + 0.05 * rng.normal())
    return _random_bumps(x, faces, rng, 2, 0.5, 3.0), _peanut(m, 0.15, 0.42, 1.0, 0.12)


SHAPES = {"global": _global, "concave": _concave, "coarse": _coarse, "labels_1mm": _labels_1mm,
          "ovoid": _ovoid, "thin": _thin, "twolobe": _twolobe, "labels_05mm": _labels_05mm}


# ----------------------------------------------------------------------------- tessellations

def _decimated(vertices: np.ndarray, faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation (VTK, no volume preservation) to about ``n_vertices``; a result that
    is not one closed 2-manifold is decimated again 3 % and 6 % off."""
    import pyvista as pv

    from core.correspondence.grooming import _arrays

    poly = pv.PolyData(vertices, np.column_stack([np.full(len(faces), 3), faces]).ravel())
    for shift in (0.0, 0.03, -0.03, 0.06, -0.06):
        target = 2 * n_vertices * (1.0 + shift) - 4
        v, f = _arrays(poly.decimate(max(1.0 - target / poly.n_cells, 0.0)).triangulate())
        if meshops.is_closed_manifold(f, len(v)) and meshops.euler_characteristic(len(v), f) == 2:
            return v, f
    raise RuntimeError("quadric decimation did not give a closed 2-manifold")


def _grid(vertices: np.ndarray, spacing: np.ndarray, rng, pad: int = 3) -> np.ndarray:
    """Voxel -> world affine of an axis-aligned grid around ``vertices`` at a random offset."""
    affine = np.diag([*spacing, 1.0])
    affine[:3, 3] = vertices.min(axis=0) - pad * spacing + rng.uniform(0, 1, 3) * spacing
    return affine


def _grid_shape(vertices: np.ndarray, affine: np.ndarray, pad: int = 3) -> tuple:
    extent = (vertices.max(axis=0) - affine[:3, 3]) / np.diag(affine)[:3]
    return tuple(int(e) + pad + 1 for e in extent)


def _labels(vertices: np.ndarray, faces: np.ndarray, spacing, rng) -> tuple[np.ndarray, np.ndarray]:
    """The product's label-map path (``mesh-labels`` without its remesh): voxelise, repair
    the mask (edge and corner contacts), Surface Nets + windowed-sinc smoothing."""
    from core.correspondence.mesh_labels import mask_surface, repair_mask
    from core.geometry.segmentation import voxelize

    spacing = np.asarray(spacing, dtype=np.float64)
    affine = _grid(vertices, spacing, rng)
    mask = voxelize(vertices, faces, _grid_shape(vertices, affine), affine)
    return mask_surface(repair_mask(mask, spacing)[0], affine)


def _marching_cubes(vertices: np.ndarray, faces: np.ndarray, spacing, rng
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Flying edges of the signed distance to the surface (inside negative) on a grid at
    ``spacing`` (distance exact within 2 voxels of the surface, clamped beyond), then 10
    windowed-sinc iterations."""
    from scipy import ndimage
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D, vtkWindowedSincPolyDataFilter

    from core.correspondence.mesh_labels import polydata_arrays, vtk_image
    from core.geometry.segmentation import voxelize
    from core.geometry.toolkit import SurfaceProjector

    spacing = np.asarray(spacing, dtype=np.float64)
    affine = _grid(vertices, spacing, rng)
    shape = _grid_shape(vertices, affine)
    inside = voxelize(vertices, faces, shape, affine).astype(bool)
    band = ndimage.binary_dilation(inside, iterations=2) & ~ndimage.binary_erosion(inside, iterations=2)
    ijk = np.argwhere(band)
    sdf = np.where(inside, -2.0, 2.0) * spacing.max()
    dist = SurfaceProjector(vertices, faces, exact=False)(ijk * spacing + affine[:3, 3])[1]
    sdf[tuple(ijk.T)] = np.where(inside[tuple(ijk.T)], -dist, dist)
    edges = vtkFlyingEdges3D()
    edges.SetInputData(vtk_image(sdf))
    edges.SetValue(0, 0.0)
    edges.ComputeNormalsOff()
    smoother = vtkWindowedSincPolyDataFilter()
    smoother.SetInputConnection(edges.GetOutputPort())
    smoother.SetNumberOfIterations(10)
    smoother.SetPassBand(0.1)
    smoother.NormalizeCoordinatesOn()
    smoother.Update()
    v, f = polydata_arrays(smoother.GetOutput())
    return v * spacing + affine[:3, 3], f


def _tessellate(style: str, vertices: np.ndarray, faces: np.ndarray, size, rng
                ) -> tuple[np.ndarray, np.ndarray]:
    """One shape's own tessellation in ``style``; ``size``: vertex-count range or spacing."""
    if style == "uneven":
        return _decimated(vertices, faces, int(rng.integers(size[0], size[1] + 1)))
    if style == "even":
        from core.correspondence.grooming import remesh

        return remesh(vertices, faces, int(rng.integers(size[0], size[1] + 1)))
    if style == "mc":
        return _marching_cubes(vertices, faces, size, rng)
    return _labels(vertices, faces, size, rng)


# ----------------------------------------------------------------------------- populations

def _pose(rng: np.random.Generator, max_angle_deg: float, shift_mm: tuple[float, float]):
    rot = random_rotation(rng, max_angle_deg)
    direction = rng.normal(size=3)
    return rot, direction / np.linalg.norm(direction) * rng.uniform(*shift_mm)


def _one_shape(family: str, rng: np.random.Generator, size, max_angle_deg: float,
               shift_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One shape of ``family``: vertices (posed, own tessellation, mm), faces, material."""
    m, faces = _icosphere(rng) if family in ICOSPHERE else _fixed_lattice(FINE_POINTS)
    x, material = SHAPES[family](m, faces, rng)
    rot, shift = _pose(rng, max_angle_deg, shift_mm)
    x = x @ rot.T + shift
    if meshops.volume(x, faces) < 0:
        faces = faces[:, ::-1]
    v, f = _tessellate(STYLE[family][0], x, faces, size, rng)
    if meshops.volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, f, material_points(v, TriMesh(x, faces), material)


def population(family: str, n_shapes: int = 8, seed: int = 0, *, size=None,
               max_angle_deg: float = 30.0, shift_mm: tuple[float, float] = (10.0, 40.0)
               ) -> KnownHomologyShapes:
    """``n_shapes`` shapes of ``family`` (module docstring), reproducible from ``seed``.

    Every shape: its own tessellation, random vertex order, random pose (rotation up to
    ``max_angle_deg`` about a random axis, a shift of ``shift_mm`` in a random direction).
    ``size``: the family's vertex-count range (uneven, even) or grid spacing in mm (mc,
    labels) instead of its default (:data:`STYLE`).
    """
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    if n_shapes < 1:
        raise ValueError(f"n_shapes must be at least 1, got {n_shapes}")
    rng = np.random.default_rng([int(seed), FAMILIES.index(family)])
    size = STYLE[family][1] if size is None else size
    meshes, material = [], []
    for s in range(n_shapes):
        v, f, mat = _one_shape(family, rng, size, max_angle_deg, shift_mm)
        perm = rng.permutation(len(v))
        meshes.append(TriMesh(v[perm], np.argsort(perm)[f], f"{family}_{s:02d}"))
        material.append(mat[perm])
    return KnownHomologyShapes(family, meshes, material)


def gate_problem(family: str) -> KnownHomologyShapes:
    """The quality gate's fixed problem of ``family``: :data:`GATE_SHAPES` shapes of about
    600-900 vertices (:data:`GATE`), seed :data:`GATE_SEED`."""
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}, got {family!r}")
    return population(family, GATE_SHAPES, GATE_SEED, **GATE[family])
