"""The one error type of file I/O, and the checks every reader starts with.

Every load or save problem is a :class:`DataFileError` whose message is one line naming
the file and the problem; library exceptions are translated, never passed on.
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import warnings
from collections.abc import Iterator
from pathlib import Path


class DataFileError(ValueError):
    """A file could not be read or written; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{display_path(path)}: {problem}")


class DataFileWarning(UserWarning):
    """Something a reader noticed and worked around; the message names the file."""


def display_path(path: str | os.PathLike) -> str:
    """``path`` as printable text: bytes of a non-UTF-8 file name shown as ``\\xNN``.

    Such names reach Python as lone surrogates (PEP 383), which cannot be encoded as UTF-8,
    so a message holding them would fail to print or to be written into a JSON report. Each
    byte is written out (``caf\\xe9.stl``, as ``ls -b`` shows it), not replaced by U+FFFD,
    so the user can still tell which file is meant.
    """
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


@contextlib.contextmanager
def warnings_as_notes(path: str | os.PathLike) -> Iterator[None]:
    """Catch the warnings libraries (nibabel, numpy) raise while reading ``path`` and re-issue
    each as one :class:`DataFileWarning` naming the file (not a two-line stderr report)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    seen = set()
    for item in caught:
        text = " ".join(str(item.message).split())[:300]
        if isinstance(item.message, DataFileWarning):
            note = text
        else:
            note = f"{display_path(path)}: {text}"
        if note not in seen:
            seen.add(note)
            warnings.warn(DataFileWarning(note), stacklevel=3)


def without_path(text: str, path: str | os.PathLike) -> str:
    """A library's message about ``path`` without the path (the caller names the file once):
    the path becomes "the file", and a trailing "for file: <path>" (VTK's readers) goes."""
    text = text.replace(str(path), "the file")
    return re.sub(r"\s*\b(for|in) file:?\s*the file\b", "", text)


def why(exc: BaseException, path: Path | None = None) -> str:
    """A library's error text on one line, without the file name (the caller adds it)."""
    text = str(exc)
    if path is not None:
        text = without_path(text, path)
    text = display_path(text)
    text = " ".join(text.split())
    return text[:300] if text else type(exc).__name__


def require_file(path: str | os.PathLike) -> Path:
    """``path`` as a Path if it is a readable, non-empty file; else a DataFileError."""
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise DataFileError(path, "file not found") from None
    except OSError as exc:  # a loop of links, a name too long, a folder not searchable
        raise DataFileError(path, f"cannot access the file ({why(exc, path)})") from None
    mode = info.st_mode
    if stat.S_ISDIR(mode):
        raise DataFileError(path, "is a folder, not a file")
    if stat.S_ISFIFO(mode):
        raise DataFileError(path, "is a named pipe (FIFO), not a regular file")
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        raise DataFileError(path, "is a device, not a regular file")
    if stat.S_ISSOCK(mode):
        raise DataFileError(path, "is a socket, not a regular file")
    if info.st_size == 0:
        raise DataFileError(path, "file is empty (0 bytes)")
    if not os.access(path, os.R_OK):
        raise DataFileError(path, "permission denied (the file is not readable)")
    return path
