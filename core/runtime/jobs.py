"""What every runner of :func:`core.runtime.parallel.run_jobs` shares: the error that names a
failed job, the progress tick after each result (and while waiting), and the in-process
runner the others must equal result for result.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

from core.runtime.progress import ProgressCallback, report
from core.runtime.signals import raise_if_signalled

#: ``keep(key, result)``: what a runner stores for a result (the caller's ``on_result``)
Keep = Callable[[Any, Any], Any]


class JobError(RuntimeError):
    """A job raised; ``key`` says which (the original exception is chained)."""

    def __init__(self, key: Any, exc: BaseException):
        super().__init__(f"job {key!r} failed: {type(exc).__name__}: {exc}")
        self.key = key


def _message(label: str, done: int, total: int | None) -> str:
    return f"{label} {done}/{total}" if total else f"{label} {done}"


def tick(progress: ProgressCallback | None, done: int, total: int | None, label: str) -> None:
    """Progress after a job or while waiting (a heartbeat): the GUI's Cancel is raised from
    the callback, a swallowed signal from here."""
    raise_if_signalled()
    report(progress, done / total if total else 0.0, _message(label, done, total))


def run_inline(fn: Callable[[Any, Any], Any], iterator: Iterator[tuple[Any, Any]], common: Any,
               total: int | None, progress: ProgressCallback | None, keep: Keep,
               label: str) -> dict:
    """The jobs in this process, in order."""
    results: dict = {}
    for key, arg in iterator:
        try:
            out = fn(arg, common)
        except Exception as exc:
            raise JobError(key, exc) from exc
        results[key] = keep(key, out)
        tick(progress, len(results), total, label)
    return results
