"""Workaround for a reference-count bug of PySide6 6.12.0 that aborts the interpreter.

PySide6 6.12.0's ``SignalInstance.emit()`` returns ``True`` without taking a reference, so
every ``emit()`` called from Python drops one reference to the ``True`` singleton. CPython
3.11 deallocates it after a few thousand emissions and aborts ("Fatal Python error:
bool_dealloc: deallocating True or False"), e.g. after scrolling through a few thousand
slices. Reproduce: 100 calls of ``obj.sig.emit()`` lower ``sys.getrefcount(True)`` by 100
with 6.12.0 and by 0 with 6.11.3.

:func:`guard_singletons` (run when ``app`` is imported, before any Qt object exists) adds
2**40 references to True, False and None: they become effectively immortal, as CPython 3.12+
makes them by design (PEP 683), so the leak can never reach zero. It is a no-op on 3.12+.
"""

from __future__ import annotations

import ctypes
import sys

_GUARD = 1 << 40
_guarded = False


def _affected_pyside_installed() -> bool:
    """True when the installed PySide6 is the release with the leak (6.12.0)."""
    from importlib import metadata

    for dist in ("PySide6-Essentials", "PySide6"):
        try:
            return metadata.version(dist) == "6.12.0"
        except metadata.PackageNotFoundError:
            continue
    return False


def guard_singletons() -> None:
    """Make True, False and None immune to the PySide6 6.12.0 ``emit()`` reference leak."""
    global _guarded
    if _guarded or sys.version_info >= (3, 12) or sys.implementation.name != "cpython":
        return
    if not _affected_pyside_installed():
        return
    for obj in (True, False, None):
        ctypes.c_ssize_t.from_address(id(obj)).value += _GUARD   # ob_refcnt: first field
    _guarded = True
