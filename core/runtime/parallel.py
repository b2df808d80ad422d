"""The one executor for independent jobs: per-shape correspondence, per-fold evaluation, per-pair
image registration. A job list runs in a local process pool (default) or, with a scheduler, as
Dask tasks on a Dask distributed cluster (Rocklin, "Dask: parallel computation with blocked
algorithms and task scheduling", SciPy 2015; the ``distributed`` scheduler) -- the same call,
the same results.

:func:`run_jobs` calls ``fn(arg, common)`` for every ``(key, arg)`` item:

- ``common`` (e.g. the reference mesh, or the training shapes of all folds) is sent once per
  worker process -- through the pool's initialiser, or scattered once to the Dask cluster --
  not once per job;
- jobs are submitted through a bounded window (a few per worker), and every result is handed
  to ``on_result(key, result)`` as soon as it arrives, so a caller can write it and keep only a
  summary: memory on the client stays flat in the number of jobs;
- ``progress(fraction, message)`` follows completed jobs (and is called every 0.1 s while
  waiting, a heartbeat); raising :class:`core.runtime.progress.Cancelled` from it (the GUI's Cancel)
  stops everything, also while the workers are still starting.

Interruption (issue 18 item 14). :func:`termination_signals` (installed by the command line for
every command) turns SIGTERM into :class:`Terminated`, as Python already turns SIGINT into
``KeyboardInterrupt``. The executor's waits are short timeouts, so either exception surfaces
within a fraction of a second; the pool's workers are then terminated (and ignore SIGINT
themselves, so a Ctrl-C to the terminal's process group does not spray tracebacks), outstanding
Dask futures are cancelled, and the exception propagates to the command, which writes what
completed and exits 130 (SIGINT) or 143 (SIGTERM). On Linux, pool workers also ask the kernel
for SIGTERM when their parent dies (``PR_SET_PDEATHSIG``), and so does the fork server they
are forked from (it dies with the process that started it), so even a SIGKILLed command
leaves no worker computing and no idle server behind.

Dask. ``scheduler`` is ``"local:N"`` (a ``LocalCluster`` of N single-threaded worker processes
on this machine) or the address of a running scheduler (``tcp://host:8786``, started with
``dask scheduler``; workers with ``dask worker ADDRESS``; they must have SSM Studio installed and
see the input paths). :func:`use_scheduler` opens the client once for a whole command; jobs of
a worker that dies are rescheduled on the others by Dask itself, so the run completes.
Jobs much shorter than Dask's per-task overhead warrants go several to a task (the first are
timed); long jobs are one task each.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import signal
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

from core.runtime.progress import ProgressCallback, report

_SCHEDULER: contextvars.ContextVar = contextvars.ContextVar("ssm_studio_scheduler", default=None)
_COMMON: Any = None  # a pool worker's copy of ``common``
_WORKER_MODULES: list[str] = []  # imported once by the fork server (see preload_in_workers)
# pid of the process that starts the fork server (inherited by the server through its
# environment: the server and the processes it forks only ever import this module once)
_SERVER_CLIENT_ENV = "SSM_STUDIO_POOL_CLIENT"


class Terminated(BaseException):
    """Raised in the main thread when the process receives SIGTERM (exit code 128 + 15)."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(f"terminated by signal {signum}")
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


_DEFERRED: list[int] | None = None  # signals held back by signals_deferred, or None
# The signal received under termination_signals. It stays set: a raise that got swallowed
# (Python ignores exceptions raised in a destructor, where a signal can land) is raised again
# by the executor's next wait.
_SIGNALLED: int | None = None


def _raise_for(signum: int) -> None:
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise Terminated(signum)


def _on_signal(signum, frame) -> None:
    global _SIGNALLED
    _SIGNALLED = signum
    if _DEFERRED is not None:  # inside a critical section: raise when it ends
        _DEFERRED.append(signum)
        return
    _raise_for(signum)


@contextlib.contextmanager
def termination_signals() -> Iterator[None]:
    """While active, SIGTERM raises :class:`Terminated` in the main thread and SIGINT
    ``KeyboardInterrupt`` (also when the process started with SIGINT ignored, as a shell's
    background job does). A no-op outside the main thread; a SIGINT handler someone else
    installed (e.g. a GUI's) is left alone."""
    global _SIGNALLED
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous_signalled = _SIGNALLED
    previous_term = signal.signal(signal.SIGTERM, _on_signal)
    previous_int = signal.getsignal(signal.SIGINT)
    ours_int = previous_int in (signal.SIG_IGN, signal.SIG_DFL, None, signal.default_int_handler)
    if ours_int:
        signal.signal(signal.SIGINT, _on_signal)
    try:
        yield
    finally:
        _SIGNALLED = previous_signalled
        signal.signal(signal.SIGTERM, previous_term)
        if ours_int:
            signal.signal(signal.SIGINT, previous_int if previous_int is not None else signal.SIG_DFL)


def raise_if_signalled() -> None:
    """Raise ``KeyboardInterrupt``/:class:`Terminated` again if a signal arrived under
    :func:`termination_signals` (its first raise may have been swallowed)."""
    if _SIGNALLED is not None:
        _raise_for(_SIGNALLED)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT/SIGTERM (as installed by :func:`termination_signals`) back until the block
    ends, for steps that must not be cut in half: starting a worker process (one started but
    not yet registered could not be stopped, and would print a traceback on its own), or
    writing an output and recording that it was written."""
    global _DEFERRED
    if _DEFERRED is not None or threading.current_thread() is not threading.main_thread():
        yield
        return
    _DEFERRED = []
    try:
        yield
    finally:
        pending, _DEFERRED = _DEFERRED, None
        if pending:
            _raise_for(pending[0])


# ----------------------------------------------------------------------------- scheduler choice

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
        with dask.config.set({"distributed.worker.profile.enabled": False}):
            cluster = LocalCluster(n_workers=int(scheduler.split(":", 1)[1]), threads_per_worker=1,
                                   processes=True, dashboard_address=None,
                                   scheduler_kwargs={"dashboard": False, "dashboard_address": ":0"},
                                   silence_logs=logging.ERROR)
        return Client(cluster), cluster
    try:
        return Client(scheduler, timeout="10s"), None
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
    client, cluster = _dask_client(scheduler)
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


def active_client():
    """The Dask client set by :func:`use_scheduler`, or None."""
    return _SCHEDULER.get()


def runs_inline(n_jobs: int | None, n_items: int) -> bool:
    """Whether :func:`run_jobs` would run in this process (no scheduler, one job or one core)."""
    return active_client() is None and (resolve_jobs(n_jobs) <= 1 or n_items <= 1)


def resolve_jobs(n_jobs: int | None) -> int:
    """Worker processes for a pool: ``n_jobs`` or the CPU count."""
    return max(1, int(n_jobs)) if n_jobs is not None else (os.cpu_count() or 1)


# ----------------------------------------------------------------------------- pool workers

_BLAS_KEYS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def single_threaded_children() -> Iterator[None]:
    """Spawned workers inherit these: one BLAS thread each, so n processes fill n cores."""
    saved = {key: os.environ.get(key) for key in _BLAS_KEYS}
    os.environ.update({key: "1" for key in _BLAS_KEYS})
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def descendants(pid: int) -> set[int]:
    """Process ids of every descendant of ``pid`` (workers, fork servers, trackers), from
    Linux's /proc; empty where there is none. For checks that no process is left behind."""
    out: set[int] = set()
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            tasks = list(Path(f"/proc/{p}/task").glob("*"))
        except OSError:  # the process ended meanwhile
            continue
        for task in tasks:
            try:
                kids = [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                continue
            todo.extend(c for c in kids if c not in out)
            out.update(kids)
    return out


def die_with_parent() -> None:
    """Linux: ask for SIGTERM when the parent process dies (no orphan keeps computing): pool
    workers, and core.io's isolated mesh readers."""
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(Exception):
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG = 1


def _server_dies_with_its_client() -> None:
    """In a process started by this module's pool (the fork server): exit when the process
    that started it is gone, as the workers die with the server. Run when the module is
    imported; a no-op elsewhere (its parent is not the recorded client).

    A watch of the parent pid rather than ``PR_SET_PDEATHSIG``: that signal comes when the
    *thread* that started the server ends (a GUI worker thread), not the process."""
    client = os.environ.get(_SERVER_CLIENT_ENV, "")
    if not client.isdigit() or os.getppid() != int(client):
        return

    def watch() -> None:
        while os.getppid() == int(client):
            time.sleep(0.2)
        os._exit(1)

    threading.Thread(target=watch, name="ssm-studio-client-watch", daemon=True).start()


def _pool_init(common: Any, parent_pid: int) -> None:
    global _COMMON
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides; it terminates us
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    die_with_parent()
    try:  # the submitting process died before prctl took effect
        os.kill(parent_pid, 0)
    except ProcessLookupError:
        os._exit(1)
    except OSError:
        pass
    _COMMON = common


def _pool_call(fn: Callable, key: Any, arg: Any) -> tuple[Any, Any]:
    return key, fn(arg, _COMMON)


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


# ----------------------------------------------------------------------------- executor

class JobError(RuntimeError):
    """A job raised; ``key`` says which (the original exception is chained)."""

    def __init__(self, key: Any, exc: BaseException):
        super().__init__(f"job {key!r} failed: {type(exc).__name__}: {exc}")
        self.key = key


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
            return _run_dask(client, fn, iterator, common, total, progress, keep, label,
                             window, retries)
    client = active_client()
    if client is not None:
        return _run_dask(client, fn, iterator, common, total, progress, keep, label, window, retries)
    n = resolve_jobs(n_jobs)
    if n <= 1 or (total is not None and total <= 1):
        return _run_inline(fn, iterator, common, total, progress, keep, label)
    return _run_pool(fn, iterator, common, n if total is None else min(n, total), total,
                     progress, keep, label, window)


def _message(label: str, done: int, total: int | None) -> str:
    return f"{label} {done}/{total}" if total else f"{label} {done}"


def _tick(progress, done: int, total: int | None, label: str) -> None:
    """Progress after a job or while waiting (a heartbeat): the GUI's Cancel is raised from
    the callback, a swallowed signal from here."""
    raise_if_signalled()
    report(progress, done / total if total else 0.0, _message(label, done, total))


def _run_inline(fn, iterator, common, total, progress, keep, label) -> dict:
    results: dict = {}
    for key, arg in iterator:
        try:
            out = fn(arg, common)
        except Exception as exc:
            raise JobError(key, exc) from exc
        results[key] = keep(key, out)
        _tick(progress, len(results), total, label)
    return results


def preload_in_workers(module: str) -> None:
    """Pool workers start with ``module`` (a module whose functions are jobs) already imported:
    the fork server imports it once and every worker is forked from it. Call at import time;
    effective for the modules registered before the session's first pool."""
    if module not in _WORKER_MODULES:
        _WORKER_MODULES.append(module)


def _pool_context(fn: Callable):
    """forkserver where the platform has it, else spawn -- never a fork of this (possibly
    multi-threaded GUI or BLAS) process. The fork server is a fresh single-threaded process,
    started once per session, that imports the job modules once; a pool then starts in
    milliseconds instead of an interpreter start and imports per worker (spawn)."""
    import multiprocessing as mp

    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    context = mp.get_context("forkserver")
    os.environ[_SERVER_CLIENT_ENV] = str(os.getpid())   # read by the server it may start
    module = getattr(fn, "__module__", None)
    extra = [module] if module and module != "__main__" and module not in _WORKER_MODULES else []
    # effective when the server (re)starts; '__main__' is multiprocessing's default
    context.set_forkserver_preload(["__main__", *_WORKER_MODULES, *extra])
    return context


def _run_pool(fn, iterator, common, n, total, progress, keep, label, window) -> dict:
    # Workers start on demand (at submit); they, and a fork server started now, inherit one
    # BLAS thread each for the whole run.
    with single_threaded_children():
        return _run_pool_jobs(fn, iterator, common, n, total, progress, keep, label, window)


def _run_pool_jobs(fn, iterator, common, n, total, progress, keep, label, window) -> dict:
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    # concurrent.futures rather than multiprocessing.Pool: Pool.terminate() can deadlock on the
    # task queue's lock held by a worker it kills; this executor survives killed workers.
    executor = ProcessPoolExecutor(max_workers=n, mp_context=_pool_context(fn),
                                   initializer=_pool_init, initargs=(common, os.getpid()))
    results: dict = {}
    limit = max(1, int(window) if window else 4 * n)
    in_flight: dict = {}
    exhausted = False

    def submit_more() -> None:
        nonlocal exhausted
        while not exhausted and len(in_flight) < limit:
            try:
                key, arg = next(iterator)
            except StopIteration:
                exhausted = True
                return
            with signals_deferred():  # submit may start a worker process
                in_flight[executor.submit(_pool_call, fn, key, arg)] = key

    try:
        submit_more()
        while in_flight:
            # short waits: SIGINT/SIGTERM are handled within a fraction of a second
            finished, _ = wait(list(in_flight), timeout=0.1, return_when=FIRST_COMPLETED)
            if not finished:  # heartbeat
                _tick(progress, len(results), total, label)
            for fut in finished:
                key = in_flight.pop(fut)
                exc = fut.exception()
                if exc is not None:
                    raise JobError(key, exc) from exc
                results[key] = keep(key, fut.result()[1])
                _tick(progress, len(results), total, label)
            submit_more()
        executor.shutdown(wait=True)
    except BaseException:
        _terminate_executor(executor)
        raise
    return results


def _terminate_executor(executor) -> None:
    """Stop the workers now: SIGTERM, SIGKILL for any still alive after 1 s, no waiting on jobs."""
    queue = getattr(executor, "_call_queue", None)   # shutdown() drops it
    procs = list((getattr(executor, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = time.monotonic() + 1.0
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(0.5)
    with contextlib.suppress(Exception):
        executor.shutdown(wait=False, cancel_futures=True)
    if queue is not None:
        _unblock_call_queue(queue)
        _keep_for_exit(queue)


_STOPPED_QUEUES: list = []   # call queues of pools stopped by _terminate_executor
_EXIT_HOOK = False


def _keep_for_exit(queue) -> None:
    """Keep a stopped pool's call queue (its manager thread may outlive the pool) so that the
    interpreter's exit drains it first (see :func:`_unblock_call_queue`)."""
    global _EXIT_HOOK
    if not _EXIT_HOOK:
        # threading's exit hooks run in reverse order of registration: this one runs before
        # concurrent.futures' own, which joins the pools' manager threads
        with contextlib.suppress(Exception):
            threading._register_atexit(_unblock_at_exit)
        _EXIT_HOOK = True
    # only queues whose feeder still runs can block: the others (and their pipes) are let go
    _STOPPED_QUEUES[:] = [q for q in _STOPPED_QUEUES if _feeder_alive(q)]
    if _feeder_alive(queue):
        _STOPPED_QUEUES.append(queue)


def _feeder_alive(queue) -> bool:
    thread = getattr(queue, "_thread", None)
    return thread is not None and thread.is_alive()


def _unblock_at_exit() -> None:
    for queue in _STOPPED_QUEUES:
        _unblock_call_queue(queue)


def _unblock_call_queue(queue) -> None:
    """Read away what a stopped pool's call queue still sends to its killed workers.

    Its feeder thread can be blocked writing a job into the pipe (this process holds the
    other end, so the write neither fails nor completes), and the executor's manager thread
    joins that feeder when it tears the broken pool down; the interpreter's exit then joins
    the manager thread, and the process never ends (seen after a cancelled build). Draining
    the pipe lets the feeder reach the queue's close and end.
    """
    reader = getattr(queue, "_reader", None)
    if reader is None:
        return
    with contextlib.suppress(Exception):
        queue.cancel_join_thread()
    deadline = time.monotonic() + 5.0
    with contextlib.suppress(Exception):
        while time.monotonic() < deadline and reader.poll(0.2):
            reader.recv_bytes()


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


def _run_dask(client, fn, iterator, common, total, progress, keep, label, window, retries) -> dict:
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
                _tick(progress, len(results), total, label)  # heartbeat
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
                    _tick(progress, len(results), total, label)
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


_server_dies_with_its_client()
