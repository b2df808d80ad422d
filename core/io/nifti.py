"""NIfTI-1 and NIfTI-2 volumes (.nii, .nii.gz) through nibabel.

Kept with nibabel's best voxel->world affine (sform if set, else qform; RAS, mm), oblique
affines included, and with both orientation records (:class:`NiftiOrientation`) so that a
label map written on the image's grid gets the image's own sform, qform and codes. The
header is checked by us first so that truncated, non-NIfTI, .hdr/.img pair and CIFTI files
get precise errors, and the data size it declares is checked against the file size and the
memory before anything is allocated. A .nii.gz is decompressed once, by us, to its end, so
that a damaged deflate stream is caught by the gzip CRC instead of yielding wrong voxels.
"""

from __future__ import annotations

import contextlib
import gzip
import logging
import os
import zlib
from collections.abc import Iterator
from math import prod
from pathlib import Path

import numpy as np

from core.errors import DataFileError, require_file, why
from core.io.atomic import atomic_path
from core.io.limits import DEFLATE_MAX_RATIO, check_declared_size
from core.io.registry import FileFormat, file_suffix, register
from core.types.volume import NiftiOrientation, Volume

VOLUME_SUFFIXES = (".nii", ".nii.gz")

_NIFTI1_HEADER_SIZE = 348
_NIFTI2_HEADER_SIZE = 540


def _read_head(path: Path, n_bytes: int) -> bytes:
    """The first ``n_bytes`` of a file, decompressed when its name ends in .gz."""
    if path.name.lower().endswith(".gz"):
        try:
            with gzip.open(path, "rb") as fh:
                return fh.read(n_bytes)
        except gzip.BadGzipFile:
            raise DataFileError(path, "not gzip-compressed data although the name ends in "
                                      ".gz") from None
        except (EOFError, zlib.error) as exc:
            raise DataFileError(path, f"truncated or corrupt gzip data ({exc})") from None
    with open(path, "rb") as fh:
        return fh.read(n_bytes)


def _check_data_size(path: Path, image_class, head: bytes) -> int:
    """The bytes header + voxel data take, after checking them against file and memory."""
    import io as _bytes_io

    try:
        header = image_class.header_class.from_fileobj(_bytes_io.BytesIO(head), check=False)
        shape = [int(s) for s in header.get_data_shape()]
        itemsize = int(header.get_data_dtype().itemsize)
        offset = int(header.get_data_offset())
    except Exception as exc:  # nibabel raises many types for bad headers
        raise DataFileError(path, f"invalid NIfTI header ({type(exc).__name__}: "
                                  f"{why(exc, path)})") from None
    if any(s < 0 for s in shape):
        raise DataFileError(path, f"invalid NIfTI header (negative dimension in {tuple(shape)})")
    n_bytes = prod(shape) * itemsize
    what = f"{'x'.join(map(str, shape))} voxels"
    size = path.stat().st_size
    if path.name.lower().endswith(".gz"):
        check_declared_size(path, n_bytes, what, max_ratio=DEFLATE_MAX_RATIO)
    else:
        check_declared_size(path, n_bytes, what, stored=max(size - offset, 0),
                            truncated="image data are truncated or corrupt")
    _check_voxel_size(path, header)
    return offset + n_bytes


def _check_voxel_size(path: Path, header) -> None:
    """Refuse a zero or non-finite voxel size (pixdim[1..3]) when the geometry comes from it.

    The qform (and the fallback without any orientation) takes the voxel sizes from pixdim;
    nibabel replaces a 0 by 1 mm after a console warning, placing the image at a scale that
    no file records. An sform holds its own scale, so there pixdim does not matter (nibabel
    then warns for nothing: its warning is silenced in :func:`load_nifti`).
    """
    pixdim = np.asarray(header["pixdim"][1:4], dtype=np.float64)
    if int(header["sform_code"]) > 0 or (np.all(np.isfinite(pixdim)) and np.all(pixdim != 0)):
        return
    source = "the qform" if int(header["qform_code"]) > 0 else "no sform or qform (fallback)"
    shown = " ".join(f"{v:g}" for v in pixdim)
    raise DataFileError(path, f"voxel size pixdim[1..3] = {shown} and the geometry comes from "
                              f"{source}, which scales by it: the voxel size is unknown "
                              "(refused rather than assumed 1 mm)")


def _gunzip_checked(path: Path, keep: int) -> bytes:
    """The first ``keep`` decompressed bytes; the rest is decompressed and discarded so
    that the CRC and length at the end of the gzip stream are verified."""
    try:
        with gzip.open(path, "rb") as fh:
            data = fh.read(keep)
            while fh.read(1 << 22):
                pass
    except gzip.BadGzipFile as exc:
        raise DataFileError(path, f"corrupt gzip data ({why(exc, path)}): the image would "
                                  "be wrong, it is not read") from None
    except (EOFError, zlib.error) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip data ({why(exc, path)})") from None
    return data


def _nifti_class(path: Path):
    """Which nibabel class reads ``path``: checks the header size field and the magic string.

    Deciding this ourselves (instead of ``nibabel.load`` guessing) gives precise errors for
    truncated, non-NIfTI, .hdr/.img pair and CIFTI files.
    """
    import nibabel as nib

    head = _read_head(path, _NIFTI2_HEADER_SIZE)
    if len(head) < 4:
        raise DataFileError(path, f"truncated NIfTI header ({len(head)} bytes)")
    sizes = {int(np.frombuffer(head[:4], dtype=order + "i4")[0]) for order in "<>"}
    if _NIFTI1_HEADER_SIZE in sizes:
        if len(head) < _NIFTI1_HEADER_SIZE:
            raise DataFileError(path, f"truncated NIfTI header ({len(head)} of "
                                      f"{_NIFTI1_HEADER_SIZE} bytes)")
        magic = head[344:348]
        if magic == b"ni1\x00":
            raise DataFileError(path, "header of a NIfTI .hdr/.img pair, not a single-file .nii")
        if magic != b"n+1\x00":
            raise DataFileError(path, "not a NIfTI file (an Analyze-style header without the "
                                      "NIfTI magic string)")
        return nib.Nifti1Image
    if _NIFTI2_HEADER_SIZE in sizes:
        if len(head) < _NIFTI2_HEADER_SIZE:
            raise DataFileError(path, f"truncated NIfTI header ({len(head)} of "
                                      f"{_NIFTI2_HEADER_SIZE} bytes)")
        if head[4:8] == b"ni2\x00":
            raise DataFileError(path, "header of a NIfTI .hdr/.img pair, not a single-file .nii")
        if head[4:8] != b"n+2\x00":
            raise DataFileError(path, "not a NIfTI file (NIfTI-2 header size but no magic string)")
        return nib.Nifti2Image
    size = int(np.frombuffer(head[:4], dtype="<i4")[0])
    raise DataFileError(path, f"not a NIfTI file (header size field is {size}, expected "
                              f"{_NIFTI1_HEADER_SIZE} for NIfTI-1 or {_NIFTI2_HEADER_SIZE} for "
                              "NIfTI-2)")


@contextlib.contextmanager
def _nibabel_header_checks_quiet() -> Iterator[None]:
    """nibabel's header checks log fixes ("pixdim[1,2,3] should be non-zero; setting 0 dims
    to 1") straight to stderr through its ``nibabel.global`` logger; the ones that matter
    are refused by our own checks first, so its console reports are held back here."""
    logger = logging.getLogger("nibabel.global")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


def load_nifti(path: str | os.PathLike) -> Volume:
    """Read a 3D NIfTI-1 or NIfTI-2 image (.nii or .nii.gz).

    The affine is nibabel's best affine (sform when its code is set, else qform, else the
    voxel-size-only fallback), so oblique acquisitions keep their orientation. Trailing
    singleton dimensions (a 4D image with one volume) are dropped; any other 2D, 4D or
    higher-dimensional image is refused. Intensity scaling (scl_slope/scl_inter) is applied;
    the array is returned in native byte order; NaN/inf voxels are replaced by 0.

    Raises
    ------
    DataFileError
        Not found, empty, truncated or corrupt gzip, not a NIfTI file, .hdr/.img pair, CIFTI,
        wrong dimensionality, unsupported voxel type, non-finite or singular affine.
    """

    path = require_file(path)
    if file_suffix(path) not in VOLUME_SUFFIXES:
        raise DataFileError(path, f"not a NIfTI file name (expected .nii or .nii.gz, got "
                                  f"'{file_suffix(path) or path.name}')")
    image_class = _nifti_class(path)
    needed = _check_data_size(path, image_class, _read_head(path, _NIFTI2_HEADER_SIZE))
    try:
        with _nibabel_header_checks_quiet():  # what they report is checked above
            if path.name.lower().endswith(".gz"):
                img = image_class.from_bytes(_gunzip_checked(path, needed))
            else:
                img = image_class.from_filename(str(path))
    except DataFileError:
        raise
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip data ({why(exc, path)})") from None
    except Exception as exc:  # nibabel raises many types for bad headers
        raise DataFileError(path, f"invalid NIfTI header ({type(exc).__name__}: "
                                  f"{why(exc, path)})") from None
    intent_code = int(img.header["intent_code"])
    if 3000 <= intent_code < 3100:  # NIFTI_INTENT_CONNECTIVITY_* codes, used by CIFTI-2
        raise DataFileError(path, f"a CIFTI file (intent {img.header.get_intent()[0]}), "
                                  "not a volume")
    full_shape = tuple(int(s) for s in img.shape)
    shape = full_shape
    while len(shape) > 3 and shape[-1] == 1:
        shape = shape[:-1]
    if len(shape) != 3:
        extra = f", {full_shape[3]} volumes" if len(full_shape) == 4 else ""
        raise DataFileError(path, f"a 3D image is needed, this one is {len(full_shape)}D with "
                                  f"shape {full_shape}{extra}")
    if min(shape) < 1:
        raise DataFileError(path, f"image has an empty dimension, shape {full_shape}")
    affine = np.asarray(img.affine, dtype=np.float64)
    if not np.all(np.isfinite(affine)):
        raise DataFileError(path, "the voxel-to-world affine (sform/qform) has NaN or infinite "
                                  "entries")
    if abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise DataFileError(path, "the voxel-to-world affine (sform/qform) is singular "
                                  "(zero voxel size?)")
    dtype = img.get_data_dtype()
    if dtype.kind not in "iufb":
        raise DataFileError(path, f"unsupported voxel type {dtype} (RGB or complex images "
                                  "cannot be segmented)")
    proxy = img.dataobj
    scaled = getattr(proxy, "slope", 1.0) != 1.0 or getattr(proxy, "inter", 0.0) != 0.0
    try:
        # scl_slope / scl_inter applied when set (as float32: half of nibabel's float64)
        data = img.get_fdata(dtype=np.float32) if scaled else np.asanyarray(proxy)
    except (EOFError, zlib.error, gzip.BadGzipFile) as exc:
        raise DataFileError(path, f"truncated or corrupt gzip data ({why(exc, path)})") from None
    except (OSError, ValueError) as exc:
        raise DataFileError(path, f"image data are truncated or corrupt ({why(exc, path)})") \
            from None
    data = data.reshape(shape)
    if data.dtype.kind == "b":
        data = data.astype(np.uint8)
    if not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="))
    if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
        data = np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0)
    header = img.header
    sform, sform_code = header.get_sform(coded=True)
    qform, qform_code = header.get_qform(coded=True)
    orientation = NiftiOrientation(
        sform=np.asarray(header.get_sform(), np.float64), sform_code=int(sform_code),
        qform=np.asarray(header.get_qform(), np.float64), qform_code=int(qform_code),
        pixdim=np.asarray(header["pixdim"][:4], np.float64))
    return Volume(data=data, affine=affine, path=path, orientation=orientation)


def save_nifti(path: str | os.PathLike, data: np.ndarray, affine: np.ndarray, *,
               like: Volume | None = None) -> None:
    """Write a 3D array as NIfTI-1 with ``affine`` as sform and qform (code 1, scanner).

    The sform keeps the affine exactly (to float32 precision); the qform holds its nearest
    rotation (a qform cannot store shear). Booleans are written as uint8, 64-bit integers as
    int32 when their range allows it (many tools cannot read 64-bit NIfTI), else float64.

    ``like``: the image this array lies on (a label map of it). When it came from a NIfTI
    file on the same grid, its own sform, qform and codes are written instead, so that every
    viewer (ITK reads the qform where nibabel reads the sform) puts the two in one place.
    """
    import nibabel as nib

    path = Path(path)
    if file_suffix(path) not in VOLUME_SUFFIXES:
        raise DataFileError(path, "volumes are written as .nii or .nii.gz")
    data = np.asarray(data)
    if data.ndim != 3:
        raise DataFileError(path, f"a 3D array is needed, got shape {data.shape}")
    affine = np.asarray(affine, dtype=np.float64)
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)) or \
            abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise DataFileError(path, "the affine must be a finite, invertible 4x4 matrix")
    if data.dtype == bool:
        data = data.astype(np.uint8)
    elif data.dtype.kind in "iu" and data.dtype.itemsize == 8:
        info = np.iinfo(np.int32)
        fits = data.size == 0 or (data.min() >= info.min and data.max() <= info.max)
        data = data.astype(np.int32 if fits else np.float64)
    img = nib.Nifti1Image(data, affine)
    orientation = _orientation_of(like, data.shape, affine)
    if orientation is None:
        img.set_sform(affine, code=1)
        img.set_qform(affine, code=1)
    else:
        img.set_qform(orientation.qform, code=orientation.qform_code)
        img.set_sform(orientation.sform, code=orientation.sform_code)
        img.header["pixdim"][:4] = orientation.pixdim
    with atomic_path(path) as tmp:
        nib.save(img, str(tmp))


def _orientation_of(like: Volume | None, shape: tuple, affine: np.ndarray
                    ) -> NiftiOrientation | None:
    """``like``'s NIfTI records if ``like`` is on the grid being written, else None."""
    if like is None or like.orientation is None or tuple(like.shape) != tuple(shape):
        return None
    if not np.allclose(like.affine, affine, atol=1e-6, rtol=1e-7):
        return None
    return like.orientation


for _suffix in VOLUME_SUFFIXES:
    register(FileFormat(_suffix, "volume", "NIfTI image", read=load_nifti, write=save_nifti))
