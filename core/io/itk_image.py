"""NRRD (.nrrd, .nhdr) and MetaImage (.mha, .mhd) images through SimpleITK, in world RAS mm.

ITK describes an image by an origin, a spacing and a 3x3 direction matrix in LPS+ (DICOM's
patient coordinates): voxel (i, j, k) lies at ``origin + D @ (spacing * (i, j, k))``. SSM Studio
works in RAS+ (nibabel's convention), so the voxel -> world affine is

    A_RAS = diag(-1, -1, 1, 1) @ [[D * spacing, origin], [0, 0, 0, 1]]

exactly (oblique and left-handed grids included: nothing is rounded to the nearest axis).
The inverse, :func:`itk_geometry`, splits an affine back into ITK's three parts. SimpleITK's
array is indexed [k, j, i]; its transpose (a view, no copy) is the [i, j, k] array the rest
of SSM Studio uses. Headers are checked before SimpleITK reads the data
(:func:`core.io.nrrd.check_nrrd_header`, :func:`check_metaimage_header`), so a truncated
file or a header lying about the data size is a one-line error naming the file.

References: ITK Software Guide, "Image" (origin, spacing, direction); NRRD format
specification (teem.sourceforge.net/nrrd/format.html); MetaIO documentation (itk.org).
"""

from __future__ import annotations

import contextlib
import gzip
import os
import re
import sys
import zlib
from pathlib import Path

import numpy as np

from core.errors import DataFileError, without_path
from core.io.atomic import atomic_path
from core.io.registry import FileFormat, register
from core.types.volume import Volume

ITK_IMAGE_SUFFIXES = (".nrrd", ".nhdr", ".mha", ".mhd")

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])  # its own inverse

_METAIMAGE_TYPES = {
    "MET_CHAR": 1, "MET_UCHAR": 1, "MET_SHORT": 2, "MET_USHORT": 2, "MET_INT": 4,
    "MET_UINT": 4, "MET_LONG": 4, "MET_ULONG": 4, "MET_LONG_LONG": 8, "MET_ULONG_LONG": 8,
    "MET_FLOAT": 4, "MET_DOUBLE": 8,
}


def sitk():
    """SimpleITK, imported on first use (it is large), with ITK's console warnings off."""
    import SimpleITK

    SimpleITK.ProcessObject.SetGlobalWarningDisplay(False)
    return SimpleITK


@contextlib.contextmanager
def quiet_native_stderr():
    """Silence C-level stderr (GDCM and codec libraries print there) for the block.

    Their messages duplicate the exception we turn into a one-line error, and a console
    full of "Invalid marker size" is not an error message.
    """
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


def affine_from_itk(origin, spacing, direction) -> np.ndarray:
    """The RAS voxel -> world affine (4, 4) of an ITK geometry (LPS origin, spacing, direction)."""
    d = np.asarray(direction, dtype=np.float64).reshape(3, 3)
    lps = np.eye(4)
    lps[:3, :3] = d * np.asarray(spacing, dtype=np.float64)[None, :]
    lps[:3, 3] = np.asarray(origin, dtype=np.float64)
    return LPS_TO_RAS @ lps


def itk_geometry(affine: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin (3,), spacing (3,), direction (3, 3)) in LPS of a RAS voxel -> world affine.

    The direction's columns are the unit voxel axes; a sheared affine gives a direction that
    is not orthogonal (NRRD stores it exactly, MetaImage and DICOM cannot).
    """
    lps = LPS_TO_RAS @ np.asarray(affine, dtype=np.float64)
    spacing = np.linalg.norm(lps[:3, :3], axis=0)
    return lps[:3, 3].copy(), spacing, lps[:3, :3] / spacing[None, :]


def image_arrays(image, path: Path, layers: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(voxels [i, j, k], RAS affine) of a 3D scalar SimpleITK image.

    ``layers``: a 3D image with L values per voxel (a layered 3D Slicer segmentation, read by
    ITK as a vector image) is returned as (L, I, J, K).
    """
    size = tuple(int(s) for s in image.GetSize())
    components = image.GetNumberOfComponentsPerPixel()
    if components != 1 and not layers:
        raise DataFileError(path, f"{components} values per voxel "
                                  "(an RGB or vector image), a scalar image is needed")
    dim = image.GetDimension()
    if dim == 4 and size[3] == 1:
        image = image[:, :, :, 0]
    elif dim != 3:
        extra = f", {size[3]} volumes" if dim == 4 else ""
        raise DataFileError(path, f"a 3D image is needed, this one is {dim}D with size "
                                  f"{'x'.join(map(str, size))}{extra}")
    if min(image.GetSize()) < 1:
        raise DataFileError(path, f"image has an empty dimension, size {size}")
    affine = affine_from_itk(image.GetOrigin(), image.GetSpacing(), image.GetDirection())
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise DataFileError(path, "the image geometry (origin, spacing, direction) is not a "
                                  "finite, invertible voxel-to-world mapping")
    array = sitk().GetArrayFromImage(image)  # [k, j, i] or [k, j, i, l]
    data = array.T if array.ndim == 3 else array.transpose(3, 2, 1, 0)  # views, no copy
    if data.dtype.kind == "c":
        raise DataFileError(path, f"unsupported voxel type {data.dtype} (complex)")
    if data.dtype.kind == "b":
        data = data.astype(np.uint8)
    if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
        data = np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0)
    return data, affine


def image_to_volume(image, path: Path) -> Volume:
    """A 3D scalar SimpleITK image as a :class:`Volume` (array [i, j, k], RAS affine)."""
    data, affine = image_arrays(image, path)
    return Volume(data=data, affine=affine, path=path)


def volume_to_image(data: np.ndarray, affine: np.ndarray):
    """A SimpleITK image with the geometry of ``affine`` (RAS) and voxels ``data`` [i, j, k]."""
    origin, spacing, direction = itk_geometry(affine)
    image = sitk().GetImageFromArray(np.ascontiguousarray(np.asarray(data).T))
    image.SetOrigin(tuple(float(v) for v in origin))
    image.SetSpacing(tuple(float(v) for v in spacing))
    image.SetDirection(tuple(float(v) for v in direction.ravel()))
    return image


def sitk_error_text(exc: BaseException, path: Path | None = None) -> str:
    """ITK's exception text reduced to its message line (no C++ file names or line numbers)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    useful = [ln for ln in lines if not ln.startswith(("Exception thrown in SimpleITK", "/"))
              and ".cxx:" not in ln and ".h:" not in ln]
    text = " ".join(useful or lines[-1:]) or type(exc).__name__
    text = re.sub(r"\w+\(0x[0-9a-fA-F]+\):\s*", "", text.replace("ITK ERROR:", "")).strip()
    if path is not None:
        text = without_path(text, path)
    return " ".join(text.split())[:240]


def read_itk_image(path: str | os.PathLike, *, allow_outside: bool = False) -> Volume:
    """Read a 3D NRRD/NHDR or MetaImage (MHA/MHD) file as a RAS :class:`Volume`.

    ``allow_outside``: a detached header (.nhdr, .mhd) may name a data file outside its own
    folder (an absolute or ``..`` path). Off by default: a header found among the user's
    files must not make SSM Studio read, say, ``/etc/passwd`` as voxels; the caller turns it
    on only when the user named that data file.

    Raises
    ------
    DataFileError
        Truncated or corrupt files, a header whose sizes do not match the data, missing
        detached data files or ones outside the header's folder, non-3D, vector or complex
        images, singular geometry.
    """
    from core.io.nrrd import check_nrrd_header

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".nrrd", ".nhdr"):
        check_nrrd_header(path, allow_outside=allow_outside)
    elif suffix in (".mha", ".mhd"):
        check_metaimage_header(path, allow_outside=allow_outside)
    else:
        raise DataFileError(path, f"not an NRRD or MetaImage file name ('{suffix}')")
    return image_to_volume(read_sitk_image(path), path)


def read_sitk_image(path: Path):
    """SimpleITK's image of a file whose header was checked; ITK's errors as one line.

    NRRD data in bzip2 encoding, which SimpleITK's NRRD library is built without, are
    decompressed here (stdlib ``bz2``) into a raw NRRD that ITK then reads.
    """
    from core.io.nrrd import raw_nrrd_copy

    with raw_nrrd_copy(path) as readable:
        reader = sitk().ImageFileReader()
        reader.SetFileName(str(readable))
        try:
            return reader.Execute()
        except RuntimeError as exc:
            raise DataFileError(path, f"cannot read the image data "
                                      f"({sitk_error_text(exc, readable)})") from None


def data_file_outside(header: Path, name: str) -> bool:
    """Whether a detached header's data file name leaves the header's folder: an absolute
    path, or one whose ``..`` parts climb above it (judged on the name, not on links)."""
    if os.path.isabs(name) or re.match(r"^[A-Za-z]:", name) or name.startswith("\\"):
        return True
    normal = os.path.normpath(name.replace("\\", "/"))
    return normal == ".." or normal.startswith("../") or normal.startswith("..\\")


def refuse_outside(header: Path, name: str, allow_outside: bool) -> None:
    """The one-line refusal of a data file outside the header's folder (see read_itk_image)."""
    if not allow_outside and data_file_outside(header, name):
        raise DataFileError(header, f"the header names the data file '{name[:200]}', outside "
                                    "the header's folder: refused (a header may only read "
                                    "data beside it; move the data file next to the header)")


def write_metaimage(path: str | os.PathLike, data: np.ndarray, affine: np.ndarray) -> None:
    """Write a 3D array as a single-file MetaImage (.mha, compressed) with its geometry."""
    path = Path(path)
    if path.suffix.lower() != ".mha":
        raise DataFileError(path, "MetaImage is written as a single .mha file (a .mhd header "
                                  "needs a separate data file)")
    data = np.asarray(data)
    if data.dtype == bool:
        data = data.astype(np.uint8)
    image = volume_to_image(data, affine)
    writer = sitk().ImageFileWriter()
    writer.UseCompressionOn()
    with atomic_path(path) as tmp:
        writer.SetFileName(str(tmp))
        try:
            writer.Execute(image)
        except RuntimeError as exc:
            raise DataFileError(path, f"cannot write ({sitk_error_text(exc, tmp)})") from None


# --------------------------------------------------------------------------------------
# MetaImage header check
# --------------------------------------------------------------------------------------


def _read_text_header(path: Path, limit: int = 65536) -> tuple[bytes, int]:
    """The first bytes of a file (at most ``limit``) and the file size."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        return fh.read(min(size, limit)), size


def check_metaimage_header(path: Path, *, allow_outside: bool = False) -> dict[str, str]:
    """Parse and check a MetaImage header; returns its fields (upper-case keys).

    Checks what ITK would otherwise report with a multi-line exception or read wrongly:
    NDims and DimSize, a known ElementType, the data file exists, and the raw data size
    (or, compressed, the CompressedDataSize) matches what the header announces.
    """
    head, file_size = _read_text_header(path)
    fields: dict[str, str] = {}
    offset = 0
    for raw_line in head.splitlines(keepends=True):
        offset += len(raw_line)
        line = raw_line.decode("latin-1").strip()
        if not line:
            continue
        if "=" not in line:
            raise DataFileError(path, f"not a MetaImage header (line '{line[:40]}' has no '=')")
        key, value = (part.strip() for part in line.split("=", 1))
        fields[key.upper()] = value
        if key.upper() == "ELEMENTDATAFILE":
            break
    else:
        raise DataFileError(path, "not a MetaImage file, or truncated header (no ElementDataFile "
                                  "line)")
    try:
        ndims = int(fields.get("NDIMS", ""))
        dims = [int(v) for v in fields.get("DIMSIZE", "").split()]
    except ValueError:
        raise DataFileError(path, "MetaImage header has a non-integer NDims or DimSize") from None
    if len(dims) != ndims or ndims < 1:
        raise DataFileError(path, f"MetaImage header: NDims = {ndims} but DimSize has "
                                  f"{len(dims)} values")
    if any(d < 1 for d in dims):
        raise DataFileError(path, f"MetaImage header: DimSize {dims} has an empty dimension")
    element = fields.get("ELEMENTTYPE", "").upper()
    if element not in _METAIMAGE_TYPES:
        raise DataFileError(path, f"MetaImage header: unknown ElementType '{element}'")
    channels = int(fields.get("ELEMENTNUMBEROFCHANNELS", "1") or 1)
    expected = int(np.prod(dims, dtype=np.int64)) * _METAIMAGE_TYPES[element] * channels
    data_file = fields["ELEMENTDATAFILE"]
    if data_file.upper() == "LOCAL":
        available = file_size - offset
        where = "after the header"
    elif data_file.upper().startswith("LIST") or "%" in data_file:
        names = data_file.split()[:1] if "%" in data_file else \
            [ln.strip() for ln in head[offset:].decode("latin-1").splitlines() if ln.strip()]
        for name in names:
            refuse_outside(path, name, allow_outside)
        return fields  # a list of slice files: ITK checks those
    else:
        refuse_outside(path, data_file, allow_outside)
        data_path = path.parent / data_file
        if not data_path.is_file():
            raise DataFileError(path, f"the data file '{data_file}' named by the header is missing")
        available = data_path.stat().st_size
        where = f"in '{data_file}'"
    compressed = fields.get("COMPRESSEDDATA", "False").lower() == "true"
    header_skip = int(fields.get("HEADERSIZE", "0") or 0)
    if compressed:
        announced = fields.get("COMPRESSEDDATASIZE")
        if announced is not None and announced.isdigit() and int(announced) > available:
            raise DataFileError(path, f"truncated: the header announces {announced} bytes of "
                                      f"compressed data, the file holds {available} {where}")
        # inflated whole (not kept): a corrupt stream of the announced size is read by ITK
        # as zeros with only a console message ("Uncompress failed")
        if data_file.upper() == "LOCAL":
            _check_zlib_stream(path, path, offset, expected)
        else:
            _check_zlib_stream(path, data_path, 0, expected)
        return fields
    if header_skip >= 0 and available - max(header_skip, 0) < expected:
        raise DataFileError(path, f"truncated or header lying about the size: DimSize "
                                  f"{'x'.join(map(str, dims))} of {element} needs {expected} "
                                  f"bytes, the file holds {available} {where}")
    if data_file.upper() == "LOCAL" and header_skip == 0 and available > expected:
        raise DataFileError(path, f"the header describes {expected} bytes of voxel data but "
                                  f"{available} bytes follow it (wrong DimSize or ElementType?)")
    return fields


def _check_zlib_stream(path: Path, where: Path, offset: int, expected: int) -> None:
    """Inflate the zlib stream of ``where`` from ``offset`` (without keeping it) and compare
    its size with what the header ``path`` describes; the zlib checksum is verified too."""
    inflater = zlib.decompressobj()
    total = 0
    try:
        with open(where, "rb") as fh:
            fh.seek(offset)
            while chunk := fh.read(1 << 20):
                total += len(inflater.decompress(chunk))
                if inflater.eof:
                    break
        total += len(inflater.flush())
    except zlib.error as exc:
        raise DataFileError(path, f"corrupt compressed voxel data ({exc}): the image would be "
                                  "wrong, it is not read") from None
    if not inflater.eof or total < expected:
        raise DataFileError(path, f"truncated compressed voxel data: {total} of {expected} "
                                  "bytes")
    if total > expected:
        raise DataFileError(path, f"the compressed data hold {total} bytes but the header "
                                  f"describes {expected} (wrong DimSize or ElementType?)")


def check_gzip_stream(path: Path, offset: int, expected: int) -> None:
    """Check an embedded gzip stream (NRRD ``encoding: gzip``) holds ``expected`` bytes.

    Fast path: the gzip trailer's ISIZE (uncompressed size mod 2^32, RFC 1952) matches.
    Otherwise the stream is inflated (without keeping it) for a precise message.
    """
    size = path.stat().st_size
    if size - offset >= 18:
        with open(path, "rb") as fh:
            fh.seek(offset)
            magic = fh.read(2)
            fh.seek(size - 4)
            isize = int.from_bytes(fh.read(4), "little")
        if magic == b"\x1f\x8b" and isize == expected % (1 << 32):
            return
    total = 0
    try:
        with open(path, "rb") as raw:
            raw.seek(offset)
            with gzip.GzipFile(fileobj=raw) as fh:
                while chunk := fh.read(1 << 20):
                    total += len(chunk)
    except (EOFError, OSError, zlib.error) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip voxel data ({exc})") from None
    if total != expected:
        raise DataFileError(path, f"the gzip data hold {total} bytes but the header describes "
                                  f"{expected} (header lying about the size?)")


register(FileFormat(".mha", "volume", "MetaImage", read=read_itk_image, write=write_metaimage))
register(FileFormat(".mhd", "volume", "MetaImage header + detached data", read=read_itk_image))
