"""The local process pool of :func:`core.runtime.parallel.run_jobs`: loky's
``ProcessPoolExecutor`` (joblib's robust executor: it detects killed workers, and
``shutdown(kill_workers=True)`` stops a pool at once, however full its call queue) on
workers forked from a fork server that has the job modules imported.

- ``common`` reaches each worker once, through the pool's initialiser;
- one BLAS thread per worker (:func:`single_threaded_children`), so n processes fill n cores;
- the start method is the standard library's forkserver where the platform has it (loky's
  own spawn-like context elsewhere), never a fork of this possibly multi-threaded process.
  The fork server is a fresh single-threaded process, started once per session, that imports
  the job modules once (:func:`preload_in_workers`); a pool then starts in milliseconds.
  loky's default context starts every worker as a new interpreter that imports the job
  modules again, for every pool, and a command runs several pools (reading, grooming,
  correspondence, residuals): measured by ``benchmarks/bench_pool.py`` (200 jobs of ~0.1 ms,
  2 workers, load ~3 on 2 cores), a session's second and third pools reach their first
  result after 0.11 s here (0.08-0.10 s for the standard library's executor on the same fork
  server, the code this replaced) against 0.68-0.87 s with loky's context; per job, after
  start-up, 1.5-1.8 ms against 1.4-1.5 ms (loky pickles jobs with cloudpickle);
- workers ignore SIGINT (the parent decides, and stops them: a Ctrl-C to the terminal's
  process group sprays no tracebacks), and on Linux ask the kernel for SIGTERM when their
  parent dies (``PR_SET_PDEATHSIG``); so does the fork server, by watching the process that
  started it, so even a SIGKILLed command leaves no worker computing and no idle server.

On any exception while the jobs run (a job error, Cancel, SIGINT/SIGTERM) the workers are
killed with ``shutdown(wait=True, kill_workers=True)`` before the exception propagates.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from core.runtime.jobs import JobError, Keep, tick
from core.runtime.progress import ProgressCallback
from core.runtime.signals import signals_deferred

_COMMON: Any = None  # a pool worker's copy of ``common``
_WORKER_MODULES: list[str] = []  # imported once by the fork server (see preload_in_workers)
# pid of the process that starts the fork server (inherited by the server through its
# environment: the server and the processes it forks only ever import this module once)
_SERVER_CLIENT_ENV = "SSM_STUDIO_POOL_CLIENT"

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


def preload_in_workers(module: str) -> None:
    """Pool workers start with ``module`` (a module whose functions are jobs) already imported:
    the fork server imports it once and every worker is forked from it. Call at import time;
    effective for the modules registered before the session's first pool."""
    if module not in _WORKER_MODULES:
        _WORKER_MODULES.append(module)


def _pool_context(fn: Callable):
    """The standard library's forkserver where the platform has it (its preload list set to
    the job modules), else loky's spawn-like context -- never a fork of this (possibly
    multi-threaded GUI or BLAS) process."""
    import multiprocessing as mp

    if "forkserver" not in mp.get_all_start_methods():
        from loky.backend import get_context

        return get_context("loky")
    context = mp.get_context("forkserver")
    os.environ[_SERVER_CLIENT_ENV] = str(os.getpid())   # read by the server it may start
    module = getattr(fn, "__module__", None)
    extra = [module] if module and module != "__main__" and module not in _WORKER_MODULES else []
    # effective when the server (re)starts; '__main__' is multiprocessing's default
    context.set_forkserver_preload(["__main__", *_WORKER_MODULES, *extra])
    return context


def run_pool(fn: Callable[[Any, Any], Any], iterator: Iterator[tuple[Any, Any]], common: Any,
             n: int, total: int | None, progress: ProgressCallback | None, keep: Keep,
             label: str, window: int | None) -> dict:
    """The jobs on ``n`` worker processes, at most ``window`` (default 4 per worker) in
    flight; results handed to ``keep`` as they arrive."""
    from concurrent.futures import FIRST_COMPLETED, wait

    from loky import ProcessPoolExecutor

    # The workers, and a fork server started now, inherit one BLAS thread each.
    with single_threaded_children():
        # The executor's queues create named semaphores and register them with the resource
        # tracker, and its shutdown unlinks them: a signal raised halfway through either can
        # leave one that the tracker reports as leaked at exit. Both run with signals held back.
        with signals_deferred():
            executor = ProcessPoolExecutor(max_workers=n, context=_pool_context(fn),
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
                with signals_deferred():  # submit may start the worker processes
                    in_flight[executor.submit(_pool_call, fn, key, arg)] = key

        try:
            submit_more()
            while in_flight:
                # Short waits: SIGINT/SIGTERM are handled within a fraction of a second. They
                # are held back over the wait and the reads of its futures: ``wait`` takes
                # every future's lock in turn, and a KeyboardInterrupt raised between two
                # takes would leave one held by this thread, so loky's result thread would
                # block on it for good and the shutdown below would never return.
                with signals_deferred():
                    finished, _ = wait(list(in_flight), timeout=0.1,
                                       return_when=FIRST_COMPLETED)
                    arrived = []
                    for fut in finished:
                        exc = fut.exception()
                        arrived.append((in_flight.pop(fut), exc,
                                        None if exc is not None else fut.result()[1]))
                if not arrived:  # heartbeat
                    tick(progress, len(results), total, label)
                for key, exc, value in arrived:
                    if exc is not None:
                        raise JobError(key, exc) from exc
                    results[key] = keep(key, value)
                    tick(progress, len(results), total, label)
                submit_more()
        except BaseException:
            with signals_deferred():  # a second Ctrl-C must not cut the shutdown short
                executor.shutdown(wait=True, kill_workers=True)
            raise
        with signals_deferred():
            executor.shutdown(wait=True)
    return results


_server_dies_with_its_client()
