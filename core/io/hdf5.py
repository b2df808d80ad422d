"""HDF5 files read without ever leaving them (h5py), with every HDF5 error one line.

HDF5 can keep a file's objects in other files (HDF5 User's Guide, "Links" and "Datasets";
h5py's ``ExternalLink``, ``create_dataset(external=...)`` and ``VirtualLayout``):

- an *external link* names an object in another HDF5 file, opened when the link is followed;
- *external raw storage* (``H5Pset_external``) keeps a dataset's bytes in any other file
  (``/etc/passwd`` reads as numbers);
- a *virtual dataset* (VDS) maps its data from datasets of other files;
- a *soft link* names a path, which can run through an external link.

:class:`H5Reader` reaches every object by walking its path one link at a time
(``Group.get(name, getlink=True)``): hard links are followed, soft links are resolved by
the same walk (inside the file, with a hop limit), and an external or user-defined link is
refused before anything opens it. Before a dataset's data is read, its layout is checked
(no external storage, not virtual, only HDF5's built-in filters, so no filter plugin is
loaded) and its declared size is checked against the file and the memory
(:func:`core.io.limits.check_declared_size`). Any h5py/HDF5 exception on the way becomes a
:class:`DataFileError` naming the file and the object.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import overload

import numpy as np

from core.errors import DataFileError, why
from core.io.limits import DEFLATE_MAX_RATIO, bytes_on_disk, check_declared_size, human_bytes

_MAX_SOFT_LINK_HOPS = 16
_MAX_ATTRIBUTE_BYTES = 1 << 20  # statismo's string attributes are a few bytes
_SPARSE_CHECK_BYTES = 64 << 20  # datasets above this must be backed by blocks on disk
# HDF5's built-in filters and LZF (built into h5py): anything else would load a plugin
_BUILTIN_FILTERS = {1: "deflate", 2: "shuffle", 3: "fletcher32", 4: "szip", 5: "nbit",
                    6: "scaleoffset", 32000: "lzf"}
# h5py/HDF5 failures on a damaged file (KeyError: "Unable to synchronously open object
# (addr overflow ...)", OSError: "... can't read data", RuntimeError from visits)
H5_ERRORS = (OSError, KeyError, RuntimeError, ValueError, TypeError, IndexError,
             OverflowError, SystemError)


def _h5py():
    import h5py

    return h5py


def h5_problem(exc: BaseException) -> str:
    """An h5py/HDF5 error text on one line, short."""
    text = why(exc)
    if isinstance(exc, KeyError):
        text = text.strip("'\"")
    return text[:200]


@contextlib.contextmanager
def open_h5(path: str | os.PathLike) -> Iterator[H5Reader]:
    """Open ``path`` read-only as an :class:`H5Reader`; not HDF5 or damaged: DataFileError."""
    path = Path(path)
    h5py = _h5py()
    try:
        h5 = h5py.File(path, "r")
    except H5_ERRORS as exc:
        text = h5_problem(exc)
        problem = "not an HDF5 file" if "signature" in text else "truncated or corrupt HDF5 file"
        raise DataFileError(path, f"{problem} ({text[:160]})") from None
    try:
        yield H5Reader(path, h5)
    finally:
        with contextlib.suppress(*H5_ERRORS):
            h5.close()


class H5Reader:
    """Checked, read-only access to the objects of one open HDF5 file (module docstring).

    Names are absolute (``/model/mean``) or relative to the file's root. Every method raises
    :class:`DataFileError` (file and object named) for a link leaving the file, a dataset
    stored elsewhere, a declared size the file cannot hold, or an HDF5 error.
    """

    def __init__(self, path: Path, h5):
        self.path = path
        self.h5 = h5
        self.file_size = path.stat().st_size
        self.disk_size = bytes_on_disk(path)
        self.declared = 0  # bytes of the datasets read so far (checked as a total)

    # ---- errors --------------------------------------------------------------------------
    def error(self, name: str, problem: str) -> DataFileError:
        return DataFileError(self.path, f"'{name.lstrip('/')}' {problem}")

    @contextlib.contextmanager
    def reading(self, name: str) -> Iterator[None]:
        """Translate an h5py/HDF5 error while reading ``name`` into one DataFileError."""
        try:
            yield
        except DataFileError:
            raise
        except MemoryError:
            raise self.error(name, "is too large for the memory available") from None
        except H5_ERRORS as exc:
            raise DataFileError(self.path, f"cannot read '{name.lstrip('/')}': truncated or "
                                           f"corrupt HDF5 file ({h5_problem(exc)})") from None

    # ---- links ---------------------------------------------------------------------------
    def node(self, name: str, *, _hops: int = 0):
        """The group or dataset at ``name`` (None when absent), reached link by link."""
        h5py = _h5py()
        parts = [p for p in name.split("/") if p and p != "."]
        with self.reading(name):
            current = self.h5["/"]
            walked = ""
            for part in parts:
                walked = f"{walked}/{part}"
                if not isinstance(current, h5py.Group):
                    return None
                link = current.get(part, getlink=True)
                if link is None:
                    return None
                if isinstance(link, h5py.ExternalLink):
                    raise self.error(walked, f"is an external link to '{link.path}' in file "
                                             f"'{link.filename}': a model file must not point "
                                             "into other files (not followed)")
                if isinstance(link, h5py.SoftLink):
                    if _hops >= _MAX_SOFT_LINK_HOPS:
                        raise self.error(walked, "is a soft link in a loop (more than "
                                                 f"{_MAX_SOFT_LINK_HOPS} hops)")
                    target = link.path if link.path.startswith("/") else \
                        f"{walked.rsplit('/', 1)[0]}/{link.path}"
                    current = self.node(target, _hops=_hops + 1)
                    if current is None:
                        return None
                    continue
                if not isinstance(link, h5py.HardLink):
                    raise self.error(walked, f"is a {type(link).__name__} link of a kind this "
                                             "reader does not follow")
                current = current[part]
            return current

    def group(self, name: str):
        """The group at ``name``, or None (absent or a dataset)."""
        node = self.node(name)
        return node if isinstance(node, _h5py().Group) else None

    def children(self, name: str) -> list[str]:
        """Names of the links in group ``name`` (not followed), sorted."""
        group = self.group(name)
        if group is None:
            return []
        with self.reading(name):
            return sorted(group.keys())

    # ---- datasets ------------------------------------------------------------------------
    def dataset(self, name: str):
        """The dataset at ``name`` checked to keep its data in this file (None when absent)."""
        h5py = _h5py()
        node = self.node(name)
        if node is None:
            return None
        if not isinstance(node, h5py.Dataset):
            raise self.error(name, f"is a {type(node).__name__.lower()}, not a dataset")
        with self.reading(name):
            if node.is_virtual:
                raise self.error(name, "is a virtual dataset (its data would come from other "
                                       "files): refused")
            if node.external:
                files = ", ".join(f"'{text_value(entry[0])}'" for entry in node.external[:3])
                raise self.error(name, f"keeps its data in another file ({files}, HDF5 external "
                                       "storage): refused, a model file must hold its own data")
            plist = node.id.get_create_plist()
            for i in range(plist.get_nfilters()):
                code = plist.get_filter(i)[0]
                if code not in _BUILTIN_FILTERS:
                    raise self.error(name, f"is encoded with HDF5 filter {code}, which needs a "
                                           "plugin: not read")
        return node

    @overload
    def read(self, name: str, *, kinds: str = ..., required_by: str) -> np.ndarray: ...

    @overload
    def read(self, name: str, *, kinds: str = ..., required_by: None = ...) -> np.ndarray | None: ...

    def read(self, name: str, *, kinds: str = "iuf", required_by: str | None = None
             ) -> np.ndarray | None:
        """The data of dataset ``name`` (numbers as float64 when ``kinds`` is "iuf", else as
        stored), after its checks; None when absent unless ``required_by`` names what needs it."""
        node = self.dataset(name)
        if node is None:
            if required_by:
                raise DataFileError(self.path, f"{required_by}: no dataset '{name.lstrip('/')}'")
            return None
        with self.reading(name):
            dtype = node.dtype
        if dtype.kind not in kinds:
            wanted = {"iuf": "numbers", "iu": "integers", "SUO": "text"}.get(kinds,
                                                                              "numbers or text")
            raise self.error(name, f"holds {dtype} values, {wanted} are needed")
        self.check_size(name, node)
        with self.reading(name):
            data = node[()]
        if kinds == "iuf":
            # a damaged float type can overflow in the cast: the caller's finiteness check says so
            with np.errstate(invalid="ignore", over="ignore"):
                return np.asarray(data, dtype=np.float64)
        return np.asarray(data)

    def check_size(self, name: str, node) -> None:
        """Refuse a dataset whose declared size the file (with its compression) or the
        memory cannot hold, before it is read (numbers also get a float64 copy)."""
        with self.reading(name):
            shape, dtype = node.shape, node.dtype
            filtered = node.id.get_create_plist().get_nfilters() > 0
        count = int(np.prod(shape, dtype=object)) if shape else 1
        stored = count * (dtype.itemsize if dtype.kind != "O" else 16)
        what = f"'{name.lstrip('/')}' as {' x '.join(map(str, shape)) or 'a scalar'} {dtype}"
        ratio = DEFLATE_MAX_RATIO if filtered else 1.0
        check_declared_size(self.path, stored, what, stored=self.file_size, max_ratio=ratio,
                            truncated="truncated or corrupt HDF5 file")
        self.declared += stored
        check_declared_size(self.path, self.declared, f"{what} and the datasets read before it",
                            stored=self.file_size, max_ratio=ratio,
                            truncated="truncated or corrupt HDF5 file")
        if stored > _SPARSE_CHECK_BYTES and self.disk_size is not None and \
                stored > self.disk_size * DEFLATE_MAX_RATIO:
            raise DataFileError(self.path, f"{what} declares {human_bytes(stored)} but the file "
                                           f"occupies only {human_bytes(self.disk_size)} on disk "
                                           "(a sparse file: its holes read as zeros): not read")
        # numbers are also copied as float64: both must fit in memory
        check_declared_size(self.path, stored + 8 * count, what, stored=1 << 62)

    # ---- attributes ----------------------------------------------------------------------
    def attribute(self, name: str, attr: str):
        """Attribute ``attr`` of the object ``name`` as stored (None when either is absent)."""
        node = self.node(name)
        if node is None:
            return None
        with self.reading(f"{name}@{attr}"):
            if attr not in node.attrs:
                return None
            size = node.attrs.get_id(attr).get_storage_size()
            if size > _MAX_ATTRIBUTE_BYTES:
                raise self.error(name, f"has an attribute '{attr}' of {size} bytes: not read")
            return node.attrs[attr]


    def text_attribute(self, name: str, attr: str, default: str = "") -> str:
        """Attribute ``attr`` of ``name`` as text (:func:`text_value`); ``default`` if absent."""
        value = self.attribute(name, attr)
        return default if value is None else text_value(value)


def text_value(value) -> str:
    """An HDF5 string as statismo (scalar, fixed or variable length) or Scalismo (a
    1-element array of strings) stores it, as str."""
    if isinstance(value, np.ndarray):
        value = value.reshape(-1)[0] if value.size else b""
    if isinstance(value, bytes | np.bytes_):
        return value.decode("utf-8", "replace").rstrip("\0")
    return str(value).rstrip("\0")


def integer_value(value) -> int | None:
    """An HDF5 integer as statismo stores it (a scalar or a 1-element int32 array), a
    whole-valued float, or a decimal string; None for anything else."""
    array = np.asarray(value)
    if array.size != 1:
        return None
    item = array.reshape(-1)[0]
    if array.dtype.kind in "iu":
        return int(item)
    if array.dtype.kind == "f":
        return int(item) if np.isfinite(item) and float(item).is_integer() else None
    if array.dtype.kind in "SUO":
        text = text_value(item).strip()
        return int(text) if text.lstrip("+-").isdigit() else None
    return None
