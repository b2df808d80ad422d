"""The dispatch table: which reader and writer handle a file, by kind and suffix.

As in nibabel's image classes and trimesh's ``load`` mappings, each format module registers
a :class:`FileFormat` (suffix, kind, read and write functions); :func:`core.io.load_mesh`,
:func:`core.io.load_volume`, ... look the file's suffix up here instead of branching on
names. A new format is one new module that calls :func:`register` (imported by
``core/io/__init__.py``).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

# Suffixes of more than one dot that name one format (checked before Path.suffix).
_COMPOUND_SUFFIXES: set[str] = {".nii.gz", ".mrk.json"}


@dataclass(frozen=True)
class FileFormat:
    """One file format of one kind of data.

    Attributes
    ----------
    suffix : str
        Lower-case file-name ending, with its dot (``".vtk"``, ``".nii.gz"``).
    kind : str
        ``"mesh"``, ``"volume"``, ``"points"`` or ``"model"``.
    description : str
        Human name, for error messages and file dialogs.
    read : callable or None
        ``read(path: Path) -> object``; the path exists and is not empty.
    write : callable or None
        ``write(path: Path, data, **options) -> None``, atomic.
    keeps_vertex_order : bool
        Meshes: whether a written mesh reads back with the same vertex numbering.
    """

    suffix: str
    kind: str
    description: str
    read: Callable[..., object] | None = None
    write: Callable[..., None] | None = None
    keeps_vertex_order: bool = True


_FORMATS: dict[tuple[str, str], FileFormat] = {}


def register(fmt: FileFormat) -> FileFormat:
    """Add (or replace) a format in the table."""
    _FORMATS[(fmt.kind, fmt.suffix)] = fmt
    if fmt.suffix.count(".") > 1:
        _COMPOUND_SUFFIXES.add(fmt.suffix)
    return fmt


def split_member(path: str | os.PathLike) -> tuple[Path, str | None]:
    """``FILE#MEMBER`` (a model inside a file that holds several, as scalismo-faces names
    them with a URI fragment) as ``(Path(FILE), MEMBER)``; any other path as ``(path, None)``.

    Only split when ``path`` itself is not an existing file and ``FILE`` is not empty, so
    a file whose name holds '#' still opens.
    """
    text = os.fspath(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    base, sep, member = text.rpartition("#")
    if not sep or not base or os.path.lexists(text):
        return Path(text), None
    return Path(base), member


def file_suffix(path: str | os.PathLike) -> str:
    """The lower-case suffix that names the format of ``path`` (``.nii.gz`` as one)."""
    name = Path(path).name.lower()
    for compound in sorted(_COMPOUND_SUFFIXES, key=len, reverse=True):
        if name.endswith(compound):
            return compound
    return Path(name).suffix


def lookup(path: str | os.PathLike, kind: str) -> FileFormat | None:
    """The registered format of ``kind`` for the suffix of ``path``, or None."""
    return _FORMATS.get((kind, file_suffix(path)))


def suffixes(kind: str) -> tuple[str, ...]:
    """The registered suffixes of ``kind``, in registration order."""
    return tuple(suffix for (k, suffix) in _FORMATS if k == kind)
