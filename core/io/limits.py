"""Declared sizes checked against the file and the memory before anything is allocated.

A damaged or hostile header can claim billions of points or voxels in a few bytes; a reader
that trusts it allocates gigabytes (or aborts with ``std::bad_alloc`` inside VTK) before
noticing. Every reader that sizes buffers from a header calls :func:`check_declared_size`
first: the data the header announces must fit in what the file can hold (times the best
ratio its compression can reach) and in the memory available now.
"""

from __future__ import annotations

import os
from pathlib import Path

from core.errors import DataFileError

# deflate cannot expand data more than ~1032:1 (RFC 1951 block limits); a little margin
DEFLATE_MAX_RATIO = 1100


def available_memory() -> int:
    """Bytes of memory available to this process now (MemAvailable; a guess if unknown)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return 8 << 30


def human_bytes(n: float) -> str:
    """``n`` bytes as a short text (``"2.7 GB"``)."""
    for unit in ("bytes", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} PB"


def check_declared_size(path: str | os.PathLike, declared: int, what: str, *,
                        stored: int | None = None, max_ratio: float = 1.0,
                        truncated: str = "truncated or corrupt") -> None:
    """Refuse a header that announces more data than the file or the memory can hold.

    Parameters
    ----------
    declared : bytes the header announces once decoded (e.g. n_points * 3 * 4).
    what : what was announced, for the message ("2000000000 points").
    stored : bytes of the file that can hold that data (default: the whole file).
    max_ratio : how many decoded bytes one stored byte can become at most (1 for raw
        binary data, :data:`DEFLATE_MAX_RATIO` for zlib/gzip-compressed data).
    truncated : the start of the message when the file is too small.
    """
    path = Path(path)
    if stored is None:
        stored = path.stat().st_size
    if declared > stored * max_ratio:
        raise DataFileError(path, f"{truncated}: the header declares {what} "
                                  f"({human_bytes(declared)}) but the file holds only "
                                  f"{human_bytes(stored)}")
    memory = available_memory()
    if declared > memory:
        raise DataFileError(path, f"the header declares {what} ({human_bytes(declared)}), more "
                                  f"than the memory available ({human_bytes(memory)})")


def bytes_on_disk(path: str | os.PathLike) -> int | None:
    """The bytes the file occupies on disk (``st_blocks`` x 512), None where unknown.

    A sparse file (a hole seeked over, never written) can claim gigabytes in ``st_size``
    while holding a few kilobytes; its holes read as zeros. Filesystems with transparent
    compression also report fewer blocks than ``st_size``, so compare with a compression
    ratio (e.g. :data:`DEFLATE_MAX_RATIO`), never 1:1.
    """
    try:
        blocks = getattr(os.stat(path), "st_blocks", None)
    except OSError:
        return None
    return None if blocks is None else int(blocks) * 512


# Coordinates beyond 1 km of the origin are not positions in a scan (scanner coordinates
# stay within a few hundred mm); larger values overflow the fits' squared distances (1e300
# -> inf -> NaN far from the file that held them), so readers refuse them by name.
MAX_COORDINATE_MM = 1e6


def coordinate_problem(values, what: str) -> str | None:
    """Why ``values`` (any shape, mm) are not usable coordinates, or None: NaN/inf, or
    beyond :data:`MAX_COORDINATE_MM` of the origin."""
    import numpy as np

    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return None
    finite = np.isfinite(values)
    if not finite.all():
        rows = int((~finite.reshape(len(values), -1).all(axis=1)).sum()) if values.ndim > 1 \
            else int((~finite).sum())
        return f"{rows} {what} have NaN or infinite coordinates"
    largest = float(np.abs(values).max())
    if largest > MAX_COORDINATE_MM:
        rows = int((np.abs(values).reshape(len(values), -1) > MAX_COORDINATE_MM)
                   .any(axis=1).sum()) if values.ndim > 1 else 1
        return (f"{rows} of {len(values)} {what} lie up to {largest:.3g} mm from the origin, "
                f"beyond {MAX_COORDINATE_MM:.0e} mm (1 km): not coordinates in mm of a scan")
    return None
