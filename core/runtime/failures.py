"""How a per-item job's failure is reported, so that a batch goes on without hiding bugs.

A batch (correspondence shapes, image pairs, evaluation folds) reports a failed item and goes
on. Failures the data can cause (unreadable files, singular geometry, a solver that does not
converge, memory) are expected and reported in one line; any other exception is a programming
error and is reported with its traceback, so that it reaches the report instead of passing
for a bad shape.
"""

from __future__ import annotations

import logging
import traceback

import numpy as np

#: Exceptions that data can cause. DataFileError is a ValueError; SimpleITK and VTK raise
#: RuntimeError; numpy's LinAlgError and FloatingPointError are data-dependent as well.
EXPECTED_ERRORS: tuple[type[BaseException], ...] = (
    ValueError, OSError, RuntimeError, MemoryError, np.linalg.LinAlgError, FloatingPointError,
    ArithmeticError)

log = logging.getLogger(__name__)


def describe_failure(exc: BaseException) -> str:
    """``"Type: message"`` for an expected failure; for any other exception the same line
    followed by its traceback (and logged), since it is a bug rather than bad data."""
    line = f"{type(exc).__name__}: {exc}"
    if isinstance(exc, EXPECTED_ERRORS):
        return line
    log.error("unexpected error in a job", exc_info=exc)
    trace = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    return f"internal error (a bug, please report it) {line}\n{trace}"
