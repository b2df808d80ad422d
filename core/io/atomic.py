"""Atomic saves: write to a temporary file beside the target, then rename it over.

A killed or failing writer never leaves a truncated file at the target path: the previous
file stays until the rename, which POSIX and NTFS make atomic within one folder. A killed
writer does leave its hidden temporary file (``.NAME.<pid>.XXXX.tmp.EXT``): the next save
of the same name removes those of processes that are no longer running, and folder
expansion (:func:`core.io.meshes.expand_mesh_paths`) never reads hidden or temporary files.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from core.errors import DataFileError
from core.io.registry import file_suffix


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _current_umask()

# .<name>.<pid>.<random>.tmp<suffix>; older versions wrote .<name>.<random>.tmp<suffix>
_TEMP_PATTERN = re.compile(r"^\.(?P<name>.+?)\.(?:(?P<pid>\d+)\.)?[^.]+\.tmp(?:\.[^/]*)?$")
_STALE_WITHOUT_PID_S = 3600.0


def is_temporary_name(name: str) -> bool:
    """Whether ``name`` is one of :func:`atomic_path`'s temporary files."""
    return bool(_TEMP_PATTERN.match(name))


def _safe_name(name: str) -> str:
    """File name text usable inside a temporary name by every writer (ASCII, no spaces).

    VTK's writers cannot open names that are not valid UTF-8 (lone surrogates from a
    non-UTF-8 file system name); the temporary file only needs to be recognisable.
    """
    return re.sub(r"[^A-Za-z0-9_+=-]", "_", name.rsplit(".", 1)[0])[:60] or "file"


def _process_gone(pid: int) -> bool:
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except (PermissionError, OSError):
        return False
    return False


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove temporary files left beside ``path`` by killed writers; returns them.

    A temporary file is stale when the process that made it has ended (its pid is in the
    name), or, for names without a pid, when it is older than an hour.
    """
    path = Path(path)
    removed: list[Path] = []
    prefix = f".{_safe_name(path.name)}."
    try:
        candidates = [p for p in path.parent.iterdir() if p.name.startswith(prefix)]
    except OSError:
        return removed
    for candidate in candidates:
        match = _TEMP_PATTERN.match(candidate.name)
        if not match:
            continue
        try:
            if match["pid"] is not None:
                stale = _process_gone(int(match["pid"]))
            else:
                stale = time.time() - candidate.stat().st_mtime > _STALE_WITHOUT_PID_S
            if stale:
                candidate.unlink()
                removed.append(candidate)
        except OSError:
            continue
    return removed


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, allow_empty: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary name keeps the target's suffix so that writers choosing a format by
    extension (VTK, nibabel) pick the right one. If the block raises (or, unless
    ``allow_empty``, leaves the temporary file empty, as a failing VTK writer does), the
    previous file at ``path`` is left untouched and the temporary file is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{_safe_name(path.name)}.{os.getpid()}.",
                               suffix=f".tmp{file_suffix(path)}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if not tmp_path.exists() or (tmp_path.stat().st_size == 0 and not allow_empty):
            raise DataFileError(path, "nothing was written (the writer produced no data)")
        # mkstemp creates the file private (0600); give the result the permissions a plain
        # open() would (or keep those of the file being replaced).
        mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_UMASK
        os.chmod(tmp_path, mode)
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path, allow_empty=True) as tmp:
        tmp.write_text(text, encoding="utf-8")


def atomic_write_json(path: str | os.PathLike, obj: object) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, default=json_default) + "\n")


def json_default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")
