"""Progress reporting and cancellation for long computations, with no GUI dependency.

Long-running functions in ``core`` take an optional ``progress`` callable
``progress(fraction: float, message: str) -> None``. The caller may raise :class:`Cancelled`
from inside it to stop the work (the GUI's workers do so when the user presses Cancel); the
exception propagates out of the computation, which leaves no partial output behind.
:class:`StderrProgress` is the command line's text progress bar.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

ProgressCallback = Callable[[float, str], None]


class Cancelled(Exception):
    """Raised by a progress callback to stop a computation."""


def report(progress: ProgressCallback | None, fraction: float, message: str = "") -> None:
    """Call ``progress`` if given (fraction clipped to [0, 1])."""
    if progress is not None:
        progress(min(max(float(fraction), 0.0), 1.0), message)


def sub_progress(progress: ProgressCallback | None, start: float, stop: float,
                 prefix: str = "") -> ProgressCallback | None:
    """A callback mapping [0, 1] onto [start, stop] of ``progress`` (for nested steps), its
    messages after ``prefix`` (a nested step that says what it is part of)."""
    if progress is None:
        return None

    def inner(fraction: float, message: str = "") -> None:
        progress(start + (stop - start) * min(max(fraction, 0.0), 1.0),
                 f"{prefix}{message}" if message else prefix.rstrip(": "))

    return inner


class StderrProgress:
    """A one-line text progress bar on stderr, shown only for steps lasting over a second."""

    def __init__(self, title: str, stream=None, width: int = 30, delay: float = 1.0):
        self.title = title
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self.delay = delay
        self._start = time.monotonic()
        self._shown = False

    def __call__(self, fraction: float, message: str = "") -> None:
        elapsed = time.monotonic() - self._start
        if elapsed < self.delay and fraction < 1.0:
            return
        filled = int(round(self.width * fraction))
        bar = "#" * filled + "-" * (self.width - filled)
        self.stream.write(f"\r{self.title} [{bar}] {100 * fraction:5.1f}% {elapsed:6.1f}s {message[:40]:<40}")
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        if self._shown:
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self) -> StderrProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
