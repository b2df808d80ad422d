"""The model builder's calls into ``core``, one function per worker job (no Qt here).

Every function here runs inside an :class:`app.workers.Worker`: it takes plain data, returns
plain data, reports ``progress(fraction, message)`` and lets ``core.progress.Cancelled``
propagate. The stage functions wrap ``core.pipeline``'s stages (correspond -> align -> fit
model) so that the panel can cache each stage's result and rerun only what changed.
"""

from __future__ import annotations

import importlib
import inspect
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.io import TriMesh, load_meshes
from core.mesh import surface_problems
from core.progress import ProgressCallback, report, sub_progress

try:
    from core.pipeline import ALIGN_METHODS, TRANSFORMS
except ImportError:  # pragma: no cover - older core
    ALIGN_METHODS = ("sync", "gpa")
    TRANSFORMS = ("similarity", "euclidean", "rigid", "affine")
MODEL_ORDER = ("pca", "lsf", "splocs", "varimax")


# ------------------------------------------------------------------------------------------
# Training meshes
# ------------------------------------------------------------------------------------------


@dataclass
class MeshEntry:
    """One training mesh file: the mesh (None if it could not be read) and its problems."""

    path: str
    name: str
    mesh: TriMesh | None
    problems: list[str] = field(default_factory=list)
    included: bool = True


def load_entries(files: list[str | os.PathLike], progress: ProgressCallback | None = None
                 ) -> list[MeshEntry]:
    """Read each file; an unreadable file becomes an entry with ``mesh=None`` and its error."""
    loaded, failures = load_meshes(files, progress)
    meshes = {str(path): mesh for path, mesh in loaded}
    entries = []
    for f in map(Path, files):
        mesh = meshes.get(str(f))
        if mesh is None:
            entries.append(MeshEntry(str(f), f.name, None, [failures[str(f)]], included=False))
            continue
        mesh.name = f.name
        entries.append(MeshEntry(str(f), f.name, mesh, surface_problems(mesh.vertices, mesh.faces)))
    return entries


def load_label_entries(files: list[str | os.PathLike], label: str,
                       progress: ProgressCallback | None = None) -> list[MeshEntry]:
    """One label of each label map as a training mesh (core.mesh_labels); errors per file."""
    from core.mesh_labels import label_map_surfaces

    entries = []
    for path, mesh, error in label_map_surfaces(files, label, progress=progress):
        if mesh is None:
            entries.append(MeshEntry(path, Path(path).name, None, [error], included=False))
        else:
            entries.append(MeshEntry(path, mesh.name, mesh, surface_problems(mesh.vertices, mesh.faces)))
    return entries


# ------------------------------------------------------------------------------------------
# Model classes (for the parameter forms)
# ------------------------------------------------------------------------------------------


def model_classes() -> dict[str, type]:
    """Model-building estimator classes by method name, in the order PCA, LSF, SPLOCS, Varimax."""
    try:
        from core.models import MODELS

        return {name: MODELS[name] for name in sorted(MODELS, key=_model_rank)}
    except ImportError:  # some estimator module missing: list those that import
        pass
    found: dict[str, type] = {}
    try:
        from core.models.base import DeformationModel
    except ImportError:
        return found
    for name in MODEL_ORDER:
        try:
            module = importlib.import_module(f"core.models.{name}")
        except ImportError:
            continue
        for obj in vars(module).values():
            if isinstance(obj, type) and issubclass(obj, DeformationModel) and \
                    getattr(obj, "method", "") == name:
                found[name] = obj
    return found


def _model_rank(name: str) -> int:
    return MODEL_ORDER.index(name) if name in MODEL_ORDER else len(MODEL_ORDER)


def method_summary(cls: type) -> str:
    """First paragraph of a class docstring (for tooltips)."""
    doc = inspect.getdoc(cls) or cls.__name__
    return doc.split("\n\n")[0].replace("\n", " ")


def default_n_references() -> int:
    try:
        from core.correspondence import establish_correspondence
    except ImportError:
        return 3
    default = inspect.signature(establish_correspondence).parameters.get("n_references")
    return int(default.default) if default is not None and isinstance(default.default, int) else 3


# ------------------------------------------------------------------------------------------
# Pipeline stages
# ------------------------------------------------------------------------------------------


NO_CORRESPONDENCE = "none (already corresponded)"


def run_correspondence(meshes: list[TriMesh], reference: str | int = "auto", n_references: int = 3,
                       progress: ProgressCallback | None = None):
    """Stage 1 (``core.pipeline.correspond``): every mesh with the reference's topology.

    ``reference`` is "auto", an index into ``meshes``, or :data:`NO_CORRESPONDENCE` for meshes
    that already share one topology (checked; they are used as they are).
    Returns a ``core.correspondence.CorrespondenceResult``.
    """
    from core import pipeline
    from core.correspondence import CorrespondenceResult

    if reference == NO_CORRESPONDENCE:
        report(progress, 0.0, "checking the meshes share one topology")
        names, shapes, faces = pipeline.corresponded_shapes(meshes)
        report(progress, 1.0, "meshes already in correspondence")
        return CorrespondenceResult(
            meshes=[TriMesh(x, faces, n) for x, n in zip(shapes, names)], reference_index=None,
            reference_name="(input topology)", faces=faces, residuals_mm=[None] * len(names),
            failures={}, timings={})
    return pipeline.correspond(meshes, reference=reference, n_references=n_references,
                               progress=progress)


def _corresponded(corr) -> tuple[list[str], np.ndarray]:
    """Names and (K, N, 3) vertices of the meshes that were put in correspondence."""
    pairs = [(m.name, m.vertices) for m in corr.meshes if m is not None]
    if len(pairs) < 3:
        raise ValueError(f"only {len(pairs)} meshes could be put in correspondence; a model "
                         "needs at least 3")
    return [p[0] for p in pairs], np.stack([p[1] for p in pairs])


def run_alignment(corr, method: str = "sync", transform: str = "similarity",
                  progress: ProgressCallback | None = None):
    """Stage 2 (``core.pipeline.align``): remove the pose of the corresponded shapes."""
    from core import pipeline

    _, shapes = _corresponded(corr)
    return pipeline.align(shapes, method=method, transform=transform, progress=progress)


def run_model(corr, aligned, method: str = "pca", params: dict[str, Any] | None = None,
              progress: ProgressCallback | None = None):
    """Stage 3 (``core.pipeline.fit_model``): fit the model on the aligned shapes; returns a
    ShapeModel placed in world by ``core.pipeline.world_placement``."""
    from core import pipeline

    names, shapes = _corresponded(corr)
    estimator = pipeline.fit_model(aligned.aligned, corr.faces, method=method,
                                   method_params=params, progress=progress)
    world = pipeline.world_placement(estimator.mean_, shapes,
                                     aligned.transform if aligned.method != "none" else "rigid")
    info = {"alignment": {"method": aligned.method, "transform": aligned.transform},
            "n_iter": getattr(estimator, "n_iter_", None),
            "converged": getattr(estimator, "converged_", None)}
    return estimator.to_shape_model(corr.faces, world_transform=world, source_meshes=names,
                                    info=info)


def run_evaluation(corr, aligned, methods: dict[str, dict[str, Any]],
                   progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Evaluate each method (name -> parameters) on the aligned training shapes.

    Returns ``core.evaluation.evaluate_model``'s result per method (per-shape "avg"/"max"
    errors in mm for reconstruction, generalisation, specificity, sparse reconstruction;
    compactness).
    """
    from core.evaluation import evaluate_model

    results = {}
    for i, (method, params) in enumerate(methods.items()):
        sub = sub_progress(progress, i / len(methods), (i + 1) / len(methods))
        report(sub, 0.0, f"evaluating {method}")
        results[method] = evaluate_model(method, aligned.aligned, corr.faces, params=params,
                                         progress=sub)
    return results


def evaluation_table(results: dict[str, Any]) -> tuple[list[str], dict[str, list[str]]]:
    """Column titles and, per method, the cells: factors, then mean ± SD over shapes (mm) of
    each measure's per-shape average and maximum error, then the variance explained."""
    from core.evaluation import LABELS, PER_SHAPE_MEASURES

    present = [m for m in PER_SHAPE_MEASURES if any(m in r for r in results.values())]
    columns = ["factors"]
    for name in present:
        short = LABELS[name][0]
        columns += [f"{short} avg (mm)", f"{short} max (mm)"]
    columns.append("variance explained")
    rows: dict[str, list[str]] = {}
    for method, res in results.items():
        cells = [str(res.get("n_factors", ""))]
        for name in present:
            for stat in ("avg", "max"):
                if name in res:
                    v = np.asarray(res[name][stat], dtype=np.float64)
                    cells.append(f"{v.mean():.3f} ± {v.std(ddof=1) if len(v) > 1 else 0.0:.3f}")
                else:
                    cells.append("")
        comp = res.get("compactness")
        cells.append(f"{100 * float(comp[-1]):.1f}%" if comp is not None and len(comp) else "")
        rows[method] = cells
    return columns, rows


def evaluation_figure(results: dict[str, Any]):
    """The boxplot figure of ``core.evaluation`` (matplotlib Figure, paper's Figure 4 style)."""
    from core.evaluation import plot_metrics

    return plot_metrics(results)


# ------------------------------------------------------------------------------------------
# Shapes for the training-meshes view
# ------------------------------------------------------------------------------------------


def corresponded_meshes(corr) -> list[tuple[str, np.ndarray, np.ndarray]]:
    return [(m.name, m.vertices, corr.faces) for m in corr.meshes if m is not None]


def aligned_meshes(corr, aligned) -> list[tuple[str, np.ndarray, np.ndarray]]:
    names = [m.name for m in corr.meshes if m is not None]
    return [(n, x, corr.faces) for n, x in zip(names, aligned.aligned)]
