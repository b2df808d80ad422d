"""Headless model building: raw meshes -> corresponded -> aligned -> shape model placed in world.

The façade used by ``ssm-studio build-model`` / ``evaluate`` and by the GUI's model builder.
Each stage is a separate function so a caller can cache completed stages and rerun only what
changed (e.g. only :func:`fit_model` when the method's parameters change):

1. :func:`correspond` -- put raw meshes in correspondence with a reference
   (``core.correspondence.establish_correspondence``; CPD + assignment + fairing);
   or :func:`corresponded_shapes` for meshes that already share one topology;
2. :func:`align` -- remove pose (``core.alignment.transforms.align_shapes``: transformation
   synchronisation or GPA; or ``"none"``);
3. :func:`fit_model` -- fit a ``core.models`` estimator on the aligned shapes;
4. :func:`world_placement` -- the model frame -> world transform that puts the model's mean
   where the training shapes are: the least-squares transform (class of the alignment:
   similarity, rigid, euclidean or affine) of the model mean onto the vertex-wise average of
   the corresponded, unaligned training shapes (in world mm, e.g. on the structure in the MRI
   the meshes came from).

:func:`build_model` runs them all and returns a :class:`BuildResult`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.io import TriMesh
from core.models import make_model, model_class
from core.models.base import ShapeModelEstimator
from core.models.shape_model import ShapeModel
from core.runtime.progress import ProgressCallback, report, sub_progress

ALIGN_METHODS = ("sync", "sync-sparse", "gpa", "none")
TRANSFORMS = ("similarity", "euclidean", "rigid", "affine")


@dataclass
class AlignedShapes:
    """Result of :func:`align` (same fields as ``core.alignment.transforms.AlignmentResult``).

    aligned (K, N, 3); transforms (K, 4, 4) mapping input k into the common frame
    (column vectors); mean (N, 3); method; transform.
    """

    aligned: np.ndarray
    transforms: np.ndarray
    mean: np.ndarray
    method: str
    transform: str


@dataclass
class BuildResult:
    """Everything :func:`build_model` produced.

    Attributes
    ----------
    model : ShapeModel, placed in world by ``world_transform``
    estimator : the fitted ``core.models`` estimator (model frame)
    names : names of the training meshes used (failed correspondences left out)
    meshes : corresponded training meshes (world mm, shared faces)
    shapes : (K, N, 3) corresponded vertices, unaligned (world mm)
    aligned : (K, N, 3) shapes in the model frame
    transforms : (K, 4, 4) world shape k -> model frame
    faces : (F, 3)
    correspondence : the CorrespondenceResult, or None if the inputs were corresponded
    failures : mesh name -> reason (correspondence failures)
    timings : seconds per stage ("correspondence", "alignment", "model", "total")
    """

    model: ShapeModel
    estimator: ShapeModelEstimator
    names: list[str]
    meshes: list[TriMesh]
    shapes: np.ndarray
    aligned: np.ndarray
    transforms: np.ndarray
    faces: np.ndarray
    correspondence: Any = None
    failures: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)


def corresponded_shapes(meshes: Sequence[TriMesh]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Check that meshes are in correspondence (same vertex count and faces); stack them.

    Returns names, shapes (K, N, 3) and faces (F, 3) (the first mesh's).
    """
    meshes = [m for m in meshes if m is not None]
    if len(meshes) < 3:
        raise ValueError(f"a shape model needs at least 3 training meshes, got {len(meshes)}")
    first = meshes[0]
    for m in meshes[1:]:
        if m.n_vertices != first.n_vertices:
            raise ValueError(
                f"{m.name or 'a mesh'} has {m.n_vertices} vertices but {first.name or 'the first'} "
                f"has {first.n_vertices}: the meshes are not in correspondence (use --correspond "
                "to establish correspondence first)")
        if m.faces.shape != first.faces.shape or not np.array_equal(m.faces, first.faces):
            raise ValueError(
                f"{m.name or 'a mesh'} has different triangles from {first.name or 'the first'}: "
                "corresponded meshes must share one topology (use --correspond)")
    names = [m.name or f"shape{i}" for i, m in enumerate(meshes)]
    return names, np.stack([m.vertices for m in meshes]), first.faces.copy()


def correspond(meshes: Sequence[TriMesh], *, reference: str | int | TriMesh = "auto",
               n_references: int = 3, n_jobs: int | None = None,
               progress: ProgressCallback | None = None, **cpd_params):
    """Stage 1: ``core.correspondence.establish_correspondence`` (CorrespondenceResult)."""
    from core.correspondence import establish_correspondence

    return establish_correspondence(list(meshes), reference=reference, n_references=n_references,
                                    n_jobs=n_jobs, progress=progress, **cpd_params)


def align(shapes: np.ndarray, *, method: str = "sync", transform: str = "similarity",
          progress: ProgressCallback | None = None) -> AlignedShapes:
    """Stage 2: remove pose from corresponded shapes (K, N, 3).

    method "sync" (transformation synchronisation) or "gpa" (generalised Procrustes) via
    ``core.alignment.transforms.align_shapes``; "sync-sparse" the same synchronisation on the graph of
    each shape's 10 nearest (``core.alignment.transforms.align_shapes_sparse``: cohort scale, time and
    memory linear in the number of shapes); "none" keeps the shapes as they are (identity
    transforms).
    """
    if method not in ALIGN_METHODS:
        raise ValueError(f"alignment must be one of {', '.join(ALIGN_METHODS)}; got {method!r}")
    if transform not in TRANSFORMS:
        raise ValueError(f"transform must be one of {', '.join(TRANSFORMS)}; got {transform!r}")
    shapes = np.asarray(shapes, dtype=np.float64)
    if method == "none":
        report(progress, 1.0, "no alignment")
        return AlignedShapes(shapes.copy(), np.tile(np.eye(4), (len(shapes), 1, 1)),
                             shapes.mean(axis=0), "none", transform)
    from core.alignment.transforms import align_shapes

    res = align_shapes(shapes, method=method, transform=transform, progress=progress)
    return AlignedShapes(res.aligned, res.transforms, res.mean, method, transform)


def world_placement(model_mean: np.ndarray, shapes_world: np.ndarray,
                    transform: str = "similarity") -> np.ndarray:
    """Model frame -> world (4, 4): the least-squares ``transform`` of the model mean (N, 3)
    onto the vertex-wise average of the unaligned training shapes (K, N, 3)."""
    from core.alignment.transforms import fit_transform

    cls = transform if transform in TRANSFORMS else "similarity"
    return fit_transform(np.asarray(model_mean), np.asarray(shapes_world).mean(axis=0), cls)


# build_model's keyword arguments ``correspond``/``align`` shadow the stage functions.
_correspond_stage = correspond
_align_stage = align


def fit_model(aligned: np.ndarray, faces: np.ndarray, *, method: str = "pca",
              n_factors: int | None = None, method_params: dict[str, Any] | None = None,
              progress: ProgressCallback | None = None) -> ShapeModelEstimator:
    """Stage 3: fit the ``method`` estimator on aligned shapes (K, N, 3); the mesh ``faces``
    are its ``connectivity``."""
    params = dict(method_params or {})
    if n_factors is not None:
        params["n_factors"] = int(n_factors)
    params["connectivity"] = faces
    estimator = make_model(method, **params)
    return estimator.fit(aligned, progress=progress)


def build_model(meshes: Sequence[TriMesh] | np.ndarray, *, correspond: bool = False,
                faces: np.ndarray | None = None, reference: str | int | TriMesh = "auto",
                n_references: int = 3, align: str = "sync", transform: str = "similarity",
                method: str = "pca", n_factors: int | None = None,
                method_params: dict[str, Any] | None = None, n_jobs: int | None = None,
                progress: ProgressCallback | None = None,
                correspond_options: dict[str, Any] | None = None) -> BuildResult:
    """Build a placed shape model from training meshes (or corresponded shapes).

    Parameters
    ----------
    meshes : list of TriMesh, or (K, N, 3) corresponded shapes (then ``faces`` is required)
    correspond : run the correspondence stage first (raw meshes of any topology)
    reference, n_references, n_jobs : correspondence options
    align : "sync", "sync-sparse", "gpa" or "none"; transform : "similarity", "euclidean", "rigid", "affine"
    method : "pca", "lsf", "splocs", "varimax"; n_factors; method_params : other parameters
    progress : progress(fraction, message); may raise ``core.runtime.progress.Cancelled``
    correspond_options : more keyword arguments of the correspondence stage
        (``establish_correspondence``: e.g. ``scratch``, with input paths, to stream)

    Returns
    -------
    BuildResult
    """
    model_class(method)  # unknown method: fail before any long stage
    if align not in ALIGN_METHODS:
        raise ValueError(f"alignment must be one of {', '.join(ALIGN_METHODS)}; got {align!r}")
    if transform not in TRANSFORMS:
        raise ValueError(f"transform must be one of {', '.join(TRANSFORMS)}; got {transform!r}")
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    names, shapes, faces, corresponded, corr, p_corr = _prepare_inputs(
        meshes, correspond, faces, reference, n_references, n_jobs, progress, timings,
        correspond_options or {})
    failures = dict(corr.failures) if corr is not None else {}
    p_align = p_corr + 0.1 * (1 - p_corr)
    t0 = time.perf_counter()
    alignment = _align_stage(shapes, method=align, transform=transform,
                             progress=sub_progress(progress, p_corr, p_align))
    timings["alignment"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    estimator = fit_model(alignment.aligned, faces, method=method, n_factors=n_factors,
                          method_params=method_params,
                          progress=sub_progress(progress, p_align, 1.0))
    timings["model"] = time.perf_counter() - t0
    world = world_placement(estimator.mean_, shapes, transform if align != "none" else "rigid")
    timings["total"] = time.perf_counter() - t_start
    info = {"alignment": {"method": align, "transform": transform},
            "timings": {k: round(v, 3) for k, v in timings.items()},
            "n_iter": getattr(estimator, "n_iter_", None),
            "converged": getattr(estimator, "converged_", None)}
    if corr is not None:
        info["correspondence"] = corr.provenance()
    model = estimator.to_shape_model(faces, world_transform=world, source_meshes=names, info=info)
    report(progress, 1.0, f"{estimator.method} model: {estimator.n_factors_} factors")
    return BuildResult(model=model, estimator=estimator, names=names, meshes=corresponded,
                       shapes=shapes, aligned=alignment.aligned, transforms=alignment.transforms,
                       faces=faces, correspondence=corr, failures=failures, timings=timings)


def _prepare_inputs(meshes, correspond: bool, faces, reference, n_references, n_jobs, progress,
                    timings: dict, options: dict | None = None):
    """Stage 1 of :func:`build_model`: names, shapes (K, N, 3), faces, corresponded meshes,
    the CorrespondenceResult (or None) and the progress share used."""
    if isinstance(meshes, np.ndarray):
        if correspond:
            raise ValueError("correspond=True needs meshes, not an array of shapes")
        if faces is None:
            raise ValueError("faces are required when building from an array of shapes")
        shapes = np.asarray(meshes, dtype=np.float64)
        if shapes.ndim != 3 or shapes.shape[2] != 3 or len(shapes) < 3:
            raise ValueError(f"shapes must be (K >= 3, N, 3), got {shapes.shape}")
        faces = np.asarray(faces, dtype=np.int64)
        names = [f"shape{i}" for i in range(len(shapes))]
        return names, shapes, faces, [TriMesh(s, faces, n) for s, n in zip(shapes, names)], \
            None, 0.0
    if not correspond:
        names, shapes, faces = corresponded_shapes(list(meshes))
        return names, shapes, faces, [m for m in meshes if m is not None], None, 0.0
    t0 = time.perf_counter()
    corr = _correspond_stage(meshes, reference=reference, n_references=n_references,
                             n_jobs=n_jobs, progress=sub_progress(progress, 0.0, 0.6),
                             **(options or {}))
    timings["correspondence"] = time.perf_counter() - t0
    corresponded = [m for m in corr.meshes if m is not None]
    if len(corresponded) < 3:
        raise ValueError(f"only {len(corresponded)} meshes could be put in correspondence "
                         f"(failures: {dict(corr.failures)}); a model needs at least 3")
    names, shapes, faces = corresponded_shapes(corresponded)
    return names, shapes, faces, corresponded, corr, 0.6


# --------------------------------------------------------------------------------------
# Command-line helpers (shared by ``build-model`` and ``evaluate``)
# --------------------------------------------------------------------------------------


def load_training_meshes(inputs: Sequence[str], progress: ProgressCallback | None = None, *,
                         isolate: bool = False, vertex_order: bool = False) -> list[TriMesh]:
    """Load mesh files; a folder stands for the mesh files inside it (sorted by name).

    ``isolate`` and ``vertex_order`` as in :func:`core.io.load_meshes` (read in a child
    process; refuse formats that lose vertex order, for corresponded inputs).
    Raises DataFileError / ValueError naming the file for unreadable input.
    """
    from core.io import DataFileError, load_meshes

    paths = training_mesh_paths(inputs)
    loaded, failures = load_meshes(paths, progress, isolate=isolate, vertex_order=vertex_order)
    if failures:
        name, problem = next(iter(failures.items()))
        raise DataFileError(name, problem)
    return [mesh for _, mesh in loaded]


def training_mesh_paths(inputs: Sequence[str]) -> list:
    """The mesh files of ``inputs`` (a folder stands for the mesh files in it, sorted by name;
    each file once). Raises DataFileError for a folder without mesh files."""
    from pathlib import Path

    from core.io import MESH_SUFFIXES, DataFileError, expand_mesh_paths

    paths: list = []
    seen: set = set()  # a set: a cohort's folder holds thousands of files
    for item in inputs:
        found = expand_mesh_paths([item])
        if not found and Path(item).is_dir():
            raise DataFileError(item, f"folder contains no mesh files ({', '.join(MESH_SUFFIXES)})")
        for p in found:
            if p not in seen:
                seen.add(p)
                paths.append(p)
    return paths


def parse_param_values(items: Sequence[str] | None) -> dict[str, Any]:
    """``["name=value", ...]`` -> dict; values parsed as JSON when possible (numbers, booleans),
    else kept as strings."""
    import json

    out: dict[str, Any] = {}
    for item in items or ():
        if "=" not in item:
            raise ValueError(f"--param expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        name = name.strip()
        if not name:
            raise ValueError(f"--param expects NAME=VALUE, got {item!r}")
        try:
            out[name] = json.loads(value)
        except json.JSONDecodeError:
            low = value.strip().lower()
            out[name] = {"true": True, "false": False, "none": None}.get(low, value.strip())
    return out
