"""The per-shape correspondence jobs of a training-set run, in this process or a worker pool.

Every stage of the batch (:mod:`core.correspondence.batch`: the reference-based pass of
Bernard et al., SPIE MI 2016, the checks, the groupwise refinement passes after Heimann &
Meinzer, Medical Image Analysis 2009) corresponds shapes one at a time with
:func:`core.correspondence.pair.correspond_pair`; shapes are independent, so the jobs run
in a process pool or on Dask (:func:`core.runtime.parallel.run_jobs`). A task names its
reference by a key, and the reference's arrays are sent once per worker, not once per task.
Also here: the similarity GPA mean the stages correspond to (Gower, Psychometrika 1975, one
shape at a time, :func:`core.alignment.transforms.procrustes_mean`) and the per-shape timing
tally.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from core.alignment.transforms import apply_transform, fit_transform
from core.correspondence.pair import correspond_pair
from core.correspondence.store import VertexRows, open_mesh, open_rows
from core.runtime.failures import describe_failure
from core.runtime.parallel import run_jobs, runs_inline
from core.runtime.progress import ProgressCallback, report, sub_progress
from core.types import TriMesh


def correspond_task(args: tuple) -> tuple:
    """(key, ref_v, ref_f, tgt_v, tgt_f, params, parallel[, posed]) -> (key, result or None,
    error or None): one :func:`~core.correspondence.pair.correspond_pair`, its failure
    reported rather than raised."""
    key, ref_v, ref_f, tgt_v, tgt_f, params, parallel, *rest = args
    try:
        out = correspond_pair(TriMesh(ref_v, ref_f), TriMesh(tgt_v, tgt_f), params, parallel,
                              posed=rest[0] if rest else None)
        return key, out, None
    except Exception as exc:  # reported per shape, the batch goes on; a bug with its traceback
        return key, None, describe_failure(exc)


def task_job(task: tuple, references: dict) -> tuple:
    """core.runtime.parallel job: one correspondence task whose reference arrays come from
    ``references`` (sent once per worker) -> (result or None, error or None).

    The target is a handle (:func:`core.correspondence.store.open_mesh`: the mesh itself, or
    a file the worker reads). A refinement task carries the shape's current correspondence
    (a handle too, :func:`~core.correspondence.store.open_rows`) instead of the posed mean:
    the worker poses the mean on it (core.alignment.transforms.fit_transform), as the client did before.
    """
    key, _, _, target, _, params, parallel, *rest = task
    ref_v, ref_f = references[key[0]]
    mesh = open_mesh(target)
    extra: tuple = ()
    if rest:
        current = open_rows(rest[0])
        # Affine for the offsets' fit (whose own pose refines it), similarity for CPD.
        how = "affine" if params["deformation"] == "normal_offsets" else "similarity"
        extra = (apply_transform(fit_transform(ref_v, current, how), ref_v),)
    _, out, err = correspond_task((key, ref_v, ref_f, mesh.vertices, mesh.faces, params, parallel,
                                   *extra))
    return out, err


def run_tasks(tasks: list[tuple], n_jobs: int, progress: ProgressCallback | None,
              start: float, stop: float, on_result: Callable | None = None) -> dict:
    """Run correspondence tasks in this process or through :func:`core.runtime.parallel.run_jobs`
    (process pool, or Dask inside :func:`core.runtime.parallel.use_scheduler`); cancellable via
    progress. ``on_result(key, (out, err))`` sees each result as it arrives (streaming);
    what it returns, if not None, is kept instead of the result (a summary: the client then
    holds no vertices).

    A task is :func:`task_job`'s argument; its ``parallel`` flag (index 6) is set here:
    rustcpd's own threads only when running in this process. The reference of every task is
    sent once per worker, not once per task.
    """
    results: dict[Any, Any] = {}
    total = len(tasks)
    if total == 0:
        return results
    references = {t[0][0]: (t[1], t[2]) for t in tasks}
    keep = (lambda key, value: value) if on_result is None else (
        lambda key, value: _or(on_result(key, value), value))
    if runs_inline(n_jobs, total):
        for done, t in enumerate(tasks):
            report(progress, start + (stop - start) * done / total, f"corresponding {done + 1}/{total}")
            results[t[0]] = keep(t[0], task_job(t[:6] + (True,) + t[7:], references))
        report(progress, stop, "correspondence done")
        return results
    items = [(t[0], (t[0], None, None) + t[3:6] + (False,) + t[7:]) for t in tasks]
    results = run_jobs(task_job, items, common=references, n_jobs=n_jobs, on_result=keep,
                       progress=sub_progress(progress, start, stop), label="corresponding")
    report(progress, stop, "correspondence done")
    return results


def _or(value: Any, default: Any) -> Any:
    return default if value is None else value


def make_tasks(reference: TriMesh, ref_key: Any, targets: dict, params: dict,
               current: dict | None = None) -> list[tuple]:
    """Tasks corresponding ``reference`` to each target (a mesh handle); with ``current``
    (shape -> handle of its current correspondence) the reference is posed on each shape."""
    ref_v, ref_f = np.asarray(reference.vertices, float), np.asarray(reference.faces)
    return [((ref_key, i), ref_v, ref_f, handle, None, params, False)
            + ((current[i],) if current is not None else ())
            for i, handle in targets.items()]


def add_timings(timings: dict, key: int, out: dict) -> None:
    """Tally one correspondence's seconds into the run's ``timings`` (per shape and in all)."""
    per = timings.setdefault("_per_shape", {})
    per[key] = per.get(key, 0.0) + float(out["timings"]["total"])
    timings["assignment_total"] = timings.get("assignment_total", 0.0) + out["timings"]["assignment"]
    timings["cpu_total"] = timings.get("cpu_total", 0.0) + out["timings"]["total"]
    timings["n_registrations"] = timings.get("n_registrations", 0) + 1


def spread_pick(keys: Sequence[int], n: int) -> list[int]:
    """At most ``n`` of ``keys``, evenly spread over them (deterministic)."""
    keys = list(keys)
    if len(keys) <= n:
        return keys
    return [keys[j] for j in np.unique(np.linspace(0, len(keys) - 1, n).round().astype(int))]


def gpa(vertices: Mapping, keys: list[int], tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(mean, per-shape rmsd) of the similarity GPA of ``vertices[k]`` over ``keys`` (20
    iterations at most), one shape at a time (``vertices`` in memory or a vertex store)."""
    from core.alignment.transforms import procrustes_mean

    return procrustes_mean(vertices, keys, "similarity", max_iter=20, tol=tol)


def vertex_handle(vertices: Mapping, key: int) -> Any:
    """What a job needs to read ``vertices[key]`` (the array, or a row of a vertex store)."""
    return vertices.handle(key) if isinstance(vertices, VertexRows) else vertices[key]
