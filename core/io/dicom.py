"""DICOM image series (a folder of slices, or any one file of it) as a RAS :class:`Volume`.

Series are discovered and read by SimpleITK (GDCM inside): ``GetGDCMSeriesIDs`` lists the
series of a folder, ``GetGDCMSeriesFileNames`` orders a series' files along the slice normal
and ``ImageSeriesReader`` reads them, with each slice's tags kept so that the geometry can
be checked before it is trusted (ITK itself only warns, or stacks the slices wrongly):

- every file has the same ImageOrientationPatient (else: mixed orientations, e.g. a
  localizer in the series);
- consecutive ImagePositionPatient steps are along the slice normal (else: gantry tilt or
  a sheared stack, which ITK's orthogonal grid would place wrongly);
- no two slices share a position (else: a 4D series, several volumes interleaved);
- the steps are uniform (else: missing slices when a gap is a multiple of the spacing,
  otherwise non-uniform spacing);
- one frame per file, an image SOP class (not a structured report, RT structure set,
  presentation state, ...), and a transfer syntax GDCM decodes (read from the file-meta
  group, which is always explicit VR little endian: DICOM PS3.10 section 7.1);
- no impossible tag (:func:`check_image_tags`): PixelSpacing finite and positive (GDCM reads
  NaN or 0 as 1 mm and mirrors a negative one), SliceThickness / SpacingBetweenSlices finite
  and not negative, BitsAllocated 1/8/16/32/64 and at least BitsStored, the same pixel sizes
  in every slice, and a Pixel Data element as long as the tags say
  (:func:`check_pixel_data_size`, e.g. not BitsAllocated 32 over 16-bit data).

A series that is one file holding a whole volume, an enhanced multi-frame image or a Siemens
mosaic, is read by :mod:`core.io.dicom_frames` (its 4D variants refused, saying how many
volumes). DICOMDIR files (a disc's index: PS3.10 8.6, SOP class 1.2.840.10008.1.3.10) are
skipped by name or meta group, without parsing them.

ITK's geometry (LPS origin, spacing, direction) becomes the RAS affine exactly as for the
other ITK formats (:func:`.itk_image.affine_from_itk`). Patient tags (0010,xxxx) are never
read into messages, titles or file names: a series is described by its UID, modality,
SeriesDescription and slice count only.

Reference: DICOM PS3.3 C.7.6.2 (Image Plane Module: position, orientation, spacing).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.errors import DataFileError
from core.io.itk_image import image_to_volume, quiet_native_stderr, sitk, sitk_error_text
from core.io.registry import FileFormat, register
from core.types.volume import Volume

# Transfer syntaxes: name, and whether GDCM (as built into SimpleITK) decodes it.
TRANSFER_SYNTAXES: dict[str, tuple[str, bool]] = {
    "1.2.840.10008.1.2": ("Implicit VR Little Endian", True),
    "1.2.840.10008.1.2.1": ("Explicit VR Little Endian", True),
    "1.2.840.10008.1.2.1.99": ("Deflated Explicit VR Little Endian", True),
    "1.2.840.10008.1.2.2": ("Explicit VR Big Endian", True),
    "1.2.840.10008.1.2.4.50": ("JPEG Baseline", True),
    "1.2.840.10008.1.2.4.51": ("JPEG Extended", True),
    "1.2.840.10008.1.2.4.57": ("JPEG Lossless", True),
    "1.2.840.10008.1.2.4.70": ("JPEG Lossless SV1", True),
    "1.2.840.10008.1.2.4.80": ("JPEG-LS Lossless", True),
    "1.2.840.10008.1.2.4.81": ("JPEG-LS Near-Lossless", True),
    "1.2.840.10008.1.2.4.90": ("JPEG 2000 Lossless", True),
    "1.2.840.10008.1.2.4.91": ("JPEG 2000", True),
    "1.2.840.10008.1.2.5": ("RLE Lossless", True),
    "1.2.840.10008.1.2.4.92": ("JPEG 2000 Part 2 Multi-component Lossless", False),
    "1.2.840.10008.1.2.4.93": ("JPEG 2000 Part 2 Multi-component", False),
    "1.2.840.10008.1.2.4.94": ("JPIP Referenced", False),
    "1.2.840.10008.1.2.4.95": ("JPIP Referenced Deflate", False),
    "1.2.840.10008.1.2.4.100": ("MPEG2 Main Profile", False),
    "1.2.840.10008.1.2.4.101": ("MPEG2 High Profile", False),
    "1.2.840.10008.1.2.4.102": ("MPEG-4 AVC/H.264", False),
    "1.2.840.10008.1.2.4.103": ("MPEG-4 AVC/H.264 BD", False),
    "1.2.840.10008.1.2.4.104": ("MPEG-4 AVC/H.264 2D", False),
    "1.2.840.10008.1.2.4.105": ("MPEG-4 AVC/H.264 3D", False),
    "1.2.840.10008.1.2.4.106": ("MPEG-4 AVC/H.264 Stereo", False),
    "1.2.840.10008.1.2.4.107": ("HEVC/H.265 Main", False),
    "1.2.840.10008.1.2.4.108": ("HEVC/H.265 Main 10", False),
    "1.2.840.10008.1.2.4.110": ("JPEG XL Lossless", False),
    "1.2.840.10008.1.2.4.111": ("JPEG XL JPEG Recompression", False),
    "1.2.840.10008.1.2.4.112": ("JPEG XL", False),
    "1.2.840.10008.1.2.4.201": ("High-Throughput JPEG 2000 Lossless", False),
    "1.2.840.10008.1.2.4.202": ("High-Throughput JPEG 2000 RPCL Lossless", False),
    "1.2.840.10008.1.2.4.203": ("High-Throughput JPEG 2000", False),
}

# SOP classes (or class prefixes) that hold no image volume.
NON_IMAGE_SOP_CLASSES: dict[str, str] = {
    "1.2.840.10008.5.1.4.1.1.88.": "structured report",
    "1.2.840.10008.5.1.4.1.1.11.": "presentation state",
    "1.2.840.10008.5.1.4.1.1.481.3": "RT structure set",
    "1.2.840.10008.5.1.4.1.1.481.5": "RT plan",
    "1.2.840.10008.5.1.4.1.1.481.8": "RT ion plan",
    "1.2.840.10008.5.1.4.1.1.66": "raw data object",
    "1.2.840.10008.5.1.4.1.1.66.": "registration, fiducials, segmentation or surface object",
    "1.2.840.10008.5.1.4.1.1.104.": "encapsulated document (PDF, CDA, STL)",
    "1.2.840.10008.5.1.4.1.1.9.": "waveform",
    "1.2.840.10008.5.1.4.1.1.4.2": "MR spectroscopy",
    "1.2.840.10008.1.3.10": "media storage directory (DICOMDIR)",
}

_POSITION, _ORIENTATION, _FRAMES = "0020|0032", "0020|0037", "0028|0008"


@dataclass
class SeriesInfo:
    """One image series of a folder (no patient information).

    Attributes
    ----------
    uid : str
        SeriesInstanceUID (what ``--series`` takes).
    files : list of Path
        Its files, ordered along the slice normal by GDCM.
    description, modality : str
        SeriesDescription and Modality tags ('' when absent).
    """

    uid: str
    files: list[Path] = field(default_factory=list)
    description: str = ""
    modality: str = ""

    @property
    def n_files(self) -> int:
        return len(self.files)

    def label(self) -> str:
        """A one-line description for messages and the series dialog."""
        what = " ".join(p for p in (self.modality, f"'{self.description}'" if self.description
                                    else "") if p)
        return (f"{self.uid} ({what + ', ' if what else ''}{self.n_files} "
                f"file{'s' if self.n_files != 1 else ''})")


def is_dicom_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a DICOM Part 10 file (the 'DICM' marker after the 128-byte preamble)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def read_file_meta(path: Path) -> dict[str, str]:
    """The string elements of a Part 10 file's meta group (0002): transfer syntax, SOP class."""
    return _meta_if_dicom(path) or {}


def _meta_if_dicom(path: Path) -> dict[str, str] | None:
    """:func:`read_file_meta`, or None when ``path`` is not a Part 10 file (one read)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(8192)
    except OSError:
        return None
    if len(head) < 132 or head[128:132] != b"DICM":
        return None
    out: dict[str, str] = {}
    pos = 132
    while pos + 8 <= len(head):
        group, element = struct.unpack_from("<HH", head, pos)
        if group != 0x0002:
            break
        vr = head[pos + 4:pos + 6]
        if vr in (b"OB", b"OW", b"OF", b"SQ", b"UT", b"UN"):
            if pos + 12 > len(head):
                break
            length, start = struct.unpack_from("<I", head, pos + 8)[0], pos + 12
        else:
            length, start = struct.unpack_from("<H", head, pos + 6)[0], pos + 8
        if vr in (b"UI", b"SH", b"AE", b"CS", b"LO"):
            out[f"{group:04x}|{element:04x}"] = \
                head[start:start + length].rstrip(b"\0 ").decode("ascii", "replace")
        pos = start + length
    return out


MEDIA_DIRECTORY = "1.2.840.10008.1.3.10"  # DICOMDIR's SOP class (PS3.10 7.3, PS3.3 F)


def is_dicomdir(path: Path) -> bool:
    """Whether ``path`` is a media directory (DICOMDIR): an index of the files, no image.

    Told by its name (PS3.10 8.6: the file is named DICOMDIR) or by its meta group's
    MediaStorageSOPClassUID, so only the first bytes of a file are read.
    """
    return path.name.upper() == "DICOMDIR" or \
        read_file_meta(path).get("0002|0002", "") == MEDIA_DIRECTORY


def folder_dicom_files(folder: Path) -> list[Path]:
    """The DICOM files of ``folder`` that may hold images (DICOMDIR files left out)."""
    found = []
    for path in sorted(folder.iterdir()):
        if path.name.upper() == "DICOMDIR" or not path.is_file():
            continue
        meta = _meta_if_dicom(path)
        if meta is not None and meta.get("0002|0002", "") != MEDIA_DIRECTORY:
            found.append(path)
    return found


def _non_image_kind(sop_class: str) -> str | None:
    for prefix, kind in NON_IMAGE_SOP_CLASSES.items():
        if sop_class == prefix.rstrip(".") or (prefix.endswith(".") and sop_class.startswith(prefix)):
            return kind
    return None


def _file_info(path: Path):
    """An ImageFileReader with the header of ``path`` read (raises DataFileError)."""
    reader = sitk().ImageFileReader()
    reader.SetFileName(str(path))
    reader.SetImageIO("GDCMImageIO")
    reader.LoadPrivateTagsOff()
    try:
        with quiet_native_stderr():
            reader.ReadImageInformation()
    except RuntimeError as exc:
        raise DataFileError(path, f"not a readable DICOM image ({sitk_error_text(exc, path)})") \
            from None
    return reader


def _tag(reader, key: str, default: str = "") -> str:
    return reader.GetMetaData(key).strip() if reader.HasMetaDataKey(key) else default


def _check_file_kind(path: Path, where: Path) -> None:
    """Refuse undecodable transfer syntaxes and non-image objects before reading any voxel."""
    meta = read_file_meta(path)
    syntax = meta.get("0002|0010", "")
    name, decodable = TRANSFER_SYNTAXES.get(syntax, (f"unknown transfer syntax {syntax}", True))
    if syntax and not decodable:
        raise DataFileError(where, f"{path.name} is compressed as '{name}' ({syntax}), which "
                                   "GDCM cannot decode; convert the series (e.g. to explicit VR "
                                   "little endian) first")
    kind = _non_image_kind(meta.get("0002|0002", ""))
    if kind:
        raise DataFileError(where, f"{path.name} is a {kind}, not an image slice")


def list_series(folder: str | os.PathLike) -> list[SeriesInfo]:
    """The image series in ``folder`` (not its subfolders), most files first."""
    folder = Path(folder)
    series_reader = sitk().ImageSeriesReader
    try:
        with quiet_native_stderr():
            uids = list(series_reader.GetGDCMSeriesIDs(str(folder)))
            file_lists = {uid: series_reader.GetGDCMSeriesFileNames(str(folder), uid)
                          for uid in uids}
    except RuntimeError as exc:
        raise DataFileError(folder, f"cannot scan for DICOM series ({sitk_error_text(exc)})") \
            from None
    found = []
    for uid in uids:
        files = [Path(f) for f in file_lists[uid]]
        if not files:
            continue
        info = SeriesInfo(uid=uid, files=files)
        meta = read_file_meta(files[0])
        if _non_image_kind(meta.get("0002|0002", "")):
            continue  # SR, RT structures, ...: not an image series
        if not TRANSFER_SYNTAXES.get(meta.get("0002|0010", ""), ("", True))[1]:
            found.append(info)  # reading it explains; GDCM would print codec errors here
            continue
        try:
            reader = _file_info(files[0])
            info.description = " ".join(_tag(reader, "0008|103e").split())
            info.modality = _tag(reader, "0008|0060")
        except DataFileError:
            pass  # described without tags; reading it reports the problem
        found.append(info)
    found.sort(key=lambda s: -s.n_files)
    return found


def _single_series(folder: Path) -> SeriesInfo | None:
    """Fast path for the usual folder, one series: one GDCM scan instead of two.

    GDCM's unnamed-series scan returns the (sorted) files of the first series it finds; when
    that is every DICOM file of the folder there is no other series to choose from.
    """
    dicom_files = folder_dicom_files(folder)
    if not dicom_files:
        return None
    with quiet_native_stderr():
        try:
            files = [Path(f) for f in sitk().ImageSeriesReader.GetGDCMSeriesFileNames(str(folder))]
        except RuntimeError:
            return None
    if len(files) != len(dicom_files):
        return None
    meta = read_file_meta(files[0])
    if _non_image_kind(meta.get("0002|0002", "")) or \
            not TRANSFER_SYNTAXES.get(meta.get("0002|0010", ""), ("", True))[1]:
        return None  # the full path explains these
    try:
        reader = _file_info(files[0])
    except DataFileError:
        return None
    uid = _tag(reader, "0020|000e")
    if not uid:
        return None
    return SeriesInfo(uid=uid, files=files, description=" ".join(_tag(reader, "0008|103e").split()),
                      modality=_tag(reader, "0008|0060"))


def _explain_empty(folder: Path) -> DataFileError:
    """Why a folder has no image series: no DICOM files at all, or only non-image objects."""
    files = [p for p in sorted(folder.iterdir()) if p.is_file()]
    dicom = [p for p in files if is_dicom_file(p)]
    if dicom and all(is_dicomdir(p) for p in dicom):
        return DataFileError(folder, "holds only a DICOMDIR (an index of a disc's files, no "
                                     "image): open the folder of one series it lists")
    if not files:
        return DataFileError(folder, "empty folder: no DICOM files")
    if not dicom:
        return DataFileError(folder, f"no DICOM files among its {len(files)} files (a DICOM "
                                     "folder, or one file of the series, is needed)")
    kinds = sorted({_non_image_kind(read_file_meta(p).get("0002|0002", "")) or "unreadable file"
                    for p in dicom})
    return DataFileError(folder, f"no DICOM image series: its {len(dicom)} DICOM file(s) are "
                                 f"{', '.join(kinds)}")


def choose_series(path: str | os.PathLike, series: str | None = None,
                  notify: Callable[[str], None] | None = None) -> SeriesInfo:
    """The series to read for ``path`` (a folder, or one file of a series).

    ``series`` (a SeriesInstanceUID) selects one of a folder's series; without it the
    series with most files is taken and ``notify`` is told which (and what else is there).
    """
    path = Path(path)
    if path.is_dir():
        if series is None:
            single = _single_series(path)
            if single is not None:
                return single
        candidates = list_series(path)
        if not candidates:
            raise _explain_empty(path)
        if series is not None:
            chosen = [s for s in candidates if s.uid == series]
            if not chosen:
                raise DataFileError(path, f"no series {series}; the folder holds "
                                          + "; ".join(s.label() for s in candidates))
            return chosen[0]
        if len(candidates) > 1 and notify is not None:
            others = "; ".join(s.label() for s in candidates[1:])
            notify(f"{path}: {len(candidates)} series, reading the one with most files: "
                   f"{candidates[0].label()} (others: {others}); choose with --series UID")
        return candidates[0]
    if not is_dicom_file(path):
        raise DataFileError(path, "not a DICOM file (no 'DICM' marker) and not a known image "
                                  "format")
    _check_file_kind(path, path)
    reader = _file_info(path)
    uid = _tag(reader, "0020|000e")
    if not uid:
        raise DataFileError(path, "DICOM file without a SeriesInstanceUID")
    if series is not None and series != uid:
        raise DataFileError(path, f"this file belongs to series {uid}, not {series}")
    with quiet_native_stderr():
        files = [Path(f) for f in sitk().ImageSeriesReader.GetGDCMSeriesFileNames(
            str(path.parent), uid)]
    info = SeriesInfo(uid=uid, files=files or [path],
                      description=" ".join(_tag(reader, "0008|103e").split()),
                      modality=_tag(reader, "0008|0060"))
    return info


def _floats(text: str, count: int) -> np.ndarray | None:
    try:
        values = np.array([float(v) for v in text.replace(",", "\\").split("\\")])
    except ValueError:
        return None
    return values if values.shape == (count,) else None


def _finite_floats(text: str) -> np.ndarray | None:
    """The numbers of a DS/IS tag's text ('a\\b'), None when empty or not numbers (NaN kept)."""
    try:
        values = np.array([float(v) for v in text.replace(",", "\\").split("\\")])
    except ValueError:
        return None
    return values if values.size else None


# (key, name) of the tags checked by check_image_tags; keys as in ITK's metadata dictionary.
PIXEL_SPACING = ("0028|0030", "PixelSpacing (0028,0030)")
SLICE_LENGTHS = (("0018|0050", "SliceThickness (0018,0050)"),
                 ("0018|0088", "SpacingBetweenSlices (0018,0088)"))
PIXEL_SIZES = (("0028|0010", "Rows (0028,0010)"), ("0028|0011", "Columns (0028,0011)"),
               ("0028|0100", "BitsAllocated (0028,0100)"),
               ("0028|0101", "BitsStored (0028,0101)"))


def check_image_tags(tag: Callable[[str], str], name: str, where: Path) -> None:
    """Refuse impossible values of the tags that place voxels or size the pixel data.

    ``tag(key)`` gives a tag's text ('' when absent). GDCM reads a NaN or zero PixelSpacing
    as 1 mm and a negative one as a mirrored axis, and sizes the pixel data from
    BitsAllocated whatever the data holds, so these are checked first (PS3.3 C.7.6.2.1.1:
    spacing in mm, "physical distance", so positive; C.7.6.3: BitsStored <= BitsAllocated).
    """
    key, label = PIXEL_SPACING
    text = tag(key)
    if text:
        values = _finite_floats(text)
        if values is None or values.size != 2 or not np.all(np.isfinite(values)) \
                or np.any(values <= 0):
            raise DataFileError(where, f"{name}: {label} is '{text}', not two finite, positive "
                                       "distances in mm (a pixel's height and width)")
    for key, label in SLICE_LENGTHS:
        text = tag(key)
        values = _finite_floats(text) if text else np.zeros(1)
        if values is None or values.size != 1 or not np.isfinite(values[0]) or values[0] < 0:
            raise DataFileError(where, f"{name}: {label} is '{text}', not a finite, "
                                       "non-negative distance in mm")
    sizes = {}
    for key, label in PIXEL_SIZES:
        text = tag(key)
        if text:
            if not text.isdigit() or int(text) < 1:
                raise DataFileError(where, f"{name}: {label} is '{text}', not a positive integer")
            sizes[key] = int(text)
    bits, stored = sizes.get("0028|0100"), sizes.get("0028|0101")
    if bits is not None and bits not in (1, 8, 16, 32, 64):
        raise DataFileError(where, f"{name}: BitsAllocated (0028,0100) is {bits}, not 1, 8, "
                                   "16, 32 or 64")
    if bits is not None and stored is not None and stored > bits:
        raise DataFileError(where, f"{name}: BitsStored (0028,0101) is {stored}, more than "
                                   f"BitsAllocated (0028,0100) {bits}")


NATIVE_SYNTAXES = {"1.2.840.10008.1.2": "<", "1.2.840.10008.1.2.1": "<",
                   "1.2.840.10008.1.2.2": ">"}


def pixel_data_length(path: Path, syntax: str) -> int | None:
    """The byte length of the Pixel Data element (7FE0,0010) of a native (uncompressed) file.

    Found without a DICOM parser: the element that ends exactly at the end of the file (or
    before trailing padding) is the pixel data; None when that cannot be told (encapsulated
    data, another element last). Implicit VR: tag, 4-byte length; explicit VR: tag, 'OB'/'OW',
    2 reserved bytes, 4-byte length (PS3.5 7.1.2).
    """
    order = NATIVE_SYNTAXES.get(syntax)
    if order is None:
        return None
    data = path.read_bytes()
    tag = struct.pack(order + "HH", 0x7FE0, 0x0010)
    end = len(data)
    implicit = syntax == "1.2.840.10008.1.2"
    for _ in range(8):  # the tag's bytes may also occur inside the data: try the last few
        at = data.rfind(tag, 0, end)
        if at < 0:
            return None
        if implicit:
            head, vr_ok = 8, True
        else:
            head, vr_ok = 12, data[at + 4:at + 6] in (b"OB", b"OW")
        if vr_ok and at + head <= len(data):
            length = struct.unpack_from(order + "I", data, at + head - 4)[0]
            if length != 0xFFFFFFFF and 0 <= len(data) - (at + head + length) < 256:
                return length
        end = at
    return None


def check_pixel_data_size(path: Path, syntax: str, rows: int, cols: int, frames: int,
                          samples: int, bits: int, where: Path, length: int | None = None) -> None:
    """Refuse a native file whose Pixel Data length disagrees with the size the tags give
    (e.g. BitsAllocated 32 over 16-bit data, which GDCM would read as garbage voxels).

    ``length``: the element's length when known (pydicom), else found in the file."""
    if length is None:
        length = pixel_data_length(path, syntax)
    if length is None:
        return
    expected = (rows * cols * frames * samples * bits + 7) // 8
    if length not in (expected, expected + 1):  # + 1: padding to an even length
        raise DataFileError(where, f"{path.name}: the Pixel Data (7FE0,0010) holds {length} "
                                   f"bytes but Rows x Columns x frames x samples x "
                                   f"BitsAllocated/8 = {rows} x {cols} x {frames} x {samples} x "
                                   f"{bits}/8 = {expected} bytes: inconsistent pixel data size")


def _diagnose_read_failure(series: SeriesInfo, where: Path, exc: BaseException) -> DataFileError:
    """Find the slice file that stops ITK from reading the series (error path only)."""
    sizes = {}
    for path in series.files:
        try:
            _check_file_kind(path, where)
            reader = _file_info(path)
            check_image_tags(lambda key: _tag(reader, key), path.name, where)
            sizes[path] = (_tag(reader, "0028|0010"), _tag(reader, "0028|0011"))
            with quiet_native_stderr():
                reader.Execute()
        except DataFileError as err:
            if err.problem.startswith(f"{path.name}: "):  # an impossible tag, named
                return err
            return DataFileError(where, f"slice file {path.name} is corrupt or truncated "
                                        f"({err.problem})")
        except RuntimeError as err:
            return DataFileError(where, f"slice file {path.name} is corrupt or truncated "
                                        f"({sitk_error_text(err, path)})")
    if len(set(sizes.values())) > 1:
        return DataFileError(where, f"the slices have different sizes (rows x columns: "
                                    f"{', '.join(sorted({'x'.join(v) for v in sizes.values()}))})")
    return DataFileError(where, f"cannot read the series ({sitk_error_text(exc)})")


def _with_unparsable_files(exc: DataFileError, files: list[Path], where: Path) -> DataFileError:
    """Name the slice files GDCM skipped as unreadable when the series looks incomplete.

    GDCM's folder scan silently leaves out a DICOM file it cannot parse (truncated or
    corrupt), so the first symptom is a gap in the series; say which file caused it.
    """
    folder = where if where.is_dir() else where.parent
    listed = {f.resolve() for f in files}
    bad = []
    for path in folder_dicom_files(folder):
        if path.resolve() not in listed:
            try:
                _file_info(path)
            except DataFileError as err:
                bad.append((path, err.problem))
    if not bad:
        return exc
    names = ", ".join(p.name for p, _ in bad[:3]) + (" ..." if len(bad) > 3 else "")
    return DataFileError(where, f"{len(bad)} slice file(s) corrupt or truncated ({names}: "
                                f"{bad[0][1]}), so the series is incomplete: {exc.problem}")


def _check_geometry(positions: np.ndarray, orientations: np.ndarray, names: list[str],
                    where: Path, unit: str = "files", tilt: str = "") -> np.ndarray | None:
    """The checks of the module docstring on the slices' positions and orientations.

    ``names`` name the slices in messages (file names, or "frame 7" in one file; ``unit``
    says which); ``tilt`` is the GantryDetectorTilt tag's text ('' when absent). Returns
    None when the slices are in slice order, else the order that sorts them.
    """
    n = len(names)
    mixed = np.any(np.abs(orientations - orientations[0]) > 1e-4, axis=1)
    if mixed.any():
        raise DataFileError(where, f"mixed slice orientations: {int(mixed.sum())} of {n} {unit} "
                                   f"(e.g. {names[int(np.argmax(mixed))]}) have another "
                                   "ImageOrientationPatient than the first")
    row, col = orientations[0, :3], orientations[0, 3:]
    normal = np.cross(row, col)
    if not np.isclose(np.linalg.norm(normal), 1.0, atol=1e-3):
        raise DataFileError(where, "ImageOrientationPatient is not two orthogonal unit vectors")
    depth = positions @ normal
    order = np.argsort(depth, kind="stable")
    n_positions = int(np.sum(np.diff(depth[order]) > 1e-3)) + 1
    if n_positions < n:
        raise DataFileError(where, f"a 4D series: {n} images at {n_positions} slice positions "
                                   f"(about {n // max(n_positions, 1)} volumes: time points, "
                                   "echoes or diffusion directions); split it into 3D series")
    sorted_already = bool(np.all(np.diff(depth) > 0))
    steps = np.diff(positions[order], axis=0)
    along = steps @ normal
    across = np.linalg.norm(steps - along[:, None] * normal, axis=1)
    names = [names[i] for i in order]
    tilted = across > 1e-3 + 1e-3 * np.abs(along)
    if tilted.any():
        k = int(np.argmax(across))
        angle = np.degrees(np.arctan2(across[k], abs(along[k])))
        tilt_tag = _finite_floats(tilt)
        if tilt_tag is not None and tilt_tag.size == 1 and abs(tilt_tag[0]) > 1e-3:
            raise DataFileError(where, f"gantry tilt of {tilt_tag[0]:g} degrees "
                                       "(GantryDetectorTilt): the slice positions step "
                                       f"{angle:.2f} degrees off the slice normal, a sheared "
                                       "grid; resample the series to an orthogonal grid first "
                                       "(e.g. dcm2niix's tilt correction)")
        raise DataFileError(where, f"gantry tilt or sheared slice stack: the slice positions "
                                   f"step {angle:.2f} degrees off the slice normal; resample "
                                   "the series to an orthogonal grid first")
    gaps = np.abs(along)
    spacing = float(np.median(gaps))
    off = np.abs(gaps - spacing) > 1e-3 + 1e-3 * spacing
    if off.any():
        ratios = gaps[off] / spacing
        if np.all(np.abs(ratios - np.rint(ratios)) < 0.02) and np.all(np.rint(ratios) >= 2):
            k = int(np.flatnonzero(off)[0])
            missing = int(np.sum(np.rint(ratios) - 1))
            raise DataFileError(where, f"{missing} slice(s) missing: a gap of {gaps[k]:.4g} mm "
                                       f"after {names[k]} where the slice spacing is "
                                       f"{spacing:.4g} mm")
        raise DataFileError(where, f"non-uniform slice spacing: steps from {gaps.min():.4g} to "
                                   f"{gaps.max():.4g} mm (median {spacing:.4g} mm)")
    return None if sorted_already else order


def read_dicom(path: str | os.PathLike, series: str | None = None,
               notify: Callable[[str], None] | None = None) -> Volume:
    """Read a DICOM series (``path``: a folder, or one file of the series) as a RAS volume.

    A series of one-slice files is read by ITK; one enhanced multi-frame file or one
    Siemens mosaic by :mod:`core.io.dicom_frames`. When a folder's series with most files
    was taken and cannot be read, the error names it, the folder's other readable series
    and ``--series``.

    Raises
    ------
    DataFileError
        Naming the folder (or file) and the problem: no series, unknown ``series`` UID,
        undecodable transfer syntax, non-image object, 4D data, impossible geometry or
        pixel tags, mixed orientations, gantry tilt, missing slices, non-uniform spacing,
        a corrupt slice.
    """
    path = Path(path)
    info = choose_series(path, series, notify)
    try:
        return _read_series(info, path)
    except DataFileError as exc:
        if path.is_dir() and series is None:
            raise with_other_series(exc, path, info) from None
        raise


def with_other_series(exc: DataFileError, folder: Path, chosen: SeriesInfo,
                       most: int = 6) -> DataFileError:
    """``exc`` about the series taken by default, with the folder's other readable series
    (each tried, up to ``most``: this is the error path) and how to pick one."""
    others = [s for s in list_series(folder) if s.uid != chosen.uid]
    if not others:
        return exc
    readable = []
    for other in others[:most]:
        try:
            _read_series(other, folder)
        except DataFileError:
            continue
        readable.append(other)
    if readable:
        also = (f"; other readable series: {'; '.join(s.label() for s in readable)}; choose "
                f"one with --series UID")
    else:
        also = (f"; none of the folder's {len(others)} other series"
                f"{'' if len(others) <= most else f' (first {most} tried)'} can be read either")
    return DataFileError(folder, f"series {chosen.label()} (taken as the one with most files) "
                                 f"cannot be read: {exc.problem}{also}")


def _itk_tag(reader, index: int) -> Callable[[str], str]:
    """Tag text getter of slice ``index`` of an ImageSeriesReader that kept the metadata."""
    keys = set(reader.GetMetaDataKeys(index))
    return lambda key: reader.GetMetaData(index, key).strip() if key in keys else ""


CHECKED_KEYS = tuple(key for key, _ in (PIXEL_SPACING, *SLICE_LENGTHS, *PIXEL_SIZES))


def _read_one_file_volume(info: SeriesInfo, where: Path, mosaic: bool,
                          frames: str) -> Volume:
    """A series whose one file holds the volume: an enhanced multi-frame file or a mosaic."""
    from core.io import dicom_frames

    files = info.files
    if len(files) > 1 and mosaic:
        raise DataFileError(where, f"series {info.uid} is a 4D mosaic series: {len(files)} "
                                   "Siemens mosaic files, one volume each (time points or "
                                   "diffusion directions); split it into 3D volumes first "
                                   "(e.g. dcm2niix)")
    if len(files) > 1 and where.is_dir():
        raise DataFileError(where, f"series {info.uid} has {len(files)} enhanced multi-frame "
                                   f"files (e.g. {files[0].name}, {frames} frames): open one "
                                   "of them")
    one = where if where.is_file() else files[0]
    if mosaic:
        return dicom_frames.read_mosaic(one, where)
    return dicom_frames.read_enhanced(one, where)


def _slice_geometry(reader, files: list[Path], first, where: Path) -> tuple[np.ndarray,
                                                                            np.ndarray]:
    """Every slice's position and orientation (N, 3), (N, 6), its tags checked on the way."""
    positions, orientations = [], []
    first_texts = tuple(_tag(first, key) for key in CHECKED_KEYS)
    for index, file in enumerate(files):
        tag = _itk_tag(reader, index)
        frames = tag(_FRAMES) or "1"
        if frames.isdigit() and int(frames) > 1:
            raise DataFileError(where, f"{file.name} is a multi-frame image ({frames} "
                                       "frames) in a series of one-slice files")
        texts = tuple(tag(key) for key in CHECKED_KEYS)
        if texts != first_texts:  # the first file's were checked; most series repeat them
            check_image_tags(tag, file.name, where)
        for key, label in PIXEL_SIZES[:3]:
            if tag(key) and tag(key) != _tag(first, key):
                raise DataFileError(where, f"{file.name}: {label} is {tag(key)} where "
                                           f"{files[0].name} has {_tag(first, key)}: "
                                           "inconsistent pixel data sizes")
        pos = _floats(tag(_POSITION), 3) if tag(_POSITION) else None
        ori = _floats(tag(_ORIENTATION), 6) if tag(_ORIENTATION) else None
        if pos is None or ori is None or not (np.all(np.isfinite(pos))
                                              and np.all(np.isfinite(ori))):
            raise DataFileError(where, f"{file.name} lacks a valid ImagePositionPatient or "
                                       "ImageOrientationPatient: the slice geometry is unknown")
        positions.append(pos)
        orientations.append(ori)
    return np.array(positions), np.array(orientations)


def _read_series(info: SeriesInfo, where: Path) -> Volume:
    """Read the series ``info`` (errors name ``where``, the path the user gave)."""
    files = info.files
    _check_file_kind(files[0], where)
    first = _file_info(files[0])
    frames = _tag(first, _FRAMES, "1")
    multi_frame = frames.isdigit() and int(frames) > 1
    if multi_frame or "MOSAIC" in _tag(first, "0008|0008").upper().split("\\"):
        return _read_one_file_volume(info, where, mosaic=not multi_frame, frames=frames)
    check_image_tags(lambda key: _tag(first, key), files[0].name, where)
    if len(files) < 2:
        raise DataFileError(where, f"series {info.uid} has a single slice: a 3D image needs "
                                   "at least two")
    syntax = read_file_meta(files[0]).get("0002|0010", "")
    sizes = [int(_tag(first, key) or 0) for key in ("0028|0010", "0028|0011", "0028|0100")]
    samples = _tag(first, "0028|0002", "1")
    if all(sizes):
        check_pixel_data_size(files[0], syntax, sizes[0], sizes[1], 1,
                              int(samples) if samples.isdigit() else 1, sizes[2], where)
    reader = sitk().ImageSeriesReader()
    reader.SetFileNames([str(f) for f in files])
    reader.MetaDataDictionaryArrayUpdateOn()
    reader.LoadPrivateTagsOff()
    try:
        with quiet_native_stderr():
            image = reader.Execute()
    except RuntimeError as exc:
        raise _diagnose_read_failure(info, where, exc) from None
    positions_arr, orientations_arr = _slice_geometry(reader, files, first, where)
    try:
        order = _check_geometry(positions_arr, orientations_arr, [f.name for f in files], where,
                                tilt=_tag(first, "0018|1120"))
    except DataFileError as exc:
        raise _with_unparsable_files(exc, files, where) from None
    if order is not None:  # GDCM could not sort (e.g. ties it broke by name): read in order
        files = [files[i] for i in order]
        reader.SetFileNames([str(f) for f in files])
        image = reader.Execute()
        positions_arr = positions_arr[order]
    del reader  # the image's buffer is then ours alone: no copy when it becomes an array
    volume = image_to_volume(image, where)
    # ITK's grid must be the one the tags describe (origin at the first slice, z step = gap).
    normal = np.cross(orientations_arr[0, :3], orientations_arr[0, 3:])
    gap = float(np.median(np.abs(np.diff(positions_arr, axis=0) @ normal)))
    origin_ras = positions_arr[0] * np.array([-1.0, -1.0, 1.0])
    if not (np.allclose(volume.affine[:3, 3], origin_ras, atol=1e-3)
            and np.isclose(volume.spacing[2], gap, rtol=1e-3, atol=1e-4)):
        raise DataFileError(where, "ITK's slice stacking disagrees with the slice positions "
                                   "(origin or slice spacing): the geometry cannot be trusted")
    return volume


register(FileFormat(".dcm", "volume", "DICOM series (a folder, or one file of it)",
                    read=read_dicom))
