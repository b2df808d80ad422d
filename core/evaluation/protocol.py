"""The evaluation protocol of Bernard et al. (CVPR 2016, section 3.1): which model is fitted on
which shapes, and the leave-one-out folds (run in a process pool, cancellable).

- Reconstruction, specificity and compactness use the model built on all K shapes.
- Generalisation and sparse reconstruction leave each shape out in turn and build the model on
  the other K - 1. How a fold gets its shapes is the ``folds`` argument:

  - ``None`` (*fixed*): the shapes as given, aligned (and corresponded) once with all K shapes
    -- the left-out shape took part in the alignment and correspondence, which flatters
    generalisation a little;
  - :class:`Realign` (*true leave-one-out*): each fold aligns its K - 1 training shapes afresh
    (same method and transform class as the full model) and brings the left-out shape into the
    fold's frame by the least-squares transform onto the fold mean;
  - :class:`Recorrespond`: each fold also re-runs correspondence on its K - 1 raw meshes (with a
    reference among them) and corresponds the left-out mesh to that reference, then aligns as
    :class:`Realign` does.

- Sparse reconstruction fits the left-out shape from a random ``sparse_fraction`` of its
  vertices with the prior; sigma^2 is each fold model's residual variance per coordinate on its
  training shapes (floored at 1e-4 times the data's variance per coordinate), or, with
  ``noise_var`` given, the same fixed value for every method and fold (methods compared with
  the same regularisation).

Per-shape results are "avg" and "max" arrays in mm; the result records the protocol used.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.evaluation.measures import (
    compactness,
    reconstruction_errors,
    residual_variance,
    sparse_fit,
    specificity,
    vertex_errors,
)
from core.models import make_model, model_class
from core.models.base import check_shapes
from core.runtime.parallel import JobError, preload_in_workers, run_jobs, runs_inline
from core.runtime.progress import ProgressCallback, report, sub_progress

MEASURES = ("reconstruction", "generalisation", "specificity", "sparse_reconstruction",
            "compactness")
LEAVE_ONE_OUT = ("generalisation", "sparse_reconstruction")
preload_in_workers(__name__)  # fold jobs: workers start with this module imported


# ------------------------------------------------------------------------------------------
# Fold preparation
# ------------------------------------------------------------------------------------------


def _align_fold(train: np.ndarray, test: np.ndarray, method: str, transform: str
                ) -> tuple[np.ndarray, np.ndarray]:
    """Align the training shapes among themselves, then the left-out one onto their mean."""
    from core.alignment.transforms import apply_transform, fit_transform
    from core.build.pipeline import align

    fold = align(train, method=method, transform=transform)
    cls = transform if method != "none" else "rigid"
    return fold.aligned, apply_transform(fit_transform(test, fold.mean, cls), test)


@dataclass
class Realign:
    """True leave-one-out folds: corresponded but unaligned shapes (K, N, 3), aligned per fold
    by ``core.build.pipeline.align(method, transform)``."""

    shapes: np.ndarray
    faces: np.ndarray | None = None
    method: str = "sync"
    transform: str = "similarity"
    name: str = field(default="realign", init=False)

    def prepare(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(training shapes (K-1, N, 3), left-out shape (N, 3), faces) of fold ``k``."""
        train = np.delete(np.asarray(self.shapes, dtype=np.float64), k, axis=0)
        aligned, test = _align_fold(train, np.asarray(self.shapes[k], dtype=np.float64),
                                    self.method, self.transform)
        return aligned, test, self.faces


@dataclass
class Recorrespond:
    """True leave-one-out folds from raw meshes: correspondence and alignment per fold.

    ``meshes`` : list of TriMesh (any topology); ``reference`` : index of the reference mesh
    (a fold leaving it out uses the next mesh); ``cpd_params`` : correspondence options.
    """

    meshes: list
    reference: int = 0
    method: str = "sync"
    transform: str = "similarity"
    cpd_params: dict = field(default_factory=dict)
    name: str = field(default="recorrespond", init=False)

    def prepare(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        from core.build.pipeline import corresponded_shapes
        from core.correspondence import correspond_pair, establish_correspondence

        train = [m for i, m in enumerate(self.meshes) if i != k]
        # the reference's index among the K - 1 training meshes (the first one if left out)
        ref = 0 if self.reference == k else self.reference - int(self.reference > k)
        corr = establish_correspondence(train, reference=ref, n_jobs=1, **self.cpd_params)
        _, shapes, faces = corresponded_shapes([m for m in corr.meshes if m is not None])
        test = correspond_pair(train[ref], self.meshes[k], self.cpd_params or None,
                               parallel=False)["vertices"]
        aligned, test = _align_fold(shapes, np.asarray(test, dtype=np.float64), self.method,
                                    self.transform)
        return aligned, test, faces


# ------------------------------------------------------------------------------------------
# One fold, and the pool
# ------------------------------------------------------------------------------------------


def _sparse_indices(n: int, fraction: float, seed: int, k: int) -> np.ndarray:
    rng = np.random.default_rng([seed, k])
    return np.sort(rng.choice(n, size=max(1, int(math.ceil(fraction * n))), replace=False))


def _fold(task: dict, progress: ProgressCallback | None = None) -> dict:
    """One leave-one-out fold: generalisation and sparse reconstruction of shape ``k``."""
    k, source = task["k"], task["folds"]
    if source is None:
        train, target, faces = np.delete(task["shapes"], k, axis=0), task["shapes"][k], \
            task["faces"]
    else:
        train, target, faces = source.prepare(k)
    model = make_model(task["method"], connectivity=faces, **task["params"]).fit(
        train, progress=progress)
    out: dict[str, Any] = {"k": k, "n_factors": model.n_factors_}
    if "generalisation" in task["measures"]:
        a, m = reconstruction_errors(model, target[None])
        out["generalisation"] = (float(a[0]), float(m[0]))
    if "sparse_reconstruction" in task["measures"]:
        idx = _sparse_indices(len(target), task["sparse_fraction"], task["seed"], k)
        noise_var = task["noise_var"]
        if noise_var is None:
            floor = 1e-4 * float(np.mean(train.var(axis=0)))
            noise_var = max(residual_variance(model, train), floor, 1e-12)
        a, m = vertex_errors(sparse_fit(model, target[idx], idx, noise_var)[None], target[None])
        out["sparse_reconstruction"] = (float(a[0]), float(m[0]))
    return out


def _run_serial(tasks: list[dict], progress: ProgressCallback | None) -> list[dict]:
    results = []
    for i, task in enumerate(tasks):
        report(progress, i / len(tasks), f"leave-one-out fold {i + 1}/{len(tasks)}")
        # The fit reports too, so a cancel stops within one of its iterations.
        results.append(_fold(task, sub_progress(progress, i / len(tasks), (i + 1) / len(tasks))))
    report(progress, 1.0, "leave-one-out done")
    return results


def _fold_job(task: dict, common: dict) -> dict:
    """core.runtime.parallel job: one fold; the shapes, faces and fold source come once per worker."""
    return _fold({**task, **common})


def _run_folds(tasks: list[dict], n_jobs: int, progress: ProgressCallback | None) -> list[dict]:
    """The folds in this process, or through :func:`core.runtime.parallel.run_jobs` (process pool, or
    Dask inside :func:`core.runtime.parallel.use_scheduler`); the data every fold shares is sent once."""
    if runs_inline(n_jobs, len(tasks)):
        return _run_serial(tasks, progress)
    common = {key: tasks[0][key] for key in ("shapes", "faces", "folds")}
    slim = [(t["k"], {k: v for k, v in t.items() if k not in common}) for t in tasks]
    try:
        done = run_jobs(_fold_job, slim, common=common, n_jobs=n_jobs, progress=progress,
                        label="leave-one-out folds")
    except JobError as exc:  # a fold's own exception, as when it runs here
        raise (exc.__cause__ or exc) from None
    return [done[k] for k in sorted(done)]


# ------------------------------------------------------------------------------------------
# Evaluation of one method, and of several
# ------------------------------------------------------------------------------------------


def _check_arguments(method: str, shapes, measures, sparse_fraction, params, n_factors):
    shapes = check_shapes(shapes, "shapes", min_shapes=3)
    unknown = sorted(set(measures) - set(MEASURES))
    if unknown:
        raise ValueError(f"unknown measure(s) {', '.join(unknown)} (use {', '.join(MEASURES)})")
    if not 0 < sparse_fraction <= 1:
        raise ValueError(f"sparse_fraction must be in (0, 1]; got {sparse_fraction}")
    cls = model_class(method)
    params = dict(params or {})
    if n_factors is not None:
        params["n_factors"] = int(n_factors)
    make_model(cls.method, **params)  # validates names early, before any process starts
    return shapes, cls.method, params


def _full_model_measures(out: dict, method: str, shapes, faces, params, measures, n_samples,
                         random_state, progress) -> None:
    t0 = time.perf_counter()
    model = make_model(method, connectivity=faces, **params).fit(shapes, progress=progress)
    out["timings"]["fit"] = time.perf_counter() - t0
    out["n_factors"] = model.n_factors_
    t0 = time.perf_counter()
    if "reconstruction" in measures:
        a, m = reconstruction_errors(model, shapes)
        out["reconstruction"] = {"avg": a, "max": m}
    if "specificity" in measures:
        # Reported at the end of this share: the fit filled it; these calls are cancel points.
        a, m = specificity(model, shapes, int(n_samples), random_state,
                           progress=lambda fraction, msg: report(progress, 1.0, msg))
        out["specificity"] = {"avg": a, "max": m}
    if "compactness" in measures:
        out["compactness"] = compactness(model, shapes)
    out["timings"]["measures"] = time.perf_counter() - t0


def evaluate_model(method: str, shapes: np.ndarray, faces: np.ndarray | None, *,
                   n_factors: int | None = None, params: dict | None = None,
                   measures: Sequence[str] = MEASURES, n_jobs: int | None = None,
                   random_state: int = 0, n_samples: int = 1000, sparse_fraction: float = 0.05,
                   noise_var: float | None = None, folds: Realign | Recorrespond | None = None,
                   progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Evaluate one model-building method on shapes in correspondence, aligned.

    Parameters
    ----------
    method : "pca", "lsf", "splocs" or "varimax"
    shapes : (K, N, 3) float, mm, corresponded and aligned (the full model's training set)
    faces : (F, 3) int, the mesh (the estimators' connectivity; needed by lsf/splocs)
    n_factors : number of factors (None: the method's default); params : other parameters
    measures : subset of :data:`MEASURES`
    n_jobs : processes for the leave-one-out folds (None: all cores; 1: in this process)
    random_state : seed of the specificity samples and sparse vertex subsets
    n_samples : number of specificity samples
    sparse_fraction : fraction of vertices known in sparse reconstruction (0.05)
    noise_var : sigma^2 (mm^2) of the sparse fit, the same for every method and fold (None:
        each fold model's residual variance)
    folds : None (leave-one-out on ``shapes`` as given), :class:`Realign` or
        :class:`Recorrespond` (true leave-one-out: see the module docstring)

    Returns
    -------
    dict with "method", "n_factors" (fitted on all shapes), "params", "units" ("mm"),
    "protocol" (leave-one-out, sparse noise), for each per-shape measure {"avg": (K,) or
    (n_samples,), "max": ...}, "compactness" (M,), and "timings" (seconds).
    """
    shapes, method, params = _check_arguments(method, shapes, measures, sparse_fraction, params,
                                              n_factors)
    k = len(shapes)
    out: dict[str, Any] = {"method": method, "params": params, "units": "mm", "n_shapes": k,
                           "n_vertices": int(shapes.shape[1]), "timings": {},
                           "protocol": {"leave_one_out": "fixed" if folds is None else folds.name,
                                        "sparse_noise_var": noise_var,
                                        "specificity_covariance": "full"}}
    loo = [m for m in LEAVE_ONE_OUT if m in measures]
    full = [m for m in measures if m not in LEAVE_ONE_OUT]
    full_share = 1.0 / (k + 1) if (full and loo) else (1.0 if full else 0.0)
    if full or not loo:
        _full_model_measures(out, method, shapes, faces, params, full, n_samples, random_state,
                             sub_progress(progress, 0.0, full_share))
    if loo:
        t0 = time.perf_counter()
        tasks = [{"method": method, "params": params, "shapes": shapes, "faces": faces,
                  "k": i, "measures": tuple(loo), "sparse_fraction": float(sparse_fraction),
                  "noise_var": noise_var, "seed": int(random_state), "folds": folds}
                 for i in range(k)]
        jobs = (os.cpu_count() or 1) if n_jobs is None else int(n_jobs)
        results = _run_folds(tasks, jobs, sub_progress(progress, full_share, 1.0))
        for name in loo:
            vals = np.array([f[name] for f in results])
            out[name] = {"avg": vals[:, 0], "max": vals[:, 1]}
        out.setdefault("n_factors", int(np.median([f["n_factors"] for f in results])))
        out["timings"]["leave_one_out"] = time.perf_counter() - t0
    report(progress, 1.0, f"{method} evaluated")
    return out


def evaluate_methods(methods: Sequence[str], shapes: np.ndarray, faces: np.ndarray | None, *,
                     n_factors: int | None = None, params: dict[str, dict] | None = None,
                     progress: ProgressCallback | None = None, **kwargs) -> dict[str, dict]:
    """:func:`evaluate_model` for several methods (same shapes, seeds, subsets and folds)."""
    results = {}
    for i, method in enumerate(methods):
        sub = sub_progress(progress, i / len(methods), (i + 1) / len(methods))
        key = model_class(method).method
        results[key] = evaluate_model(key, shapes, faces, n_factors=n_factors,
                                      params=(params or {}).get(key), progress=sub, **kwargs)
    return results


__all__ = ["MEASURES", "LEAVE_ONE_OUT", "Realign", "Recorrespond", "evaluate_model",
           "evaluate_methods"]
