"""Dask distributed as a runner of :func:`core.runtime.parallel.run_jobs` (Rocklin, "Dask:
parallel computation with blocked algorithms and task scheduling", SciPy 2015; the
``distributed`` scheduler): the scheduler option, the client, and the task loop.

``scheduler`` is ``"local:N"`` (a ``LocalCluster`` of N single-threaded worker processes on
this machine) or the address of a running scheduler (``tcp://host:8786``, started with
``dask scheduler``; workers with ``dask worker ADDRESS``; they must have SSM Studio installed and
see the input paths). :func:`use_scheduler` opens the client once for a whole command; jobs of
a worker that dies are rescheduled on the others by Dask itself, so the run completes.
``common`` is scattered once to the cluster. Jobs much shorter than Dask's per-task overhead
warrants go several to a task (the first are timed; :func:`dask_jobs_per_task`); long jobs
are one task each. On an interruption the outstanding futures are cancelled.
"""

from __future__ import annotations

import contextlib
import contextvars
import shutil
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from typing import Any

from core.runtime.jobs import JobError, tick

_SCHEDULER: contextvars.ContextVar = contextvars.ContextVar("ssm_studio_scheduler", default=None)

def check_scheduler(value: str | None) -> str | None:
    """Validate a ``--scheduler`` value: ``local:N`` or a scheduler address (one-line errors)."""
    if value is None:
        return None
    value = str(value).strip()
    if value.startswith("local:"):
        n = value.split(":", 1)[1]
        if not n.isdigit() or int(n) < 1:
            raise ValueError(f"--scheduler local:N needs a positive number of workers, got {value!r}")
        return value
    if not value or " " in value:
        raise ValueError(f"--scheduler expects local:N or a scheduler address like "
                         f"tcp://host:8786, got {value!r}")
    return value


def _dask_client(scheduler: str):
    """(client, the LocalCluster or None, its workers' scratch folder or None)."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ValueError("--scheduler needs Dask distributed: pip install 'ssm-studio[cluster]'") from None
    import logging

    if scheduler.startswith("local:"):
        import dask

        # no dashboard; the scheduler's HTTP server on a free port (its default 8787 may be
        # taken by another cluster, which Dask would warn about). Without a dashboard nobody
        # sees the workers' statistical profiles: their sampler thread (every 10 ms) is off
        # (it cost each idle worker about 2 % of a core, and takes the GIL from the jobs).
        # The workers' scratch space is ours, removed at the end: a worker that was killed
        # leaves its folder in Dask's shared dask-scratch-space otherwise.
        scratch = tempfile.mkdtemp(prefix="ssm-studio-dask-")
        try:
            with dask.config.set({"distributed.worker.profile.enabled": False,
                                  "temporary-directory": scratch}):  # the scheduler's too
                cluster = LocalCluster(n_workers=int(scheduler.split(":", 1)[1]),
                                       threads_per_worker=1, processes=True,
                                       dashboard_address=None, local_directory=scratch,
                                       scheduler_kwargs={"dashboard": False,
                                                         "dashboard_address": ":0"},
                                       silence_logs=logging.ERROR)
        except BaseException:
            shutil.rmtree(scratch, ignore_errors=True)
            raise
        return Client(cluster), cluster, scratch
    try:
        return Client(scheduler, timeout="10s"), None, None
    except (OSError, TimeoutError) as exc:
        raise ValueError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None


@contextlib.contextmanager
def use_scheduler(scheduler: str | None) -> Iterator[Any]:
    """Run every :func:`run_jobs` inside the block on this Dask scheduler (None: process pool).

    Opens the client (and, for ``local:N``, the LocalCluster) once, closes it at the end.
    Yields the ``distributed.Client`` (or None).
    """
    scheduler = check_scheduler(scheduler)
    if scheduler is None:
        token = _SCHEDULER.set(None)
        try:
            yield None
        finally:
            _SCHEDULER.reset(token)
        return
    client, cluster, scratch = _dask_client(scheduler)
    token = _SCHEDULER.set(client)
    try:
        yield client
    finally:
        _SCHEDULER.reset(token)
        with contextlib.suppress(Exception):
            client.close(timeout=2)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=2)
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)


def active_client():
    """The Dask client set by :func:`use_scheduler`, or None."""
    return _SCHEDULER.get()


class _JobFailed(Exception):
    """A job of a Dask task raised: which one (args: key, the job's exception)."""

    def __init__(self, key: Any, exc: BaseException):
        super().__init__(key, exc)


def _dask_batch(fn: Callable, batch: list, common: Any) -> tuple[list, float]:
    """One Dask task: the jobs of ``batch`` in order; their (key, result)s and compute seconds."""
    start = time.perf_counter()
    results = []
    for key, arg in batch:
        try:
            results.append((key, fn(arg, common)))
        except Exception as exc:
            raise _JobFailed(key, exc) from exc
    return results, time.perf_counter() - start


# Compute time one Dask task aims at. Dask's scheduler and workers spend a few milliseconds on
# every task, and a worker waits a round trip for its next one: with jobs of ~0.1 s (small
# shapes) that cost 10-15 % of the throughput. Jobs found shorter than this go several to a
# task, as Dask's best practices advise ("tasks should take longer than about 100 ms");
# longer jobs stay one per task.
DASK_TASK_SECONDS = 0.5
_MAX_JOBS_PER_TASK = 32


def dask_jobs_per_task(job_seconds: float | None, remaining: int | None, n_workers: int) -> int:
    """Jobs to put in the next Dask task: enough for :data:`DASK_TASK_SECONDS` of compute at
    ``job_seconds`` per job (one while no job has been timed), and no more than an even share
    of the ``remaining`` jobs over twice the workers, so that the last tasks stay short and
    no worker idles while another finishes a long last batch."""
    if job_seconds is None:
        return 1
    k = int(DASK_TASK_SECONDS / max(job_seconds, 1e-4))
    if remaining is not None:
        k = min(k, -(-remaining // (2 * max(n_workers, 1))))
    return max(1, min(k, _MAX_JOBS_PER_TASK))


def run_dask(client, fn: Callable[[Any, Any], Any], iterator: Iterator[tuple[Any, Any]],
             common: Any, total: int | None, progress, keep, label: str, window: int | None,
             retries: int) -> dict:
    """The jobs as tasks on ``client``'s cluster, at most ``window`` tasks (default 4 per
    worker) in flight, several short jobs to a task; results handed to ``keep`` as they
    arrive."""
    from itertools import islice

    from distributed import wait

    n_workers = max(1, len(client.scheduler_info().get("workers", {})))
    limit = max(1, int(window) if window else 4 * n_workers)
    tag = uuid.uuid4().hex[:8]
    # One future for the whole object (scattering a dict or list would scatter its items).
    common_future = (client.scatter([common], broadcast=True, hash=False)[0]
                     if common is not None else None)
    in_flight: dict = {}  # future -> keys of its jobs
    results: dict = {}
    timed = {"jobs": 0, "seconds": 0.0}
    counter = submitted = 0
    exhausted = False

    def submit_more() -> None:
        nonlocal counter, submitted, exhausted
        while not exhausted and len(in_flight) < limit:
            per_job = timed["seconds"] / timed["jobs"] if timed["jobs"] else None
            k = dask_jobs_per_task(per_job, None if total is None else total - submitted, n_workers)
            batch = list(islice(iterator, k))
            if not batch:
                exhausted = True
                return
            fut = client.submit(_dask_batch, fn, batch, common_future, pure=False,
                                key=f"ssm-{label.replace(' ', '_')}-{tag}-{counter}",
                                retries=int(retries))
            in_flight[fut] = [key for key, _ in batch]
            counter += 1
            submitted += len(batch)

    try:
        submit_more()
        while in_flight:
            # woken by the first completion (no polling delay), at least every 0.1 s so that
            # signals and the GUI's Cancel are handled promptly
            try:
                finished = wait(list(in_flight), timeout=0.1, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                finished = set()
            if not finished:
                tick(progress, len(results), total, label)  # heartbeat
                continue
            for fut in finished:
                keys = in_flight.pop(fut)
                try:
                    values, seconds = fut.result()
                except _JobFailed as failed:
                    key, exc = failed.args
                    raise JobError(key, exc) from exc
                except Exception as exc:  # e.g. the task's workers kept dying
                    raise JobError(keys[0], exc) from exc
                fut.release()
                timed["jobs"] += len(values)
                timed["seconds"] += seconds
                for key, value in values:
                    results[key] = keep(key, value)
                    tick(progress, len(results), total, label)
            submit_more()
    except BaseException:
        with contextlib.suppress(Exception):
            client.cancel(list(in_flight), force=True)
        raise
    finally:
        if common_future is not None:
            with contextlib.suppress(Exception):
                common_future.release()
    return results

