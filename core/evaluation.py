"""The standard evaluation of shape models (Bernard et al., CVPR 2016, section 3.1).

For shapes in correspondence and aligned, (K, N, 3) in mm, and a model-building method:

- reconstruction e: the model built on all K shapes projects each training shape (least-squares
  coefficients); per shape, the average and maximum per-vertex Euclidean error;
- generalisation g: leave one out -- build on the other K - 1 shapes, project the left-out one;
- specificity s: draw ``n_samples`` shapes from the full model's coefficient distribution
  N(0, diag(coef_var)); per sample, the error to the closest training shape (closest by average
  vertex distance);
- sparse reconstruction g0.05: leave one out, fit the model to a random 5% of the left-out
  shape's vertices (known correspondence) by prior-regularised least squares
  a = argmin ||Phi_S a - (y_S - mean_S)||^2 + sigma^2 sum_m a_m^2 / coef_var_m, sigma^2 the fold
  model's residual variance per coordinate on its own training shapes (floored at 1e-4 times
  the data's variance per coordinate) unless given; error over all vertices;
- compactness: cumulative fraction of the total training variance explained by the first m
  factors (projection onto the span of factors 1..m, in the model's order).

Per-shape results are "avg" and "max" arrays in mm. The leave-one-out folds run in a process
pool (``n_jobs``); the work is cancellable through the ``progress`` callback (the pool's
processes are terminated). :func:`plot_metrics` draws the paper's Figure 4 style boxplots with
matplotlib's Agg backend (no Qt), reused by the GUI.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from collections.abc import Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from core.models import make_model, model_class
from core.models.base import DeformationModel, check_shapes
from core.progress import Cancelled, ProgressCallback, report, sub_progress

MEASURES = ("reconstruction", "generalisation", "specificity", "sparse_reconstruction",
            "compactness")
PER_SHAPE_MEASURES = MEASURES[:4]
LABELS = {
    "reconstruction": ("e", "reconstruction error"),
    "generalisation": ("g", "generalisation error"),
    "specificity": ("s", "specificity error"),
    "sparse_reconstruction": ("g0.05", "sparse reconstruction error"),
}


def vertex_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Average and maximum per-vertex Euclidean distance per shape: (K,), (K,) from (K, N, 3)."""
    d = np.linalg.norm(np.asarray(estimate) - np.asarray(truth), axis=-1)
    return d.mean(axis=-1), d.max(axis=-1)


def residual_variance(model: DeformationModel, shapes: np.ndarray) -> float:
    """Mean squared residual per coordinate of the model's projection of ``shapes``."""
    rec = model.inverse_transform(model.transform(shapes))
    return float(np.mean((rec - shapes) ** 2))


def sparse_fit(model: DeformationModel, points: np.ndarray, indices: np.ndarray,
               noise_var: float) -> np.ndarray:
    """Shape (N, 3) from known vertices ``points`` (S, 3) at ``indices`` (S,) with the prior.

    Solves (Phi_S^T Phi_S + noise_var diag(1 / coef_var)) a = Phi_S^T (points - mean_S).
    """
    phi = model.factors_[:, indices, :].reshape(model.n_factors_, -1).T  # (3S, M)
    d = (points - model.mean_[indices]).reshape(-1)
    lhs = phi.T @ phi + noise_var * np.diag(1.0 / model.coef_var_)
    coef = np.linalg.solve(lhs, phi.T @ d)
    return model.inverse_transform(coef)


def compactness(model: DeformationModel, shapes: np.ndarray) -> np.ndarray:
    """Cumulative fraction (M,) of the variance of ``shapes`` about the model mean explained by
    the span of the first m factors."""
    d = (shapes - model.mean_).reshape(len(shapes), -1).T  # (3N, K)
    total = float(np.sum(d * d))
    q, r = np.linalg.qr(model.basis_)
    # Dependent factors add nothing: zero their direction.
    dependent = np.abs(np.diag(r)) <= 1e-10 * max(float(np.abs(np.diag(r)).max(initial=0)), 1e-300)
    proj = (q.T @ d) ** 2
    proj[dependent] = 0.0
    return np.cumsum(proj.sum(axis=1)) / max(total, 1e-300)


def specificity(model: DeformationModel, shapes: np.ndarray, n_samples: int,
                random_state: int | None, chunk: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Avg and max error (n_samples,) of random model instances to their closest training shape."""
    samples = model.sample(n_samples, random_state)
    avg = np.empty(n_samples)
    mx = np.empty(n_samples)
    for start in range(0, n_samples, chunk):
        s = samples[start:start + chunk]
        d = np.linalg.norm(s[:, None] - shapes[None], axis=-1)  # (c, K, N)
        mean_d = d.mean(axis=2)
        best = np.argmin(mean_d, axis=1)
        rows = np.arange(len(s))
        avg[start:start + chunk] = mean_d[rows, best]
        mx[start:start + chunk] = d[rows, best].max(axis=1)
    return avg, mx


def _fold(task: dict, progress: ProgressCallback | None = None) -> dict:
    """One leave-one-out fold: generalisation and sparse reconstruction of shape ``k``."""
    shapes, k = task["shapes"], task["k"]
    train = np.delete(shapes, k, axis=0)
    model = make_model(task["method"], **task["params"]).fit(train, task["faces"],
                                                             progress=progress)
    target = shapes[k]
    out: dict[str, Any] = {"k": k, "n_factors": model.n_factors_}
    if "generalisation" in task["measures"]:
        rec = model.inverse_transform(model.transform(target))
        a, m = vertex_errors(rec[None], target[None])
        out["generalisation"] = (float(a[0]), float(m[0]))
    if "sparse_reconstruction" in task["measures"]:
        n = shapes.shape[1]
        n_obs = max(1, int(math.ceil(task["sparse_fraction"] * n)))
        rng = np.random.default_rng([task["seed"], k])
        idx = np.sort(rng.choice(n, size=n_obs, replace=False))
        noise_var = task["noise_var"]
        if noise_var is None:
            floor = 1e-4 * float(np.mean(train.var(axis=0)))
            noise_var = max(residual_variance(model, train), floor, 1e-12)
        rec = sparse_fit(model, target[idx], idx, noise_var)
        a, m = vertex_errors(rec[None], target[None])
        out["sparse_reconstruction"] = (float(a[0]), float(m[0]))
    return out


@contextmanager
def _single_threaded_children():
    """Spawned workers inherit these: one BLAS thread each, so n_jobs processes fill n cores."""
    keys = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    saved = {key: os.environ.get(key) for key in keys}
    os.environ.update({key: "1" for key in keys})
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _run_folds(tasks: list[dict], n_jobs: int, progress: ProgressCallback | None) -> list[dict]:
    results: list[dict] = []
    if n_jobs <= 1 or len(tasks) <= 1:
        for i, task in enumerate(tasks):
            report(progress, i / len(tasks), f"leave-one-out fold {i + 1}/{len(tasks)}")
            # The fit reports too, so a cancel stops within one of its iterations.
            results.append(_fold(task, sub_progress(progress, i / len(tasks),
                                                    (i + 1) / len(tasks))))
        report(progress, 1.0, "leave-one-out done")
        return results
    ctx = mp.get_context("spawn")  # no fork from a (possibly) multi-threaded GUI process
    with _single_threaded_children():
        pool = ctx.Pool(processes=min(n_jobs, len(tasks)))
    try:
        pending = [pool.apply_async(_fold, (task,)) for task in tasks]
        while pending:
            still = []
            for job in pending:
                if job.ready():
                    results.append(job.get())  # re-raises a fold's exception here
                else:
                    still.append(job)
            pending = still
            report(progress, len(results) / len(tasks),
                   f"leave-one-out folds {len(results)}/{len(tasks)}")
            if pending:
                pending[0].wait(0.25)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()
    return sorted(results, key=lambda r: r["k"])


def evaluate_model(method: str, shapes: np.ndarray, faces: np.ndarray | None, *,
                   n_factors: int | None = None, params: dict | None = None,
                   measures: Sequence[str] = MEASURES, n_jobs: int | None = None,
                   random_state: int = 0, n_samples: int = 1000, sparse_fraction: float = 0.05,
                   noise_var: float | None = None,
                   progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Evaluate one model-building method on shapes in correspondence, aligned.

    Parameters
    ----------
    method : "pca", "lsf", "splocs" or "varimax"
    shapes : (K, N, 3) float, mm; faces : (F, 3) int (needed by lsf/splocs)
    n_factors : number of factors (None: the method's default); params : other parameters
    measures : subset of :data:`MEASURES`
    n_jobs : processes for the leave-one-out folds (None: all cores; 1: in this process)
    random_state : seed of the specificity samples and sparse vertex subsets
    n_samples : number of specificity samples
    sparse_fraction : fraction of vertices known in sparse reconstruction (0.05)
    noise_var : sigma^2 (mm^2) of the sparse fit (None: each fold model's residual variance)

    Returns
    -------
    dict with "method", "n_factors" (fitted on all shapes), "params", "units" ("mm"), for each
    per-shape measure {"avg": (K,) or (n_samples,), "max": ...}, "compactness" (M,), and
    "timings" (seconds).
    """
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
    k = len(shapes)
    out: dict[str, Any] = {"method": cls.method, "params": params, "units": "mm",
                           "n_shapes": k, "n_vertices": int(shapes.shape[1])}
    timings: dict[str, float] = {}
    needs_full = any(m in measures for m in ("reconstruction", "specificity", "compactness"))
    loo = [m for m in ("generalisation", "sparse_reconstruction") if m in measures]
    full_share = 1.0 / (k + 1) if (needs_full and loo) else (1.0 if needs_full else 0.0)
    model = None
    if needs_full or not loo:
        t0 = time.perf_counter()
        model = make_model(cls.method, **params).fit(
            shapes, faces, progress=sub_progress(progress, 0.0, full_share))
        timings["fit"] = time.perf_counter() - t0
        out["n_factors"] = model.n_factors_
        t0 = time.perf_counter()
        if "reconstruction" in measures:
            rec = model.inverse_transform(model.transform(shapes))
            a, m = vertex_errors(rec, shapes)
            out["reconstruction"] = {"avg": a, "max": m}
        if "specificity" in measures:
            a, m = specificity(model, shapes, int(n_samples), random_state)
            out["specificity"] = {"avg": a, "max": m}
        if "compactness" in measures:
            out["compactness"] = compactness(model, shapes)
        timings["measures"] = time.perf_counter() - t0
    if loo:
        t0 = time.perf_counter()
        tasks = [{"method": cls.method, "params": params, "shapes": shapes, "faces": faces,
                  "k": i, "measures": tuple(loo), "sparse_fraction": float(sparse_fraction),
                  "noise_var": noise_var, "seed": int(random_state)} for i in range(k)]
        jobs = (os.cpu_count() or 1) if n_jobs is None else int(n_jobs)
        folds = _run_folds(tasks, jobs, sub_progress(progress, full_share, 1.0))
        for name in loo:
            vals = np.array([f[name] for f in folds])
            out[name] = {"avg": vals[:, 0], "max": vals[:, 1]}
        out.setdefault("n_factors", int(np.median([f["n_factors"] for f in folds])))
        timings["leave_one_out"] = time.perf_counter() - t0
    out["timings"] = timings
    report(progress, 1.0, f"{cls.method} evaluated")
    return out


def evaluate_methods(methods: Sequence[str], shapes: np.ndarray, faces: np.ndarray | None, *,
                     n_factors: int | None = None, params: dict[str, dict] | None = None,
                     progress: ProgressCallback | None = None, **kwargs) -> dict[str, dict]:
    """:func:`evaluate_model` for several methods (same shapes, seeds and subsets)."""
    results = {}
    for i, method in enumerate(methods):
        sub = sub_progress(progress, i / len(methods), (i + 1) / len(methods))
        key = model_class(method).method
        results[key] = evaluate_model(key, shapes, faces, n_factors=n_factors,
                                      params=(params or {}).get(key), progress=sub, **kwargs)
    return results


def summary_rows(results: dict[str, dict]) -> list[dict[str, Any]]:
    """One row per method: mean over shapes of each measure's avg and max (mm), compactness."""
    rows = []
    for method, res in results.items():
        row: dict[str, Any] = {"method": method, "n_factors": res.get("n_factors")}
        for name in PER_SHAPE_MEASURES:
            if name in res:
                short = LABELS[name][0]
                row[f"{short}_avg"] = float(np.mean(res[name]["avg"]))
                row[f"{short}_max"] = float(np.mean(res[name]["max"]))
        if "compactness" in res and len(res["compactness"]):
            row["explained"] = float(res["compactness"][-1])
        rows.append(row)
    return rows


def summary_table(results: dict[str, dict]) -> str:
    """A plain-text table of :func:`summary_rows` (means over shapes, mm)."""
    rows = summary_rows(results)
    cols = ["method", "n_factors"] + [c for c in ("e_avg", "e_max", "g_avg", "g_max", "s_avg",
                                                  "s_max", "g0.05_avg", "g0.05_max", "explained")
                                      if any(c in r for r in rows)]
    lines = [" ".join(f"{c:>10}" for c in cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            cells.append(f"{v:>10.3f}" if isinstance(v, float) else f"{v!s:>10}")
        lines.append(" ".join(cells))
    return "\n".join(lines)


def to_json(results: dict[str, dict]) -> dict[str, Any]:
    """Results with numpy arrays as lists (for ``core.io.atomic_write_json``)."""
    def conv(v):
        if isinstance(v, np.ndarray):
            return v.tolist()
        if isinstance(v, np.generic):
            return v.item()
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v
    return {"units": "mm", "methods": conv(results), "summary": summary_rows(results)}


def plot_metrics(results: dict[str, dict], path: str | os.PathLike | None = None,
                 title: str | None = None):
    """Boxplots like Figure 4 of the paper: one panel per measure (avg top row, max bottom),
    plus the compactness curves. Uses the Agg canvas (no pyplot, no Qt); saves to ``path``
    (atomically) if given. Returns the matplotlib Figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    methods = list(results)
    present = [m for m in PER_SHAPE_MEASURES if any(m in r for r in results.values())]
    has_comp = any("compactness" in r for r in results.values())
    ncols = len(present) + (1 if has_comp else 0)
    fig = Figure(figsize=(3.2 * max(ncols, 1), 6.0), constrained_layout=True)
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, max(ncols, 1), squeeze=False)
    for col, name in enumerate(present):
        short, long = LABELS[name]
        for row, stat in enumerate(("avg", "max")):
            ax = axes[row, col]
            data = [np.asarray(results[m][name][stat]) if name in results[m] else np.array([])
                    for m in methods]
            key = "tick_labels" if _has_tick_labels() else "labels"
            ax.boxplot(data, **{key: methods})
            ax.set_ylabel(f"{short} {stat} [mm]")
            if row == 0:
                ax.set_title(long)
            ax.tick_params(axis="x", labelrotation=45)
            ax.grid(axis="y", alpha=0.3)
    if has_comp:
        ax = axes[0, ncols - 1]
        for m in methods:
            if "compactness" in results[m]:
                c = np.asarray(results[m]["compactness"])
                ax.plot(np.arange(1, len(c) + 1), c, label=m)
        ax.set_xlabel("number of factors")
        ax.set_ylabel("cumulative variance explained")
        ax.set_title("compactness")
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize="small")
        ax.grid(alpha=0.3)
        axes[1, ncols - 1].axis("off")
    if title:
        fig.suptitle(title)
    if path is not None:
        from core.io import atomic_path

        with atomic_path(path) as tmp:
            fig.savefig(str(tmp), dpi=110, format=os.path.splitext(str(path))[1][1:] or "png")
    return fig


def _has_tick_labels() -> bool:
    import matplotlib

    major, minor = (int(x) for x in matplotlib.__version__.split(".")[:2])
    return (major, minor) >= (3, 9)


__all__ = ["MEASURES", "evaluate_model", "evaluate_methods", "vertex_errors", "sparse_fit",
           "compactness", "specificity", "summary_rows", "summary_table", "to_json",
           "plot_metrics", "Cancelled"]
