"""The model builder's Qt-free helpers: loading the mesh list, the estimator classes for the
parameter forms, and the evaluation table's cells.

The build itself (correspond -> align -> fit model, cached stage by stage) is
:mod:`core.build.stages`; the functions here that run in an :class:`app.workers.Worker` take plain
data, return plain data and report ``progress(fraction, message)``.
"""

from __future__ import annotations

import inspect
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.build.pipeline import ALIGN_METHODS, TRANSFORMS
from core.build.stages import DEFAULT_N_REFERENCES, NO_CORRESPONDENCE
from core.geometry.mesh import surface_problems
from core.io import TriMesh, load_meshes
from core.models import MODELS
from core.runtime.progress import ProgressCallback

__all__ = ["ALIGN_METHODS", "TRANSFORMS", "NO_CORRESPONDENCE", "MeshEntry", "load_entries",
           "model_classes", "method_summary", "default_n_references", "evaluation_table",
           "label_maps_available", "load_label_entries",
           "evaluation_figure"]

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


def label_maps_available() -> bool:
    """Whether ``core.correspondence.mesh_labels`` (label maps -> surfaces) is installed."""
    import importlib.util

    return importlib.util.find_spec("core.correspondence.mesh_labels") is not None


def load_label_entries(files: list[str | os.PathLike], label: str | int,
                       n_vertices: int | None = 2000,
                       progress: ProgressCallback | None = None) -> list[MeshEntry]:
    """One label of each label map as a training mesh (core.correspondence.mesh_labels); errors per file
    (a missing or empty label names the file and the label; the other files still load)."""
    from core.correspondence.mesh_labels import label_map_surfaces

    entries = []
    for path, mesh, error in label_map_surfaces(files, label, n_vertices=n_vertices,
                                                progress=progress):
        if mesh is None:
            entries.append(MeshEntry(path, Path(path).name, None, [error], included=False))
        else:
            entries.append(MeshEntry(path, mesh.name, mesh,
                                     surface_problems(mesh.vertices, mesh.faces)))
    return entries


# ------------------------------------------------------------------------------------------
# Model classes (for the parameter forms)
# ------------------------------------------------------------------------------------------


def model_classes() -> dict[str, type]:
    """Model-building estimator classes by method name, in the order PCA, LSF, SPLOCS, Varimax."""
    return {name: MODELS[name] for name in sorted(MODELS, key=_model_rank)}


def _model_rank(name: str) -> int:
    return MODEL_ORDER.index(name) if name in MODEL_ORDER else len(MODEL_ORDER)


def method_summary(cls: type) -> str:
    """First paragraph of a class docstring (for tooltips)."""
    doc = inspect.getdoc(cls) or cls.__name__
    return doc.split("\n\n")[0].replace("\n", " ")


def default_n_references() -> int:
    """``establish_correspondence``'s default number of candidate references (read from
    ``core.build.stages`` so that opening the builder does not import the correspondence engine and
    scipy.optimize, ~1.8 s; a test keeps the two equal)."""
    return DEFAULT_N_REFERENCES


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
