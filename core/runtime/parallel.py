"""The one executor for independent jobs: per-shape correspondence, per-fold evaluation, per-pair
image registration. A job list runs in a local process pool (default,
:mod:`core.runtime.pool`) or, with a scheduler, as Dask tasks on a Dask distributed cluster
(:mod:`core.runtime.cluster`) -- the same call, the same results, byte for byte, as in this
process (:func:`core.runtime.jobs.run_inline`).

:func:`run_jobs` calls ``fn(arg, common)`` for every ``(key, arg)`` item:

- ``common`` (e.g. the reference mesh, or the training shapes of all folds) is sent once per
  worker process -- through the pool's initialiser, or scattered once to the Dask cluster --
  not once per job;
- jobs are submitted through a bounded window (a few per worker), and every result is handed
  to ``on_result(key, result)`` as soon as it arrives, so a caller can write it and keep only a
  summary: memory on the client stays flat in the number of jobs;
- ``progress(fraction, message)`` follows completed jobs (and is called every 0.1 s while
  waiting, a heartbeat); raising :class:`core.runtime.progress.Cancelled` from it (the GUI's
  Cancel) stops everything, also while the workers are still starting.

Interruption (issue 18 item 14; :mod:`core.runtime.signals`): SIGTERM raises
:class:`Terminated`, SIGINT ``KeyboardInterrupt``, within a fraction of a second of the
executor's short waits; the pool's workers are then killed, outstanding Dask futures are
cancelled, and the exception propagates to the command, which writes what completed and
exits 130 (SIGINT) or 143 (SIGTERM).

This module is the package's face: the names callers use are importable from here.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from core.runtime.cluster import (
    DASK_TASK_SECONDS,
    active_client,
    check_scheduler,
    dask_jobs_per_task,
    run_dask,
    use_scheduler,
)
from core.runtime.jobs import JobError, run_inline
from core.runtime.pool import (
    descendants,
    die_with_parent,
    preload_in_workers,
    run_pool,
    single_threaded_children,
)
from core.runtime.progress import ProgressCallback
from core.runtime.signals import (
    Terminated,
    raise_if_signalled,
    signals_deferred,
    termination_signals,
)

__all__ = [
    "DASK_TASK_SECONDS", "JobError", "Terminated", "active_client", "check_scheduler",
    "dask_jobs_per_task", "descendants", "die_with_parent", "preload_in_workers",
    "raise_if_signalled", "resolve_jobs", "run_jobs", "runs_inline", "signals_deferred",
    "single_threaded_children", "termination_signals", "use_scheduler",
]


def resolve_jobs(n_jobs: int | None) -> int:
    """Worker processes for a pool: ``n_jobs`` or the CPU count."""
    return max(1, int(n_jobs)) if n_jobs is not None else (os.cpu_count() or 1)


def runs_inline(n_jobs: int | None, n_items: int) -> bool:
    """Whether :func:`run_jobs` would run in this process (no scheduler, one job or one core)."""
    return active_client() is None and (resolve_jobs(n_jobs) <= 1 or n_items <= 1)


def run_jobs(fn: Callable[[Any, Any], Any], items: Iterable[tuple[Any, Any]], *,
             common: Any = None, n_jobs: int | None = None, total: int | None = None,
             progress: ProgressCallback | None = None,
             on_result: Callable[[Any, Any], Any] | None = None, label: str = "jobs",
             scheduler: str | None = None, window: int | None = None,
             retries: int = 0) -> dict[Any, Any]:
    """Run ``fn(arg, common)`` for every ``(key, arg)`` of ``items``; results by key.

    Parameters
    ----------
    fn : module-level callable (picklable)
    items : iterable of (key, arg); consumed lazily through the submission window.
    common : sent once per worker; ``fn`` receives it as its second argument.
    n_jobs : pool processes (None: CPU count; 1 runs here, in order). Ignored on Dask.
    total : number of items when ``items`` has no ``len``, for progress.
    progress : ``progress(fraction, message)`` after every completed job; may raise
        ``Cancelled`` to stop.
    on_result : called in this process as each result arrives; what it returns is stored
        instead of the result (return a small summary to keep memory flat).
    label : word for the progress messages.
    scheduler : ``local:N`` or an address; default: the one of the enclosing
        :func:`use_scheduler`, else the process pool.
    window : jobs (on Dask: tasks) in flight at once (default 4 per worker). On Dask, jobs
        measured shorter than :data:`DASK_TASK_SECONDS` go several to a task
        (:func:`dask_jobs_per_task`); each result is still handed over by itself.
    retries : Dask only: times a job that *raised* is retried (a job on a worker that died
        is always rescheduled by Dask).

    Raises
    ------
    JobError
        A job raised (the others are stopped).
    KeyboardInterrupt, Terminated, Cancelled
        Propagated after the workers are stopped.
    """
    if total is None and isinstance(items, Sequence):
        total = len(items)
    iterator = iter(items)
    keep = on_result if on_result is not None else (lambda key, result: result)
    if scheduler is not None:
        with use_scheduler(scheduler) as client:
            return run_dask(client, fn, iterator, common, total, progress, keep, label,
                            window, retries)
    client = active_client()
    if client is not None:
        return run_dask(client, fn, iterator, common, total, progress, keep, label, window, retries)
    n = resolve_jobs(n_jobs)
    if n <= 1 or (total is not None and total <= 1):
        return run_inline(fn, iterator, common, total, progress, keep, label)
    return run_pool(fn, iterator, common, n if total is None else min(n, total), total,
                    progress, keep, label, window)

