"""The one error type of file I/O, and the checks every reader starts with.

Every load or save problem is a :class:`DataFileError` whose message is one line naming
the file and the problem; library exceptions are translated, never passed on.
"""

from __future__ import annotations

import os
from pathlib import Path


class DataFileError(ValueError):
    """A file could not be read or written; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def why(exc: BaseException, path: Path | None = None) -> str:
    """A library's error text on one line, without the file name (the caller adds it)."""
    text = str(exc)
    if path is not None:
        text = text.replace(str(path), "the file")
    text = " ".join(text.split())
    return text[:300] if text else type(exc).__name__


def require_file(path: str | os.PathLike) -> Path:
    """``path`` as a Path if it is a readable, non-empty file; else a DataFileError."""
    path = Path(path)
    if not path.exists():
        raise DataFileError(path, "file not found")
    if path.is_dir():
        raise DataFileError(path, "is a folder, not a file")
    if path.stat().st_size == 0:
        raise DataFileError(path, "file is empty (0 bytes)")
    if not os.access(path, os.R_OK):
        raise DataFileError(path, "permission denied (the file is not readable)")
    return path
